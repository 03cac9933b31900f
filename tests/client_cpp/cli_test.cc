// mll_cli against the real mll_server: every command, its JSON output, and
// its exit codes (1 with the server's code and message, 2 for usage errors).
#include <algorithm>
#include <fstream>
#include <memory>
#include <regex>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "cli_runner.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using ::testing::StartsWith;

class CliTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH);
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = server->release();
  }
  static void TearDownTestSuite() {
    delete server_;
    server_ = nullptr;
  }

  // mll_cli <args> --address=<the server>.
  static CommandResult Cli(std::vector<std::string> args) {
    args.push_back(absl::StrCat("--address=", server_->address()));
    return RunCli(std::move(args));
  }

  // Creates an env and returns its name, from create's JSON.
  static std::string CreateEnv(std::vector<std::string> flags) {
    flags.insert(flags.begin(), "create");
    const CommandResult created = Cli(flags);
    EXPECT_EQ(created.exit_code, 0) << created.err;
    const std::string name = EnvNameIn(created.out);
    EXPECT_FALSE(name.empty()) << created.out;
    return name;
  }

  static inline ServerProcess* server_ = nullptr;
};

TEST_F(CliTest, Health) {
  const CommandResult result = Cli({"health"});
  EXPECT_EQ(result.exit_code, 0) << result.err;
  EXPECT_THAT(result.out, HasSubstr("SERVING"));
}

TEST_F(CliTest, CreateGetListResetStepRenderDelete) {
  const std::string name =
      CreateEnv({"--n_landers=2", "--render_mode=rgb_array", "--gravity=-9"});
  ASSERT_THAT(name, StartsWith("envs/"));

  CommandResult got = Cli({"get", name});
  EXPECT_EQ(got.exit_code, 0) << got.err;
  EXPECT_THAT(got.out, HasSubstr("\"n_landers\":2"));
  EXPECT_THAT(got.out, HasSubstr("\"gravity\":-9"));
  got = Cli({"get", "--name=" + name});  // The name as a flag works too.
  EXPECT_EQ(got.exit_code, 0) << got.err;

  const CommandResult listed = Cli({"list"});
  EXPECT_EQ(listed.exit_code, 0) << listed.err;
  EXPECT_THAT(listed.out, HasSubstr(name));

  const CommandResult reset = Cli({"reset", name, "--seed=3"});
  EXPECT_EQ(reset.exit_code, 0) << reset.err;
  EXPECT_THAT(reset.out, HasSubstr("\"observations\":{\"lander_0\":["));
  EXPECT_THAT(reset.out, HasSubstr("\"seed\":3"));

  const CommandResult step = Cli({"step", name, "--actions=2,0"});
  EXPECT_EQ(step.exit_code, 0) << step.err;
  EXPECT_THAT(step.out, HasSubstr("\"cycles\":1"));
  EXPECT_THAT(step.out, HasSubstr("\"outcomes\":{\"lander_0\":\"none\""));

  const std::string png = absl::StrCat(::testing::TempDir(), "/cli_frame.png");
  const CommandResult render = Cli({"render", name, "--out=" + png});
  EXPECT_EQ(render.exit_code, 0) << render.err;
  EXPECT_THAT(render.out, HasSubstr("\"width\":600"));
  std::ifstream file(png, std::ios::binary);
  std::string header(8, '\0');
  file.read(header.data(), 8);
  EXPECT_EQ(header, "\x89PNG\r\n\x1a\n");

  const CommandResult deleted = Cli({"delete", name});
  EXPECT_EQ(deleted.exit_code, 0) << deleted.err;
  const CommandResult gone = Cli({"get", name});
  EXPECT_EQ(gone.exit_code, 1);
  EXPECT_THAT(gone.err, HasSubstr("NOT_FOUND"));
  EXPECT_THAT(gone.err, HasSubstr(name));
}

TEST_F(CliTest, ServerErrorsExitOneWithTheServersMessage) {
  const std::string name = CreateEnv({"--n_landers=2"});
  CommandResult result = Cli({"step", name, "--actions=0,0"});
  EXPECT_EQ(result.exit_code, 1);  // Step before reset.
  EXPECT_THAT(result.err, HasSubstr("FAILED_PRECONDITION"));
  ASSERT_EQ(Cli({"reset", name}).exit_code, 0);
  result = Cli({"step", name, "--actions=0,9"});
  EXPECT_EQ(result.exit_code, 1);
  EXPECT_THAT(result.err, HasSubstr("INVALID_ARGUMENT"));
  EXPECT_THAT(result.err, HasSubstr("9"));
  result = Cli({"render", name, "--out=/dev/null"});  // No render mode.
  EXPECT_EQ(result.exit_code, 1);
  EXPECT_THAT(result.err, HasSubstr("FAILED_PRECONDITION"));
  EXPECT_EQ(Cli({"delete", name}).exit_code, 0);
  result = Cli({"delete", name});
  EXPECT_EQ(result.exit_code, 1);
  EXPECT_THAT(result.err, HasSubstr("NOT_FOUND"));
}

TEST_F(CliTest, UsageErrorsExitTwo) {
  CommandResult result = Cli({});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("missing command"));
  result = Cli({"fly"});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("unknown command \"fly\""));
  result = Cli({"create", "--n_landers=99"});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("n_landers"));
  EXPECT_THAT(result.err, HasSubstr("99"));
  result = Cli({"get"});
  EXPECT_EQ(result.exit_code, 2);
  result = Cli({"play", "--policy=bogus"});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("bogus"));
  result = Cli({"reset", "envs/x", "--seed=-1"});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("seed"));
}

TEST_F(CliTest, PositionalArgumentsBeyondTheCommandsAreRefused) {
  CommandResult result = Cli({"health", "extra"});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("health: takes flags only; got \"extra\""));
  result = Cli({"get", "envs/a", "envs/b"});
  EXPECT_EQ(result.exit_code, 2);
  EXPECT_THAT(result.err, HasSubstr("one environment name"));
}

TEST_F(CliTest, HelpListsEveryCommandAndEachCommandsFlags) {
  CommandResult result = RunCli({"--help"});
  EXPECT_EQ(result.exit_code, 0);
  for (const char* command : {"health", "list", "create", "get", "delete",
                              "reset", "step", "render", "play"}) {
    EXPECT_THAT(result.out, HasSubstr(absl::StrCat("  ", command)));
  }
  EXPECT_THAT(result.out, HasSubstr("--address="));
  result = RunCli({"play", "--help"});
  EXPECT_EQ(result.exit_code, 0);
  for (const char* flag : {"--policy=heuristic", "--episodes=1", "--envs=",
                           "--n_landers=3", "--continuous=", "--address="}) {
    EXPECT_THAT(result.out, HasSubstr(flag)) << flag;
  }
  result = RunCli({"render", "--help"});
  EXPECT_THAT(result.out, HasSubstr("--out=frame.png"));
  EXPECT_THAT(result.out, HasSubstr("--format=png"));
  EXPECT_THAT(result.out, Not(HasSubstr("--n_landers")));
  EXPECT_THAT(result.out, Not(HasSubstr(".cc")));  // No build paths.
}

TEST_F(CliTest, ListSaysWhenThereAreNoEnvironments) {
  // A server of its own, so that no other test's environment is listed.
  absl::StatusOr<std::unique_ptr<ServerProcess>> empty =
      ServerProcess::Start(MLL_SERVER_PATH);
  ASSERT_TRUE(empty.ok()) << empty.status();
  const CommandResult result =
      RunCli({"list", absl::StrCat("--address=", (*empty)->address())});
  EXPECT_EQ(result.exit_code, 0);
  EXPECT_EQ(result.out, "");
  EXPECT_THAT(result.err, HasSubstr("no environments on"));
}

TEST_F(CliTest, ABadAddressIsAUsageErrorNamingTheRange) {
  for (const char* address : {"127.0.0.1:99999", "127.0.0.1", "[::1",
                              "::1:50051", "localhost:port"}) {
    const CommandResult result =
        RunCli({"health", absl::StrCat("--address=", address)});
    EXPECT_EQ(result.exit_code, 2) << address;
    EXPECT_THAT(result.err, HasSubstr(absl::StrCat("\"", address, "\"")));
    EXPECT_THAT(result.err, HasSubstr("1..65535"));
  }
}

TEST_F(CliTest, AFailedConnectionGivesOneLineWithoutGrpcLogs) {
  // A target gRPC itself cannot parse: gRPC logs an error line of its own.
  const CommandResult result = RunCli({"health", "--address=dns:///[::1"});
  EXPECT_EQ(result.exit_code, 1);
  EXPECT_THAT(result.err, HasSubstr("UNAVAILABLE"));
  EXPECT_EQ(std::count(result.err.begin(), result.err.end(), '\n'), 1)
      << result.err;
}

TEST_F(CliTest, NoServerExitsOneUnavailable) {
  absl::StatusOr<CommandResult> result =
      RunCommand({MLL_CLI_PATH, "health", "--address=127.0.0.1:1"});
  ASSERT_TRUE(result.ok());
  EXPECT_EQ(result->exit_code, 1);
  EXPECT_THAT(result->err, HasSubstr("UNAVAILABLE"));
}

// The members of one JSON line that say what happened, without the figures'
// formatting: steps, lengths and outcomes.
std::string Trajectory(const std::string& line) {
  static const std::regex kParts(
      "\"steps\":([0-9]+).*(\"lengths\":\\{[^}]*\\}),(\"outcomes\":\\{[^}]*\\}"
      ")");
  std::smatch match;
  if (!std::regex_search(line, match, kParts)) return "unparsed: " + line;
  return absl::StrCat(match[1].str(), " ", match[2].str(), " ", match[3].str());
}

// play flies through the server what mll_rollout flies in-process: the same
// episodes, step for step.
TEST_F(CliTest, PlayMatchesInProcessRollout) {
  const std::vector<std::string> flags = {"--n_landers=3", "--episodes=2",
                                          "--seed=4", "--policy=heuristic"};
  std::vector<std::string> play = {"play"};
  play.insert(play.end(), flags.begin(), flags.end());
  const CommandResult remote = Cli(play);
  ASSERT_EQ(remote.exit_code, 0) << remote.err;
  std::vector<std::string> rollout_args = {MLL_ROLLOUT_PATH};
  rollout_args.insert(rollout_args.end(), flags.begin(), flags.end());
  absl::StatusOr<CommandResult> local = RunCommand(rollout_args);
  ASSERT_TRUE(local.ok());
  ASSERT_EQ(local->exit_code, 0) << local->err;

  const std::vector<std::string> remote_lines =
      absl::StrSplit(remote.out, '\n', absl::SkipEmpty());
  const std::vector<std::string> local_lines =
      absl::StrSplit(local->out, '\n', absl::SkipEmpty());
  ASSERT_EQ(remote_lines.size(), 3u) << remote.out;
  ASSERT_EQ(local_lines.size(), 3u) << local->out;
  for (int episode = 0; episode < 2; ++episode) {
    EXPECT_THAT(remote_lines[episode],
                HasSubstr(absl::StrCat("\"episode\":", episode,
                                       ",\"seed\":", 4 + episode)));
    EXPECT_EQ(Trajectory(remote_lines[episode]),
              Trajectory(local_lines[episode]));
  }
  EXPECT_THAT(remote_lines[2], StartsWith("{\"summary\":true,\"episodes\":2"));
  // The env play created is deleted when it ends.
  EXPECT_THAT(Cli({"list"}).out, ::testing::Not(HasSubstr("\"n_landers\":3")));

  const CommandResult random =
      Cli({"play", "--policy=random", "--continuous", "--n_landers=2"});
  EXPECT_EQ(random.exit_code, 0) << random.err;
  EXPECT_THAT(random.out, HasSubstr("\"summary\":true"));
}

}  // namespace
}  // namespace mll::client

// Runs the built mll_rollout binary (path from MLL_ROLLOUT_BIN) and checks
// what it prints. JSON is parsed with protobuf's JSON parser into a
// google.protobuf.Struct, a real parser that the test already has at hand.
#include <sys/wait.h>

#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "gmock/gmock.h"
#include "google/protobuf/struct.pb.h"
#include "google/protobuf/util/json_util.h"
#include "gtest/gtest.h"

namespace mll::core {
namespace {

using ::google::protobuf::Struct;
using ::google::protobuf::Value;
using ::testing::HasSubstr;

struct RunResult {
  int exit_code = -1;
  std::vector<std::string> lines;  // Non-empty lines of stdout (+ stderr).
};

// Runs mll_rollout with `args`; stderr joins stdout when `with_stderr`.
RunResult RunRollout(const std::string& args, bool with_stderr = false) {
  const std::string command = absl::StrCat(
      MLL_ROLLOUT_BIN, " ", args, with_stderr ? " 2>&1" : " 2>/dev/null");
  RunResult result;
  FILE* pipe = popen(command.c_str(), "r");
  if (pipe == nullptr) {
    ADD_FAILURE() << "popen failed: " << command;
    return result;
  }
  std::string output;
  char buffer[4096];
  size_t n;
  while ((n = fread(buffer, 1, sizeof(buffer), pipe)) > 0) {
    output.append(buffer, n);
  }
  const int status = pclose(pipe);
  result.exit_code = WIFEXITED(status) ? WEXITSTATUS(status) : -1;
  for (absl::string_view line :
       absl::StrSplit(output, '\n', absl::SkipEmpty())) {
    result.lines.emplace_back(line);
  }
  return result;
}

Struct ParseJson(const std::string& line) {
  Struct object;
  const auto status =
      google::protobuf::util::JsonStringToMessage(line, &object);
  EXPECT_TRUE(status.ok()) << status.ToString() << " in: " << line;
  return object;
}

const Value& Field(const Struct& object, const std::string& key) {
  static const Value* const kMissing = new Value();
  auto it = object.fields().find(key);
  if (it == object.fields().end()) {
    ADD_FAILURE() << "missing key \"" << key << "\"";
    return *kMissing;
  }
  return it->second;
}

constexpr char kTwoEpisodes[] =
    "--n_landers=2 --episodes=2 --seed=5 --policy=random --max_cycles=300";

TEST(RolloutTest, PrintsOneJsonLinePerEpisodeAndASummary) {
  const RunResult run = RunRollout(kTwoEpisodes);
  ASSERT_EQ(run.exit_code, 0);
  ASSERT_EQ(run.lines.size(), 3u);
  const std::vector<std::string> kOutcomes = {
      "landed", "crashed", "out_of_bounds", "truncated", "aborted"};
  for (int episode = 0; episode < 2; ++episode) {
    const Struct line = ParseJson(run.lines[episode]);
    EXPECT_EQ(Field(line, "episode").number_value(), episode);
    EXPECT_EQ(Field(line, "seed").number_value(), 5 + episode);
    const double steps = Field(line, "steps").number_value();
    EXPECT_GE(steps, 1);
    EXPECT_LE(steps, 300);
    const Struct& returns = Field(line, "returns").struct_value();
    const Struct& outcomes = Field(line, "outcomes").struct_value();
    const Struct& lengths = Field(line, "lengths").struct_value();
    EXPECT_EQ(returns.fields_size(), 2);
    EXPECT_EQ(outcomes.fields_size(), 2);
    for (const std::string agent : {"lander_0", "lander_1"}) {
      EXPECT_EQ(Field(returns, agent).kind_case(), Value::kNumberValue);
      EXPECT_THAT(kOutcomes,
                  ::testing::Contains(Field(outcomes, agent).string_value()))
          << agent;
      EXPECT_LE(Field(lengths, agent).number_value(), steps);
    }
  }
  const Struct summary = ParseJson(run.lines[2]);
  EXPECT_TRUE(Field(summary, "summary").bool_value());
  EXPECT_EQ(Field(summary, "episodes").number_value(), 2);
  EXPECT_EQ(Field(summary, "mean_return").struct_value().fields_size(), 2);
  const double landing_rate = Field(summary, "landing_rate").number_value();
  EXPECT_GE(landing_rate, 0.0);
  EXPECT_LE(landing_rate, 1.0);
  EXPECT_GT(Field(summary, "mean_steps").number_value(), 0.0);
  EXPECT_GT(Field(summary, "agent_steps_per_second").number_value(), 0.0);
}

TEST(RolloutTest, SameSeedPrintsTheSameEpisodes) {
  const RunResult first = RunRollout(kTwoEpisodes);
  const RunResult second = RunRollout(kTwoEpisodes);
  ASSERT_EQ(first.exit_code, 0);
  ASSERT_EQ(second.exit_code, 0);
  ASSERT_EQ(first.lines.size(), 3u);
  ASSERT_EQ(second.lines.size(), 3u);
  // The summary's throughput differs run to run; the episodes must not.
  EXPECT_EQ(first.lines[0], second.lines[0]);
  EXPECT_EQ(first.lines[1], second.lines[1]);
  // And the seed matters.
  const RunResult other = RunRollout(
      "--n_landers=2 --episodes=2 --seed=6 --policy=random --max_cycles=300");
  ASSERT_EQ(other.exit_code, 0);
  ASSERT_GE(other.lines.size(), 1u);
  EXPECT_NE(ParseJson(other.lines[0]).DebugString(),
            ParseJson(first.lines[0]).DebugString());
}

TEST(RolloutTest, RenderingDoesNotChangeTheEpisodes) {
  const std::string frames =
      (std::filesystem::path(testing::TempDir()) / "mll_rollout_frames")
          .string();
  std::filesystem::remove_all(frames);
  const RunResult plain =
      RunRollout("--n_landers=3 --episodes=1 --seed=1 --policy=heuristic");
  const RunResult rendered = RunRollout(
      absl::StrCat("--n_landers=3 --episodes=1 --seed=1 --policy=heuristic "
                   "--frames_dir=",
                   frames));
  ASSERT_EQ(plain.exit_code, 0);
  ASSERT_EQ(rendered.exit_code, 0);
  ASSERT_FALSE(plain.lines.empty());
  ASSERT_FALSE(rendered.lines.empty());
  EXPECT_EQ(plain.lines[0], rendered.lines[0]);
  // One frame after the reset and one after each step.
  const int steps = static_cast<int>(
      Field(ParseJson(plain.lines[0]), "steps").number_value());
  int pngs = 0;
  for (const auto& entry : std::filesystem::directory_iterator(frames)) {
    pngs += entry.path().extension() == ".png";
  }
  EXPECT_EQ(pngs, steps + 1);
  EXPECT_TRUE(
      std::filesystem::exists(std::filesystem::path(frames) / "000_00000.png"));
  std::filesystem::remove_all(frames);
}

// Runs `--<flag>=<value>` and expects an error naming the flag; config
// errors exit 2, absl's own flag-parsing errors exit 1.
void ExpectRejected(const std::string& args, int exit_code) {
  const RunResult run = RunRollout(args, /*with_stderr=*/true);
  EXPECT_EQ(run.exit_code, exit_code) << args;
  const std::string flag = args.substr(2, args.find('=') - 2);
  std::string all;
  for (const std::string& line : run.lines) all += line + "\n";
  EXPECT_THAT(all, HasSubstr(flag)) << args;
}

TEST(RolloutTest, BadValuesExitNonZeroNamingTheField) {
  // Ranges checked by the core's ValidateEnvConfig.
  ExpectRejected("--n_landers=33", 2);
  ExpectRejected("--gravity=-13", 2);
  ExpectRejected("--max_cycles=0", 2);
  ExpectRejected("--wind_power=21", 2);
  // The tool's own flags.
  ExpectRejected("--render_mode=human", 2);
  ExpectRejected("--policy=greedy", 2);
  ExpectRejected("--episodes=0", 2);
  // Not a number at all: absl's parser rejects it.
  ExpectRejected("--n_landers=three", 1);
}

}  // namespace
}  // namespace mll::core

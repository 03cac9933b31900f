// One client over several real mll_server processes on loopback: placement,
// lookups, StepBatch fanned out over the servers (bit-identical to one
// server), a server's failure, sessions, and mll_cli with an address list.
#include <cstring>
#include <memory>
#include <regex>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "cli_runner.h"
#include "core_bridge.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;
using ::testing::UnorderedElementsAreArray;

constexpr int kServers = 2;

// Starts kServers plain servers into `servers`, their addresses in order.
void StartServers(std::vector<std::unique_ptr<ServerProcess>>* servers,
                  std::vector<std::string>* addresses) {
  for (int i = 0; i < kServers; ++i) {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH);
    ASSERT_TRUE(server.ok()) << server.status();
    addresses->push_back((*server)->address());
    servers->push_back(*std::move(server));
  }
}

// Two servers for the whole suite: tests use their own environments.
class TwoServers : public ::testing::Environment {
 public:
  void SetUp() override { StartServers(&servers_, &addresses_); }
  void TearDown() override { servers_.clear(); }
  static const std::vector<std::string>& addresses() { return addresses_; }

 private:
  static inline std::vector<std::unique_ptr<ServerProcess>> servers_;
  static inline std::vector<std::string> addresses_;
};

Client Connect(const std::vector<std::string>& addresses) {
  absl::StatusOr<Client> client = Client::Create(addresses);
  EXPECT_TRUE(client.ok()) << client.status();
  return *std::move(client);
}
Client ConnectBoth() { return Connect(TwoServers::addresses()); }
Client ConnectOne(int server) {
  return Connect({TwoServers::addresses()[server]});
}

std::set<std::string> Names(const Client& client) {
  absl::StatusOr<std::vector<EnvInfo>> envs = client.ListEnvs();
  EXPECT_TRUE(envs.ok()) << envs.status();
  std::set<std::string> names;
  if (envs.ok()) {
    for (const EnvInfo& env : *envs) names.insert(env.name);
  }
  return names;
}

RemoteEnvConfig Landers(int n, int max_cycles = 500) {
  RemoteEnvConfig config;
  config.n_landers = n;
  config.max_cycles = max_cycles;
  return config;
}

TEST(ScaleOutTest, CreateRejectsBadAddressLists) {
  absl::StatusOr<Client> none = Client::Create(std::vector<std::string>{});
  EXPECT_EQ(none.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(none.status().message(), HasSubstr("addresses is empty"));
  const std::string a = TwoServers::addresses()[0];
  absl::StatusOr<Client> twice = Client::Create({a, "127.0.0.1:1", a});
  EXPECT_EQ(twice.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(twice.status().message(),
              HasSubstr(absl::StrCat("addresses[2] is \"", a, "\"")));
  absl::StatusOr<Client> empty = Client::Create({a, ""});
  EXPECT_EQ(empty.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(empty.status().message(), HasSubstr("addresses[1]"));
}

TEST(ScaleOutTest, EnvsSpreadEvenlyOverBothServers) {
  const Client client = ConnectBoth();
  ASSERT_EQ(client.server_count(), kServers);
  EXPECT_EQ(client.address(1), TwoServers::addresses()[1]);
  ASSERT_TRUE(client.CheckHealth().ok());
  std::vector<RemoteEnv> envs;
  std::vector<std::set<std::string>> placed(kServers);
  for (int i = 0; i < 4; ++i) {
    absl::StatusOr<RemoteEnv> env = client.CreateEnv(Landers(1));
    ASSERT_TRUE(env.ok()) << env.status();
    // Each new env goes to the server hosting fewer: the two alternate.
    if (i % 2 == 1) {
      EXPECT_NE(env->server(), envs.back().server());
    }
    placed[env->server()].insert(env->name());
    envs.push_back(*std::move(env));
  }
  EXPECT_EQ(placed[0].size(), 2u);
  EXPECT_EQ(placed[1].size(), 2u);
  // Each server holds exactly its share, as its own ListEnvs says.
  for (int server = 0; server < kServers; ++server) {
    const std::set<std::string> listed = Names(ConnectOne(server));
    for (const RemoteEnv& env : envs) {
      EXPECT_EQ(listed.count(env.name()), env.server() == server ? 1u : 0u)
          << env.name() << " on server " << server;
    }
  }
  // The client's list is both servers', each env tagged with its server.
  absl::StatusOr<std::vector<EnvInfo>> all = client.ListEnvs();
  ASSERT_TRUE(all.ok()) << all.status();
  int found = 0;
  for (const EnvInfo& info : *all) {
    for (int server = 0; server < kServers; ++server) {
      if (placed[server].count(info.name) != 0) {
        EXPECT_EQ(info.server, server) << info.name;
        ++found;
      }
    }
  }
  EXPECT_EQ(found, 4);
}

// Placement by load: a server already hosting another client's envs gets
// none of the new ones until the other has caught up.
TEST(ScaleOutTest, CreateEnvGoesToTheLeastLoadedServer) {
  const Client tenant = ConnectOne(0);
  std::vector<RemoteEnv> theirs;
  for (int i = 0; i < 3; ++i) {
    absl::StatusOr<RemoteEnv> env = tenant.CreateEnv(Landers(1));
    ASSERT_TRUE(env.ok()) << env.status();
    theirs.push_back(*std::move(env));
  }
  const Client client = ConnectBoth();
  std::vector<RemoteEnv> mine;
  for (int i = 0; i < 3; ++i) {
    absl::StatusOr<RemoteEnv> env = client.CreateEnv(Landers(1));
    ASSERT_TRUE(env.ok()) << env.status();
    EXPECT_EQ(env->server(), 1) << "env " << i;
    mine.push_back(*std::move(env));
  }
}

TEST(ScaleOutTest, CreateEnvOnPicksTheServer) {
  const Client client = ConnectBoth();
  absl::StatusOr<RemoteEnv> env = client.CreateEnvOn(1, Landers(2));
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_EQ(env->server(), 1);
  EXPECT_EQ(Names(ConnectOne(1)).count(env->name()), 1u);
  EXPECT_EQ(Names(ConnectOne(0)).count(env->name()), 0u);
  for (int bad : {-1, kServers}) {
    absl::StatusOr<RemoteEnv> wrong = client.CreateEnvOn(bad);
    EXPECT_EQ(wrong.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(wrong.status().message(),
                HasSubstr(absl::StrCat("server is ", bad, "; allowed: 0..1")));
  }
}

// A server of the list that does not answer (a name's address where no
// server listens yet) is passed over: every CreateEnv lands on the other.
TEST(ScaleOutTest, CreateEnvPassesOverAServerThatDoesNotAnswer) {
  const Client client = Connect({"127.0.0.1:1", TwoServers::addresses()[0]});
  for (int k = 0; k < 3; ++k) {
    absl::StatusOr<RemoteEnv> env = client.CreateEnv(Landers(1));
    ASSERT_TRUE(env.ok()) << env.status();
    EXPECT_EQ(env->server(), 1);
  }
  const Client none = Connect({"127.0.0.1:1", "127.0.0.1:2"});
  absl::StatusOr<RemoteEnv> env = none.CreateEnv(Landers(1));
  EXPECT_EQ(env.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(env.status().message(), HasSubstr("server 127.0.0.1:"));
}

TEST(ScaleOutTest, NamesAreFoundOnWhicheverServerHasThem) {
  const Client client = ConnectBoth();
  absl::StatusOr<RemoteEnv> env = client.CreateEnvOn(1, Landers(2));
  ASSERT_TRUE(env.ok()) << env.status();
  const std::string name = env->Release();

  absl::StatusOr<EnvInfo> info = client.GetEnv(name);
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->server, 1);
  absl::StatusOr<RemoteEnv> attached = client.Attach(name);
  ASSERT_TRUE(attached.ok()) << attached.status();
  EXPECT_EQ(attached->server(), 1);
  ASSERT_TRUE(attached->Reset(3).ok());
  absl::StatusOr<EnvInfo> refreshed = attached->Refresh();
  ASSERT_TRUE(refreshed.ok()) << refreshed.status();
  EXPECT_TRUE(refreshed->episode_started);
  EXPECT_EQ(refreshed->server, 1);  // Refresh keeps the server.

  EXPECT_TRUE(client.DeleteEnv(name).ok());
  EXPECT_EQ(client.GetEnv(name).status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(client.DeleteEnv(name).code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(client.Attach("envs/none").status().code(),
            absl::StatusCode::kNotFound);
}

// The StepData bits that a step determines.
void ExpectSameBits(const StepData& a, const StepData& b,
                    const std::string& where) {
  ASSERT_EQ(a.n_landers, b.n_landers) << where;
  ASSERT_EQ(a.observations.size(), b.observations.size()) << where;
  EXPECT_EQ(std::memcmp(a.observations.data(), b.observations.data(),
                        a.observations.size() * sizeof(float)),
            0)
      << where;
  EXPECT_EQ(std::memcmp(a.rewards.data(), b.rewards.data(),
                        a.rewards.size() * sizeof(float)),
            0)
      << where;
  EXPECT_EQ(a.terminations, b.terminations) << where;
  EXPECT_EQ(a.truncations, b.truncations) << where;
  EXPECT_EQ(a.outcomes, b.outcomes) << where;
  EXPECT_EQ(a.episode_over, b.episode_over) << where;
  EXPECT_EQ(a.cycles, b.cycles) << where;
}

// Envs flown with the heuristic through one client, stepped with StepBatch in
// reversed creation order (so the caller's order is not the servers').
class Fleet {
 public:
  Fleet(const Client& client, int n_envs) : client_(client) {
    for (int j = 0; j < n_envs; ++j) {
      // Different lander counts make a misrouted result visible.
      absl::StatusOr<RemoteEnv> env =
          client.CreateEnv(Landers(1 + j % 3, /*max_cycles=*/60));
      EXPECT_TRUE(env.ok()) << env.status();
      if (!env.ok()) return;
      pilots_.emplace_back(PilotPolicy::kHeuristic, 1 + j % 3, false, 0);
      envs_.push_back(*std::move(env));
    }
  }

  std::vector<StepData> Reset() {
    last_.clear();
    for (size_t j = 0; j < envs_.size(); ++j) {
      absl::StatusOr<StepData> data = envs_[j].Reset(1000 + j);
      EXPECT_TRUE(data.ok()) << data.status();
      last_.push_back(data.ok() ? *data : StepData());
    }
    return last_;
  }

  // One StepBatch of every env still flying; empty when none is.
  std::vector<StepData> Step() {
    std::vector<size_t> order;
    for (size_t j = envs_.size(); j-- > 0;) {
      if (!last_[j].episode_over) order.push_back(j);
    }
    if (order.empty()) return {};
    std::vector<BatchStep> batch;
    for (size_t j : order) {
      batch.push_back({&envs_[j], pilots_[j].Act(last_[j])});
    }
    absl::StatusOr<std::vector<absl::StatusOr<StepData>>> results =
        client_.StepBatch(batch);
    EXPECT_TRUE(results.ok()) << results.status();
    if (!results.ok()) return {};
    std::vector<StepData> out;
    for (size_t k = 0; k < order.size(); ++k) {
      EXPECT_TRUE((*results)[k].ok()) << (*results)[k].status();
      if (!(*results)[k].ok()) return {};
      last_[order[k]] = *(*results)[k];
      out.push_back(last_[order[k]]);
    }
    return out;
  }

  std::vector<RemoteEnv>& envs() { return envs_; }

 private:
  const Client& client_;
  std::vector<RemoteEnv> envs_;
  std::vector<RemotePilot> pilots_;
  std::vector<StepData> last_;
};

// Unary and session clients.
class ScaleOutBatchTest : public ::testing::TestWithParam<bool> {
 protected:
  static Client Maybe(Client client, bool session) {
    if (!session) return client;
    absl::StatusOr<Client> opened = client.OpenSession();
    EXPECT_TRUE(opened.ok()) << opened.status();
    return *std::move(opened);
  }
};

TEST_P(ScaleOutBatchTest, BatchAcrossServersIsBitIdenticalToOneServer) {
  const Client both = Maybe(ConnectBoth(), GetParam());
  const Client one = Maybe(ConnectOne(0), GetParam());
  constexpr int kEnvs = 6;
  Fleet spread(both, kEnvs);
  Fleet single(one, kEnvs);
  ASSERT_EQ(spread.envs().size(), static_cast<size_t>(kEnvs));
  ASSERT_EQ(single.envs().size(), static_cast<size_t>(kEnvs));
  // Placed by load: each server holds its even share.
  std::vector<int> per_server(kServers, 0);
  for (const RemoteEnv& env : spread.envs()) ++per_server[env.server()];
  EXPECT_EQ(per_server, std::vector<int>(kServers, kEnvs / kServers));
  std::vector<StepData> a = spread.Reset();
  std::vector<StepData> b = single.Reset();
  int steps = 0;
  while (!a.empty()) {
    ASSERT_EQ(a.size(), b.size()) << "step " << steps;
    for (size_t k = 0; k < a.size(); ++k) {
      ASSERT_NO_FATAL_FAILURE(ExpectSameBits(
          a[k], b[k], absl::StrCat("step ", steps, " item ", k)));
    }
    a = spread.Step();
    b = single.Step();
    ++steps;
  }
  EXPECT_TRUE(b.empty());
  EXPECT_GT(steps, 1);
  EXPECT_LE(steps, 61);  // max_cycles bounds every episode.
  // Both servers really stepped their envs.
  for (RemoteEnv& env : spread.envs()) {
    absl::StatusOr<EnvInfo> info = env.Refresh();
    ASSERT_TRUE(info.ok()) << info.status();
    EXPECT_GT(info->cycles, 0) << env.name() << " on server " << env.server();
    EXPECT_TRUE(info->episode_over);
  }
}

TEST_P(ScaleOutBatchTest, BatchRejectsHandlesOfOtherServers) {
  const Client both = Maybe(ConnectBoth(), GetParam());
  // The same server as a gRPC target is another address to the client (a
  // name would resolve to the same address: the same server).
  const std::string port =
      std::string(absl::StripPrefix(TwoServers::addresses()[0], "127.0.0.1:"));
  const Client other = Connect({"ipv4:127.0.0.1:" + port});
  absl::StatusOr<RemoteEnv> foreign = other.CreateEnv(Landers(1));
  ASSERT_TRUE(foreign.ok()) << foreign.status();
  const std::vector<int32_t> action = {0};
  const BatchStep step{&*foreign, Actions::Discrete(action)};
  absl::StatusOr<std::vector<absl::StatusOr<StepData>>> results =
      both.StepBatch({&step, 1});
  EXPECT_EQ(results.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(results.status().message(),
              HasSubstr(absl::StrCat("steps[0].env (", foreign->name(),
                                     ") lives on ipv4:127.0.0.1:", port)));
}

INSTANTIATE_TEST_SUITE_P(Transports, ScaleOutBatchTest, ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& info) {
                           return info.param ? "Session" : "Unary";
                         });

TEST(ScaleOutTest, SessionEnvsLiveOnBothServersAndDieWithIt) {
  std::vector<std::string> names;
  {
    const Client unary = ConnectBoth();
    absl::StatusOr<Client> session = unary.OpenSession();
    ASSERT_TRUE(session.ok()) << session.status();
    EXPECT_TRUE(session->is_session());
    EXPECT_EQ(session->server_count(), kServers);
    std::vector<RemoteEnv> envs;
    for (int server = 0; server < kServers; ++server) {
      absl::StatusOr<RemoteEnv> env = session->CreateEnv(Landers(1));
      ASSERT_TRUE(env.ok()) << env.status();
      EXPECT_EQ(env->server(), server);
      EXPECT_TRUE(env->info().session_bound);
      EXPECT_EQ(Names(ConnectOne(server)).count(env->name()), 1u);
      names.push_back(env->name());
      envs.push_back(*std::move(env));
    }
  }
  // The session's streams have ended: each server destroys its env.
  for (int server = 0; server < kServers; ++server) {
    const Client one = ConnectOne(server);
    EXPECT_TRUE(Eventually([&] {
      return Names(one).count(names[server]) == 0;
    })) << names[server]
        << " on server " << server;
  }
}

// Private servers, so that one can be killed.
TEST(ScaleOutFailureTest, ADeadServerFailsOnlyItsItems) {
  std::vector<std::unique_ptr<ServerProcess>> servers;
  std::vector<std::string> addresses;
  ASSERT_NO_FATAL_FAILURE(StartServers(&servers, &addresses));
  ClientOptions options;
  options.call_timeout = std::chrono::seconds(10);
  absl::StatusOr<Client> client = Client::Create(addresses, options);
  ASSERT_TRUE(client.ok()) << client.status();
  std::vector<RemoteEnv> envs;
  for (int server = 0; server < kServers; ++server) {
    absl::StatusOr<RemoteEnv> env = client->CreateEnv(Landers(1));
    ASSERT_TRUE(env.ok()) << env.status();
    ASSERT_TRUE(env->Reset(1).ok());
    envs.push_back(*std::move(env));
  }
  const std::vector<int32_t> action = {2};
  const std::vector<BatchStep> batch = {{&envs[1], Actions::Discrete(action)},
                                        {&envs[0], Actions::Discrete(action)}};
  servers[1]->Kill();
  absl::StatusOr<std::vector<absl::StatusOr<StepData>>> results =
      client->StepBatch(batch);
  ASSERT_TRUE(results.ok()) << results.status();
  EXPECT_EQ((*results)[0].status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT((*results)[0].status().message(),
              HasSubstr("server " + addresses[1] + ": "));
  EXPECT_TRUE((*results)[1].ok()) << (*results)[1].status();
  const absl::Status health = client->CheckHealth();
  EXPECT_EQ(health.code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(health.message(), HasSubstr(addresses[1]));
  EXPECT_EQ(client->ListEnvs().status().code(), absl::StatusCode::kUnavailable);

  servers[0]->Kill();
  results = client->StepBatch(batch);
  EXPECT_EQ(results.status().code(), absl::StatusCode::kUnavailable);
}

// ------------------------------------------------------------------ mll_cli

std::string BothFlag() {
  return "--address=" + absl::StrJoin(TwoServers::addresses(), ",");
}

TEST(ScaleOutCliTest, HealthListAndCreateCoverEveryServer) {
  const CommandResult health = RunCli({"health", BothFlag()});
  EXPECT_EQ(health.exit_code, 0) << health.err;
  std::vector<std::string> names;
  for (int server = 0; server < kServers; ++server) {
    const CommandResult created = RunCli({"create", BothFlag(), "--n_landers=7",
                                          absl::StrCat("--server=", server)});
    ASSERT_EQ(created.exit_code, 0) << created.err;
    names.push_back(EnvNameIn(created.out));
    ASSERT_FALSE(names.back().empty()) << created.out;
    EXPECT_EQ(Names(ConnectOne(server)).count(names.back()), 1u);
  }
  const CommandResult listed = RunCli({"list", BothFlag()});
  ASSERT_EQ(listed.exit_code, 0) << listed.err;
  for (const std::string& name : names) {
    EXPECT_THAT(listed.out, HasSubstr(name));
    // Commands naming an env find its server.
    const CommandResult deleted = RunCli({"delete", name, BothFlag()});
    EXPECT_EQ(deleted.exit_code, 0) << deleted.err;
  }
  const CommandResult bad = RunCli({"create", BothFlag(), "--server=2"});
  EXPECT_EQ(bad.exit_code, 2);
  EXPECT_THAT(bad.err, HasSubstr("server is 2"));
}

// Lines of play's output without the env and server members.
std::vector<std::string> EpisodeLines(const std::string& out) {
  std::vector<std::string> lines;
  for (absl::string_view line : absl::StrSplit(out, '\n', absl::SkipEmpty())) {
    if (absl::StrContains(line, "\"summary\"")) continue;
    lines.push_back(
        std::regex_replace(std::string(line), std::regex(",\"env\":.*"), ""));
  }
  return lines;
}

TEST(ScaleOutCliTest, PlayOverTwoServersFliesAsOneServer) {
  const std::vector<std::string> flags = {"--envs=4", "--episodes=2",
                                          "--seed=11", "--n_landers=2",
                                          "--max_cycles=80"};
  std::vector<std::string> spread = {"play", BothFlag()};
  spread.insert(spread.end(), flags.begin(), flags.end());
  std::vector<std::string> single = {"play",
                                     "--address=" + TwoServers::addresses()[0]};
  single.insert(single.end(), flags.begin(), flags.end());
  const CommandResult a = RunCli(spread);
  const CommandResult b = RunCli(single);
  ASSERT_EQ(a.exit_code, 0) << a.err;
  ASSERT_EQ(b.exit_code, 0) << b.err;
  for (const std::string& address : TwoServers::addresses()) {
    EXPECT_THAT(a.out, HasSubstr("\"server\":\"" + address + "\""));
  }
  EXPECT_THAT(b.out, Not(HasSubstr(TwoServers::addresses()[1])));
  const std::vector<std::string> lines = EpisodeLines(a.out);
  EXPECT_EQ(lines.size(), 8u) << a.out;
  // The same seeds and policy give the same episodes, figure for figure.
  EXPECT_EQ(lines, EpisodeLines(b.out));
  EXPECT_THAT(a.out, HasSubstr("{\"summary\":true,\"episodes\":2,\"envs\":4"));
  // play deletes its envs at exit.
  for (int server = 0; server < kServers; ++server) {
    for (const std::string& name : Names(ConnectOne(server))) {
      EXPECT_THAT(a.out, Not(HasSubstr(name)));
    }
  }
}

}  // namespace
}  // namespace mll::client

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  ::testing::AddGlobalTestEnvironment(new mll::client::TwoServers());
  return RUN_ALL_TESTS();
}

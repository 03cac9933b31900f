// VectorEnv over servers behind one host name (a Kubernetes headless
// Service's, in a cluster): servers on 127.0.0.2, .3 and .4 share a port, and
// the name `fleet.test` resolves to some of them through a hosts file. Each
// scenario runs as a child of this program inside a private mount namespace
// (unshare -m) whose /etc/hosts is that file bind-mounted, so the machine's
// own is never touched; the scenario changes the name by rewriting the file
// in place (the bind mount holds its inode). Skipped, saying why, where
// unshare -m is not permitted.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <chrono>
#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <map>
#include <memory>
#include <random>
#include <string>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/vector_env.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::HasSubstr;

constexpr char kName[] = "fleet.test";
constexpr char kHostsVariable[] = "MLL_FLEET_HOSTS";
constexpr int kLanders = 2;
constexpr int kSteps = 30;

// Whether `host`:`port` can be bound now.
bool Free(const std::string& host, int port) {
  const int fd = socket(AF_INET, SOCK_STREAM, 0);
  sockaddr_in address = {};
  address.sin_family = AF_INET;
  address.sin_port = htons(static_cast<uint16_t>(port));
  inet_pton(AF_INET, host.c_str(), &address.sin_addr);
  const bool free =
      bind(fd, reinterpret_cast<sockaddr*>(&address), sizeof(address)) == 0;
  close(fd);
  return free;
}

// A port free on every one of 127.0.0.2..4 (0 when none is found).
int FreePortOnFleet() {
  std::mt19937 random(static_cast<unsigned>(getpid()));
  for (int attempt = 0; attempt < 200; ++attempt) {
    const int port = 20000 + static_cast<int>(random() % 30000);
    if (Free("127.0.0.2", port) && Free("127.0.0.3", port) &&
        Free("127.0.0.4", port)) {
      return port;
    }
  }
  return 0;
}

// Rewrites the hosts file in place (truncated, the same inode): `kName`
// resolves to `hosts`.
void WriteHosts(const std::string& path,
                const std::vector<std::string>& hosts) {
  std::ofstream file(path, std::ios::trunc);
  file << "127.0.0.1 localhost\n";
  for (const std::string& host : hosts) file << host << " " << kName << "\n";
}

std::unique_ptr<ServerProcess> ServerAt(const std::string& host, int port) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server = ServerProcess::Start(
      MLL_SERVER_PATH,
      {absl::StrCat("--address=", host, ":", port), "--threads=1"});
  EXPECT_TRUE(server.ok()) << server.status();
  return server.ok() ? *std::move(server) : nullptr;
}

// The actions of step `step`, the same for every run.
std::vector<int32_t> ActionsOf(int step, int num_envs) {
  std::mt19937 random(static_cast<unsigned>(step));
  std::vector<int32_t> actions(static_cast<size_t>(num_envs) * kLanders);
  for (int32_t& action : actions) action = static_cast<int32_t>(random() % 4);
  return actions;
}

RemoteEnvConfig Config() {
  RemoteEnvConfig config;
  config.n_landers = kLanders;
  config.max_cycles = 40;  // Episodes end and auto-reset within the run.
  return config;
}

// How many of `envs`' envs each host holds.
std::map<std::string, int> Hosted(const VectorEnv& envs) {
  std::map<std::string, int> hosted;
  for (int env = 0; env < envs.num_envs(); ++env) {
    const std::string address = envs.address(env);
    ++hosted[address.substr(0, address.rfind(':'))];
  }
  return hosted;
}

// Every observation and reward of a run, in order.
struct Trajectory {
  std::vector<float> observations;
  std::vector<float> rewards;
  void Add(const VectorEnv& envs) {
    observations.insert(observations.end(), envs.observations().begin(),
                        envs.observations().end());
    rewards.insert(rewards.end(), envs.rewards().begin(), envs.rewards().end());
  }
  bool operator==(const Trajectory& other) const {
    return observations == other.observations && rewards == other.rewards;
  }
};

// `steps` steps of `num_envs` envs alone on `address`, after Reset(seed).
Trajectory Undisturbed(const std::string& address, int num_envs, int steps,
                       uint64_t seed) {
  Trajectory run;
  absl::StatusOr<Client> client = Client::Create(address);
  EXPECT_TRUE(client.ok()) << client.status();
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Create(*client, num_envs, Config());
  EXPECT_TRUE(envs.ok()) << envs.status();
  if (!envs.ok()) return run;
  EXPECT_TRUE(envs->Reset(seed).ok());
  run.Add(*envs);
  for (int step = 0; step < steps; ++step) {
    EXPECT_TRUE(envs->Step(ActionsOf(step, num_envs)).ok());
    run.Add(*envs);
  }
  return run;
}

class ElasticFleetTest : public ::testing::Test {
 protected:
  // In the parent: runs this test again as a child in a private mount
  // namespace (true: the caller returns); in the child: false, the hosts
  // file's path in hosts_.
  bool RunInNamespace() {
    const char* hosts = std::getenv(kHostsVariable);
    if (hosts != nullptr) {
      hosts_ = hosts;
      return false;
    }
    absl::StatusOr<CommandResult> probe = RunCommand({"unshare", "-m", "true"});
    if (!probe.ok() || probe->exit_code != 0) {
      skipped_ =
          absl::StrCat("unshare -m is not permitted here (",
                       probe.ok() ? probe->err : probe.status().ToString(),
                       "): no private hosts file");
      return true;
    }
    absl::StatusOr<std::string> file = WriteTempFile("hosts", "");
    EXPECT_TRUE(file.ok()) << file.status();
    char self[4096] = {};
    const ssize_t length = readlink("/proc/self/exe", self, sizeof(self) - 1);
    EXPECT_GT(length, 0);
    const std::string test =
        ::testing::UnitTest::GetInstance()->current_test_info()->name();
    absl::StatusOr<CommandResult> child =
        RunCommand({"unshare", "-m", "sh", "-c",
                    "mount --bind \"$0\" /etc/hosts && exec \"$@\"", *file,
                    "env", absl::StrCat(kHostsVariable, "=", *file), self,
                    absl::StrCat("--gtest_filter=ElasticFleetTest.", test)},
                   /*timeout_seconds=*/180);
    EXPECT_TRUE(child.ok()) << child.status();
    if (child.ok()) {
      EXPECT_EQ(child->exit_code, 0) << child->out << child->err;
      EXPECT_THAT(child->out, HasSubstr("[  PASSED  ] 1 test"))
          << child->out << child->err;
    }
    std::remove(file->c_str());
    return true;
  }

  std::string hosts_;
  // Why the test cannot run (RunInNamespace); empty when it can.
  std::string skipped_;
};

// At the top of a test: in the parent, runs the test as a child in a private
// mount namespace (or skips it, saying why) and returns.
#define MLL_RUN_IN_NAMESPACE()                       \
  if (RunInNamespace()) {                            \
    if (!skipped_.empty()) GTEST_SKIP() << skipped_; \
    return;                                          \
  }

// 24 envs over the two servers of the name; a third joins it: the envs even
// out within one (8 each) by replay, one rebalancing event, no failover, and
// every env gives the bits of an undisturbed run.
TEST_F(ElasticFleetTest, AServerThatJoinsTheNameTakesItsShareToTheSameBits) {
  MLL_RUN_IN_NAMESPACE();
  constexpr int kEnvs = 24;
  constexpr uint64_t kSeed = 9;
  const int port = FreePortOnFleet();
  ASSERT_GT(port, 0);
  auto first = ServerAt("127.0.0.2", port);
  auto second = ServerAt("127.0.0.3", port);
  WriteHosts(hosts_, {"127.0.0.2", "127.0.0.3"});
  ClientOptions options;
  options.rediscover_interval = std::chrono::milliseconds(200);
  absl::StatusOr<Client> client =
      Client::Create(absl::StrCat(kName, ":", port), options);
  ASSERT_TRUE(client.ok()) << client.status();
  EXPECT_EQ(client->server_count(), 2);
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(*client, kEnvs, Config());
  ASSERT_TRUE(envs.ok()) << envs.status();
  EXPECT_TRUE(envs->failover());  // On by default for a name.
  std::vector<std::string> events;
  envs->SetEventLog([&](const std::string& line) { events.push_back(line); });
  EXPECT_EQ(Hosted(*envs),
            (std::map<std::string, int>{{"127.0.0.2", 12}, {"127.0.0.3", 12}}));
  Trajectory run;
  ASSERT_TRUE(envs->Reset(kSeed).ok());
  run.Add(*envs);
  int step = 0;
  for (; step < kSteps; ++step) {
    ASSERT_TRUE(envs->Step(ActionsOf(step, kEnvs)).ok());
    run.Add(*envs);
  }
  auto third = ServerAt("127.0.0.4", port);
  WriteHosts(hosts_, {"127.0.0.2", "127.0.0.3", "127.0.0.4"});
  const auto joined = std::chrono::steady_clock::now();
  // Bounded in steps and in time: the trainer steps until the new server
  // holds its share.
  while (Hosted(*envs)["127.0.0.4"] < kEnvs / 3 && step < 100000 &&
         std::chrono::steady_clock::now() - joined < std::chrono::seconds(30)) {
    ASSERT_TRUE(envs->Step(ActionsOf(step, kEnvs)).ok());
    run.Add(*envs);
    ++step;
  }
  EXPECT_EQ(Hosted(*envs),
            (std::map<std::string, int>{
                {"127.0.0.2", 8}, {"127.0.0.3", 8}, {"127.0.0.4", 8}}));
  for (int more = 0; more < kSteps; ++more, ++step) {
    ASSERT_TRUE(envs->Step(ActionsOf(step, kEnvs)).ok());
    run.Add(*envs);
  }
  EXPECT_EQ(envs->rebalances(), 1);
  EXPECT_EQ(envs->failovers(), 0);
  ASSERT_EQ(events.size(), 1u);
  EXPECT_THAT(events[0],
              HasSubstr(absl::StrCat("VectorEnv rebalance: 8 env(s) moved onto "
                                     "127.0.0.4:",
                                     port)));
  EXPECT_THAT(events[0], HasSubstr("replayed"));
  EXPECT_TRUE(
      run == Undisturbed(absl::StrCat("127.0.0.2:", port), kEnvs, step, kSeed));
}

// A server that joins before a seeded Reset gets its share there, created
// afresh: nothing replayed, and the reset's observations are an undisturbed
// run's.
TEST_F(ElasticFleetTest, ASeededResetMovesEnvsWithoutReplay) {
  MLL_RUN_IN_NAMESPACE();
  constexpr int kEnvs = 6;
  const int port = FreePortOnFleet();
  ASSERT_GT(port, 0);
  auto first = ServerAt("127.0.0.2", port);
  WriteHosts(hosts_, {"127.0.0.2"});
  ClientOptions options;
  options.rediscover_interval = std::chrono::milliseconds(100);
  absl::StatusOr<Client> client =
      Client::Create(absl::StrCat(kName, ":", port), options);
  ASSERT_TRUE(client.ok()) << client.status();
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(*client, kEnvs, Config());
  ASSERT_TRUE(envs.ok()) << envs.status();
  std::vector<std::string> events;
  envs->SetEventLog([&](const std::string& line) { events.push_back(line); });
  auto second = ServerAt("127.0.0.3", port);
  WriteHosts(hosts_, {"127.0.0.2", "127.0.0.3"});
  const auto joined = std::chrono::steady_clock::now();
  Trajectory run;
  for (int reset = 0;
       reset < 100000 && Hosted(*envs)["127.0.0.3"] == 0 &&
       std::chrono::steady_clock::now() - joined < std::chrono::seconds(30);
       ++reset) {
    run = Trajectory();
    ASSERT_TRUE(envs->Reset(uint64_t{3}).ok());
    run.Add(*envs);
  }
  EXPECT_EQ(Hosted(*envs),
            (std::map<std::string, int>{{"127.0.0.2", 3}, {"127.0.0.3", 3}}));
  ASSERT_EQ(events.size(), 1u);
  EXPECT_THAT(events[0], HasSubstr("created afresh for a seeded reset"));
  EXPECT_EQ(envs->rebalances(), 1);
  EXPECT_TRUE(run ==
              Undisturbed(absl::StrCat("127.0.0.2:", port), kEnvs, 0, 3));
}

// With TLS, each server a name resolves to is checked against the name (the
// certificate of a headless Service's name serves every pod): a certificate
// for fleet.test is accepted at 127.0.0.2 and .3, one for another name is
// refused, and tls_target_name_override still decides when set.
TEST_F(ElasticFleetTest, TlsChecksEachServerAgainstTheName) {
  MLL_RUN_IN_NAMESPACE();
  const int port = FreePortOnFleet();
  ASSERT_GT(port, 0);
  absl::StatusOr<Certificate> fleet =
      MakeSelfSignedCertificate("mll_fleet", absl::StrCat("DNS:", kName));
  ASSERT_TRUE(fleet.ok()) << fleet.status();
  std::vector<std::unique_ptr<ServerProcess>> servers;
  for (const char* host : {"127.0.0.2", "127.0.0.3"}) {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(
            MLL_SERVER_PATH,
            {absl::StrCat("--address=", host, ":", port), "--threads=1",
             "--tls_cert=" + fleet->cert_file, "--tls_key=" + fleet->key_file});
    ASSERT_TRUE(server.ok()) << server.status();
    servers.push_back(*std::move(server));
  }
  WriteHosts(hosts_, {"127.0.0.2", "127.0.0.3"});
  ClientOptions options;
  options.use_tls = true;
  options.tls_root_certificates = fleet->cert_pem;
  absl::StatusOr<Client> client =
      Client::Create(absl::StrCat(kName, ":", port), options);
  ASSERT_TRUE(client.ok()) << client.status();
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(*client, 4, Config());
  ASSERT_TRUE(envs.ok()) << envs.status();
  EXPECT_EQ(Hosted(*envs),
            (std::map<std::string, int>{{"127.0.0.2", 2}, {"127.0.0.3", 2}}));
  EXPECT_TRUE(envs->Reset(uint64_t{1}).ok());
  // The same servers by address: the certificate does not name 127.0.0.2.
  absl::StatusOr<Client> by_address =
      Client::Create(absl::StrCat("127.0.0.2:", port), options);
  ASSERT_TRUE(by_address.ok()) << by_address.status();
  EXPECT_EQ(by_address->CheckHealth().code(), absl::StatusCode::kUnavailable);
  // An override names what the certificate is checked against.
  options.tls_target_name_override = kName;
  absl::StatusOr<Client> overridden =
      Client::Create(absl::StrCat("127.0.0.2:", port), options);
  ASSERT_TRUE(overridden.ok()) << overridden.status();
  EXPECT_TRUE(overridden->CheckHealth().ok());
  options.tls_target_name_override = "other.test";
  absl::StatusOr<Client> wrong =
      Client::Create(absl::StrCat(kName, ":", port), options);
  ASSERT_TRUE(wrong.ok()) << wrong.status();
  EXPECT_EQ(wrong->CheckHealth().code(), absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace mll::client

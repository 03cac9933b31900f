// VectorEnv's failover and env snapshot, against real mll_server processes: a
// server killed (kill -9) mid-run, in Step or in a Send/Recv loop, costs no
// episode and no bit; a dead failover target is passed over; failover off
// reports the loss; a server stopped (SIGSTOP) or cut off with its connection
// open (a stopped proxy) costs one pause of at most its deadline plus the
// replay, and no bit, and its envs are gone once it runs again; a snapshot
// (after Step or Send/Recv steps) restores on another server to the same bits,
// and a damaged or foreign snapshot is refused with the env untouched.
#include <unistd.h>
#include <zlib.h>

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <functional>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/vector_env.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::HasSubstr;

constexpr int kLanders = 2;

std::vector<std::unique_ptr<ServerProcess>> StartServers(int count) {
  std::vector<std::unique_ptr<ServerProcess>> servers;
  for (int i = 0; i < count; ++i) {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH, {"--threads=1"});
    EXPECT_TRUE(server.ok()) << server.status();
    if (server.ok()) servers.push_back(*std::move(server));
  }
  return servers;
}

// A client of `servers` (with the default step timeout unless one is given).
Client ClientOf(const std::vector<std::unique_ptr<ServerProcess>>& servers,
                SessionTransport transport = SessionTransport::kAuto,
                std::optional<std::chrono::milliseconds> step_timeout = {}) {
  ClientOptions options;
  options.session_transport = transport;
  if (step_timeout.has_value()) options.step_timeout = *step_timeout;
  std::vector<std::string> addresses;
  for (const auto& server : servers) addresses.push_back(server->address());
  absl::StatusOr<Client> client = Client::Create(addresses, options);
  EXPECT_TRUE(client.ok()) << client.status();
  return *std::move(client);
}

RemoteEnvConfig SmallConfig(int n_landers = kLanders) {
  RemoteEnvConfig config;
  config.n_landers = n_landers;
  // Short episodes: every run crosses auto-resets.
  config.max_cycles = 40;
  return config;
}

// Random discrete actions for every env, the same for every run.
std::vector<int32_t> ActionsOf(int step, int num_envs) {
  std::mt19937_64 rng(1000 + step);
  std::vector<int32_t> actions(num_envs * kLanders);
  for (int32_t& a : actions) a = static_cast<int32_t>(rng() % 4);
  return actions;
}

// What a run showed the caller: every step's observations and rewards.
struct Trajectory {
  std::vector<float> observations;
  std::vector<float> rewards;
  std::vector<uint8_t> auto_resets;
};

void Keep(const VectorEnv& envs, Trajectory* trajectory) {
  trajectory->observations.insert(trajectory->observations.end(),
                                  envs.observations().begin(),
                                  envs.observations().end());
  trajectory->rewards.insert(trajectory->rewards.end(), envs.rewards().begin(),
                             envs.rewards().end());
  trajectory->auto_resets.insert(trajectory->auto_resets.end(),
                                 envs.auto_reset().begin(),
                                 envs.auto_reset().end());
}

template <typename T>
bool SameBits(const std::vector<T>& a, const std::vector<T>& b) {
  return a.size() == b.size() &&
         std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0;
}

// Seeded reset, then kSteps steps with an unseeded reset at step 20;
// `before_step` runs before each step.
constexpr int kSteps = 120;
Trajectory FlyWith(VectorEnv& envs,
                   const std::function<void(int)>& before_step) {
  Trajectory trajectory;
  EXPECT_TRUE(envs.Reset(uint64_t{77}).ok());
  Keep(envs, &trajectory);
  for (int step = 0; step < kSteps; ++step) {
    before_step(step);
    if (step == 20) {
      const absl::Status status = envs.Reset();
      EXPECT_TRUE(status.ok()) << status;
      Keep(envs, &trajectory);
    }
    const absl::Status status =
        envs.Step(absl::MakeConstSpan(ActionsOf(step, envs.num_envs())));
    EXPECT_TRUE(status.ok()) << "step " << step << ": " << status;
    if (!status.ok()) break;
    Keep(envs, &trajectory);
  }
  return trajectory;
}

// As FlyWith, with `kill` before step `kill_at` (if any).
Trajectory Fly(VectorEnv& envs, int kill_at,
               const std::function<void()>& kill) {
  return FlyWith(envs, [&](int step) {
    if (step == kill_at) kill();
  });
}

using Servers = std::vector<std::unique_ptr<ServerProcess>>;

// `body` once per transport (shared memory, then the stream), each time with
// three new servers and a client of them.
void OnThreeServersPerTransport(
    const std::function<void(Servers&, Client&)>& body) {
  for (SessionTransport transport :
       {SessionTransport::kSharedMemory, SessionTransport::kNative}) {
    SCOPED_TRACE(SessionTransportName(transport));
    Servers servers = StartServers(3);
    ASSERT_EQ(servers.size(), 3u);
    Client client = ClientOf(servers, transport);
    body(servers, client);
  }
}

// A VectorEnv of `num_envs` envs of `client`, after an uninterrupted Fly of
// another such VectorEnv, whose trajectory goes to `expected`.
absl::StatusOr<VectorEnv> WithReferenceRun(const Client& client, int num_envs,
                                           Trajectory* expected) {
  absl::StatusOr<VectorEnv> reference =
      VectorEnv::Create(client, num_envs, SmallConfig());
  if (!reference.ok()) return reference.status();
  *expected = Fly(*reference, -1, [] {});
  EXPECT_EQ(reference->failovers(), 0);
  return VectorEnv::Create(client, num_envs, SmallConfig());
}

// Every observation, reward and auto-reset of `got` is `expected`'s.
void ExpectSameRun(const Trajectory& got, const Trajectory& expected) {
  EXPECT_TRUE(SameBits(got.observations, expected.observations));
  EXPECT_TRUE(SameBits(got.rewards, expected.rewards));
  EXPECT_EQ(got.auto_resets, expected.auto_resets);
}

// kill -9 of one of three servers mid-run: the run finishes, every
// observation and reward equal to an uninterrupted run's, on both
// transports.
TEST(FailoverTest, AServerKilledMidRunCostsNoBit) {
  constexpr int kEnvs = 9;
  OnThreeServersPerTransport([&](Servers& servers, Client& client) {
    Trajectory expected;
    absl::StatusOr<VectorEnv> envs = WithReferenceRun(client, kEnvs, &expected);
    ASSERT_TRUE(envs.ok()) << envs.status();
    EXPECT_TRUE(envs->failover());
    const std::string killed = servers[1]->address();
    const Trajectory got = Fly(*envs, 70, [&] { servers[1]->Kill(); });
    EXPECT_EQ(envs->failovers(), 1);
    ExpectSameRun(got, expected);
    EXPECT_GT(
        std::count(expected.auto_resets.begin(), expected.auto_resets.end(), 1),
        kEnvs);
    for (int env = 0; env < kEnvs; ++env) {
      EXPECT_NE(envs->address(env), killed) << "env " << env;
    }
  });
}

// A rolling restart (a StatefulSet's: each pod replaced at its address):
// server A is killed (its envs move to B and C), a new server starts at A's
// address, then B is killed: B's envs are spread over the new A and C, since
// every failover probes the servers found down on a new connection, rather
// than all piling onto C. No bit differs from an uninterrupted run.
TEST(FailoverTest, AServerBackAtItsAddressTakesEnvsAtTheNextFailover) {
  constexpr int kEnvs = 9;
  OnThreeServersPerTransport([&](Servers& servers, Client& client) {
    Trajectory expected;
    absl::StatusOr<VectorEnv> envs = WithReferenceRun(client, kEnvs, &expected);
    ASSERT_TRUE(envs.ok()) << envs.status();
    const std::string a = servers[0]->address();
    const std::string b = servers[1]->address();
    const auto envs_on = [&](const std::string& address) {
      int count = 0;
      for (int env = 0; env < kEnvs; ++env)
        count += envs->address(env) == address;
      return count;
    };
    const Trajectory got = FlyWith(*envs, [&](int step) {
      if (step == 30) servers[0]->Kill();
      if (step == 50) {
        EXPECT_EQ(envs->failovers(), 1);
        EXPECT_EQ(envs_on(a), 0);
        absl::StatusOr<std::unique_ptr<ServerProcess>> replacement =
            ServerProcess::Start(
                MLL_SERVER_PATH,
                {"--threads=1", absl::StrCat("--address=", a)});
        ASSERT_TRUE(replacement.ok()) << replacement.status();
        ASSERT_EQ((*replacement)->address(), a);
        servers[0] = *std::move(replacement);
      }
      if (step == 70) servers[1]->Kill();
    });
    EXPECT_EQ(envs->failovers(), 2);
    ExpectSameRun(got, expected);
    EXPECT_GE(envs_on(a), 1);
    EXPECT_EQ(envs_on(b), 0);
    EXPECT_LT(envs_on(servers[2]->address()), kEnvs);
  });
}

TEST(FailoverTest, AnEnvDeletedBehindItsBackIsRecreatedWhereItWas) {
  std::vector<std::unique_ptr<ServerProcess>> servers = StartServers(2);
  ASSERT_EQ(servers.size(), 2u);
  Client client = ClientOf(servers);
  absl::StatusOr<VectorEnv> reference =
      VectorEnv::Create(client, 4, SmallConfig());
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(client, 4, SmallConfig());
  ASSERT_TRUE(reference.ok() && envs.ok());
  const Trajectory expected = Fly(*reference, -1, [] {});
  const Trajectory got = Fly(
      *envs, 50, [&] { ASSERT_TRUE(client.DeleteEnv(envs->names()[3]).ok()); });
  EXPECT_EQ(envs->failovers(), 1);
  EXPECT_EQ(envs->address(3), servers[1]->address());
  EXPECT_TRUE(SameBits(got.observations, expected.observations));
  EXPECT_TRUE(SameBits(got.rewards, expected.rewards));
}

// Up to 10 rounds of Recv, then Send of zero actions to the envs received
// (batch_size 2); the first error.
absl::Status RecvAndSendUntilAnError(VectorEnv& envs) {
  absl::Status status = absl::OkStatus();
  for (int count = 0; count < 10 && status.ok(); ++count) {
    status = envs.Recv();
    if (status.ok()) {
      const std::vector<int> ids(envs.env_ids().begin(), envs.env_ids().end());
      status = envs.Send(
          absl::MakeConstSpan(std::vector<int32_t>(2 * kLanders, 0)), ids);
    }
  }
  return status;
}

// Failover off: Step, and a Send/Recv loop, report the loss of a server.
TEST(FailoverTest, OffTheLossReachesTheCaller) {
  std::vector<std::unique_ptr<ServerProcess>> servers = StartServers(2);
  ASSERT_EQ(servers.size(), 2u);
  Client client = ClientOf(servers);
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(
      client, 4, SmallConfig(), /*batch_size=*/0, /*failover=*/false);
  absl::StatusOr<VectorEnv> async_envs = VectorEnv::Create(
      client, 4, SmallConfig(), /*batch_size=*/2, /*failover=*/false);
  ASSERT_TRUE(envs.ok()) << envs.status();
  ASSERT_TRUE(async_envs.ok()) << async_envs.status();
  EXPECT_FALSE(envs->failover());
  ASSERT_TRUE(envs->Reset(uint64_t{1}).ok());
  ASSERT_TRUE(async_envs->AsyncReset(uint64_t{1}).ok());
  servers[1]->Kill();
  const absl::Status status = envs->Step(absl::MakeConstSpan(ActionsOf(0, 4)));
  EXPECT_EQ(status.code(), absl::StatusCode::kUnavailable) << status;
  EXPECT_EQ(envs->failovers(), 0);
  // Both envs of the killed server are met within a few Recvs.
  const absl::Status async_status = RecvAndSendUntilAnError(*async_envs);
  EXPECT_EQ(async_status.code(), absl::StatusCode::kUnavailable)
      << async_status;
  EXPECT_EQ(async_envs->failovers(), 0);
}

// Failover on with one address: with its server gone and none other, the
// step says so.
TEST(FailoverTest, OnWithOneAddressReportsThatNoServerAnswers) {
  std::vector<std::unique_ptr<ServerProcess>> servers = StartServers(1);
  ASSERT_EQ(servers.size(), 1u);
  Client client = ClientOf(servers);
  absl::StatusOr<VectorEnv> one = VectorEnv::Create(client, 2, SmallConfig());
  ASSERT_TRUE(one.ok());
  EXPECT_FALSE(one->failover());
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Create(client, 2, SmallConfig(), 0, /*failover=*/true);
  ASSERT_TRUE(envs.ok()) << envs.status();
  ASSERT_TRUE(envs->Reset(uint64_t{1}).ok());
  servers[0]->Kill();
  const absl::Status status = envs->Step(absl::MakeConstSpan(ActionsOf(0, 2)));
  EXPECT_EQ(status.code(), absl::StatusCode::kUnavailable) << status;
  EXPECT_THAT(std::string(status.message()),
              HasSubstr("found no reachable server of"));
}

// ------------------------------------------------ EnvPool's Send/Recv loop

constexpr int kAsyncEnvs = 24;
constexpr int kBatch = 8;
constexpr int kRecvs = 150;
// About 50 steps per env: each crosses an episode end (max_cycles 40).
// Every Send/Recv loop's time bound.
constexpr auto kLoopTime = std::chrono::seconds(120);

// Env `env`'s actions for its step `step`, the same for every run whatever
// the order in which Recv returns the envs.
std::vector<int32_t> ActionsOfEnv(int env, int step) {
  std::mt19937_64 rng(100000 * static_cast<uint64_t>(env) + step);
  std::vector<int32_t> actions(kLanders);
  for (int32_t& a : actions) a = static_cast<int32_t>(rng() % 4);
  return actions;
}

// One row of Recv's results as the caller saw it: its observations, rewards,
// terminations and truncations as bytes, and whether it was an auto-reset.
struct Row {
  std::string bits;
  bool auto_reset = false;
  bool operator==(const Row& other) const {
    return bits == other.bits && auto_reset == other.auto_reset;
  }
};

Row RowOf(const VectorEnv& envs, int row) {
  const StepData data = envs.Result(row);
  Row out;
  const auto append = [&](const auto& column) {
    out.bits.append(reinterpret_cast<const char*>(column.data()),
                    column.size() * sizeof(column[0]));
  };
  append(data.observations);
  append(data.rewards);
  append(data.terminations);
  append(data.truncations);
  out.auto_reset = data.auto_reset;
  return out;
}

// Each env's rows in the order Recv returned them, over kRecvs Recvs after
// AsyncReset, each env sent its next actions as soon as Recv returned it;
// `fault` runs before the Send that follows Recv number `fault_at` (so the
// fault meets the steps sent from then on, whatever the server had answered
// before). The longest Recv goes to `slowest` when given.
std::vector<std::vector<Row>> SendRecvRun(VectorEnv& envs, int fault_at,
                                          const std::function<void()>& fault,
                                          absl::Duration* slowest = nullptr) {
  const auto deadline = std::chrono::steady_clock::now() + kLoopTime;
  std::vector<std::vector<Row>> rows(envs.num_envs());
  std::vector<int> steps(envs.num_envs(), 0);
  absl::Status status = envs.AsyncReset(uint64_t{7});
  EXPECT_TRUE(status.ok()) << status;
  for (int count = 0; count < kRecvs && status.ok(); ++count) {
    if (std::chrono::steady_clock::now() > deadline) {
      ADD_FAILURE() << "recv " << count << " of " << kRecvs << " after "
                    << kLoopTime.count() << " s";
      break;
    }
    const absl::Time began = absl::Now();
    status = envs.Recv();
    if (slowest != nullptr) {
      *slowest = std::max(*slowest, absl::Now() - began);
    }
    EXPECT_TRUE(status.ok()) << "recv " << count << ": " << status;
    if (!status.ok()) break;
    const std::vector<int> ids(envs.env_ids().begin(), envs.env_ids().end());
    std::vector<int32_t> actions;
    for (size_t row = 0; row < ids.size(); ++row) {
      rows[ids[row]].push_back(RowOf(envs, static_cast<int>(row)));
      const std::vector<int32_t> mine =
          ActionsOfEnv(ids[row], steps[ids[row]]++);
      actions.insert(actions.end(), mine.begin(), mine.end());
    }
    if (count == fault_at) fault();
    status = envs.Send(absl::MakeConstSpan(actions), ids);
    EXPECT_TRUE(status.ok()) << "send " << count << ": " << status;
  }
  return rows;
}

// Each env's rows in `got` are those in `expected` as far as both went
// (which envs each Recv returns depends on timing), at least `least` each,
// and both runs returned kRecvs * kBatch rows.
void ExpectSameRows(const std::vector<std::vector<Row>>& got,
                    const std::vector<std::vector<Row>>& expected,
                    size_t least) {
  ASSERT_EQ(got.size(), expected.size());
  size_t got_rows = 0;
  size_t expected_rows = 0;
  for (size_t env = 0; env < got.size(); ++env) {
    got_rows += got[env].size();
    expected_rows += expected[env].size();
    const size_t common = std::min(got[env].size(), expected[env].size());
    EXPECT_GE(common, least) << "env " << env << ": " << got[env].size()
                             << " and " << expected[env].size() << " rows";
    for (size_t k = 0; k < common; ++k) {
      ASSERT_TRUE(got[env][k] == expected[env][k])
          << "env " << env << ", row " << k;
    }
  }
  EXPECT_EQ(got_rows, static_cast<size_t>(kRecvs * kBatch));
  EXPECT_EQ(expected_rows, static_cast<size_t>(kRecvs * kBatch));
}

bool AnyAutoReset(const std::vector<std::vector<Row>>& rows) {
  for (const std::vector<Row>& env_rows : rows) {
    // The first row is AsyncReset's: an auto-reset flag after it is an
    // episode that ended (and was replayed across the failover).
    for (size_t k = 1; k < env_rows.size(); ++k) {
      if (env_rows[k].auto_reset) return true;
    }
  }
  return false;
}

// `killed` of the three servers killed (kill -9; `fault` instead when given,
// e.g. Pause) mid-way through a Send/Recv loop: each env's results equal an
// uninterrupted run's, on both transports, and no env is left on a killed
// server. The longest Recv goes to `slowest` when given.
void ExpectSendRecvSurvives(
    const std::vector<int>& killed, int failovers,
    void (ServerProcess::*fault)() = &ServerProcess::Kill,
    absl::Duration* slowest = nullptr) {
  OnThreeServersPerTransport([&](Servers& servers, Client& client) {
    absl::StatusOr<VectorEnv> reference =
        VectorEnv::Create(client, kAsyncEnvs, SmallConfig(), kBatch);
    ASSERT_TRUE(reference.ok()) << reference.status();
    const std::vector<std::vector<Row>> expected =
        SendRecvRun(*reference, -1, [] {});
    EXPECT_EQ(reference->failovers(), 0);

    absl::StatusOr<VectorEnv> envs =
        VectorEnv::Create(client, kAsyncEnvs, SmallConfig(), kBatch);
    ASSERT_TRUE(envs.ok()) << envs.status();
    std::vector<std::string> killed_addresses;
    for (int server : killed) {
      killed_addresses.push_back(servers[server]->address());
    }
    const std::vector<std::vector<Row>> got = SendRecvRun(
        *envs, kRecvs / 2,
        [&] {
          for (int server : killed) ((*servers[server]).*fault)();
        },
        slowest);
    EXPECT_EQ(envs->failovers(), failovers);
    ExpectSameRows(got, expected, kRecvs * kBatch / kAsyncEnvs / 2);
    EXPECT_TRUE(AnyAutoReset(expected));
    for (int env = 0; env < kAsyncEnvs; ++env) {
      EXPECT_THAT(killed_addresses,
                  ::testing::Not(::testing::Contains(envs->address(env))))
          << "env " << env;
    }
  });
}

TEST(FailoverTest, AServerKilledDuringSendRecvCostsNoBit) {
  ExpectSendRecvSurvives({1}, 1);
}

// Two of three servers killed at once: the first failover's round robin
// targets the other dead one too, whose replay fails; it is passed over for
// the live server. Its own envs fail over when their Recv meets the loss.
TEST(FailoverTest, ADeadTargetIsPassedOverDuringSendRecv) {
  ExpectSendRecvSurvives({1, 2}, 2);
}

// A Send/Recv loop on two servers both killed: Recv says no server is left,
// naming the servers and the one passed over.
TEST(FailoverTest, SendRecvWithNoServerLeftNamesTheServersTried) {
  std::vector<std::unique_ptr<ServerProcess>> servers = StartServers(2);
  ASSERT_EQ(servers.size(), 2u);
  Client client = ClientOf(servers);
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Create(client, 4, SmallConfig(), /*batch_size=*/2);
  ASSERT_TRUE(envs.ok()) << envs.status();
  ASSERT_TRUE(envs->AsyncReset(uint64_t{1}).ok());
  servers[0]->Kill();
  servers[1]->Kill();
  // Both servers' envs are met within a few Recvs.
  const absl::Status status = RecvAndSendUntilAnError(*envs);
  EXPECT_EQ(status.code(), absl::StatusCode::kUnavailable) << status;
  const std::string message(status.message());
  EXPECT_THAT(message, HasSubstr("found no reachable server of"));
  EXPECT_THAT(message, HasSubstr("; passed over "));
  EXPECT_THAT(message, HasSubstr(servers[0]->address()));
  EXPECT_THAT(message, HasSubstr(servers[1]->address()));
  EXPECT_EQ(envs->failovers(), 0);
}

// ------------------------------------------------ stalls: SIGSTOP, partitions

// The deadline of the default options, and the bound the tests put on the one
// pause a stall costs: the deadline plus a generous allowance for the probe
// of the stalled server and the replay (a bound, not a measurement).
const absl::Duration kDefaultStepTimeout =
    absl::FromChrono(ClientOptions().step_timeout);
const absl::Duration kPauseBound = kDefaultStepTimeout + absl::Seconds(10);

// Whether the server at `address` holds no env (ListEnvs), within `seconds`:
// a stalled server's envs go once it runs again (their session was
// cancelled).
bool HoldsNoEnvWithin(const std::string& address, int seconds) {
  absl::StatusOr<Client> client = Client::Create(address);
  if (!client.ok()) return false;
  return Eventually(
      [&] {
        const absl::StatusOr<std::vector<EnvInfo>> envs = client->ListEnvs();
        return envs.ok() && envs->empty();
      },
      seconds);
}

// As Fly, with `fault` before step `at`; the longest time between two
// steps' starts (one step and its bookkeeping) goes to `slowest`.
Trajectory FlyTimed(VectorEnv& envs, int at, const std::function<void()>& fault,
                    absl::Duration* slowest) {
  absl::Time last = absl::Now();
  return FlyWith(envs, [&](int step) {
    const absl::Time now = absl::Now();
    *slowest = std::max(*slowest, now - last);
    if (step == at) fault();
    last = absl::Now();
  });
}

// Flies `envs` 70 steps, pausing `stall` (a server, or a proxy in front of
// one) midway, and checks what the stall costs: one failover, the bits of
// `expected`, one pause of at least the deadline and at most kPauseBound, and
// no env left at `stall`'s address.
void ExpectOneBoundedPause(VectorEnv& envs, const Trajectory& expected,
                           ServerProcess& stall) {
  absl::Duration slowest;
  const Trajectory got = FlyTimed(
      envs, 70, [&] { stall.Pause(); }, &slowest);
  EXPECT_EQ(envs.failovers(), 1);
  ExpectSameRun(got, expected);
  EXPECT_GE(slowest, kDefaultStepTimeout);
  EXPECT_LE(slowest, kPauseBound);
  for (int env = 0; env < envs.num_envs(); ++env) {
    EXPECT_NE(envs.address(env), stall.address()) << "env " << env;
  }
}

// One of three servers stopped (SIGSTOP: its sockets stay open, it answers
// nothing) mid-run, default options: one pause of at most the deadline plus
// the replay, one failover, every bit of an uninterrupted run, on both
// transports. Resumed, the server holds none of the envs any more (their
// session was cancelled), so none is stepped by two servers.
TEST(StallTest, AStoppedServerCostsOnePauseAndNoBit) {
  constexpr int kEnvs = 9;
  OnThreeServersPerTransport([&](Servers& servers, Client& client) {
    Trajectory expected;
    absl::StatusOr<VectorEnv> envs = WithReferenceRun(client, kEnvs, &expected);
    ASSERT_TRUE(envs.ok()) << envs.status();
    ExpectOneBoundedPause(*envs, expected, *servers[1]);
    servers[1]->Resume();
    EXPECT_TRUE(HoldsNoEnvWithin(servers[1]->address(), 30));
  });
}

// The same during a Send/Recv loop: the Recv that meets the stopped server
// waits at most the deadline plus the replay.
TEST(StallTest, AServerStoppedDuringSendRecvCostsOnePauseAndNoBit) {
  absl::Duration slowest;
  ExpectSendRecvSurvives({1}, 1, &ServerProcess::Pause, &slowest);
  EXPECT_GE(slowest, kDefaultStepTimeout);
  EXPECT_LE(slowest, kPauseBound);
}

// A partition with the connection left open: each server behind a proxy
// (bench/latency/delay_proxy, no delay), one proxy stopped mid-run. The
// stream transport (shared memory would bypass the proxy).
TEST(StallTest, AStoppedLinkCostsOnePauseAndNoBit) {
  if (access(MLL_DELAY_PROXY_PATH, X_OK) != 0) {
    GTEST_SKIP() << MLL_DELAY_PROXY_PATH << " is not built (benchmarks off)";
  }
  constexpr int kEnvs = 9;
  Servers servers = StartServers(3);
  ASSERT_EQ(servers.size(), 3u);
  Servers proxies;
  for (const auto& server : servers) {
    absl::StatusOr<std::unique_ptr<ServerProcess>> proxy =
        ServerProcess::StartProgram(
            {MLL_DELAY_PROXY_PATH, "--listen=127.0.0.1:0",
             "--target=" + server->address(), "--delay_us=0"});
    ASSERT_TRUE(proxy.ok()) << proxy.status();
    proxies.push_back(*std::move(proxy));
  }
  Client client = ClientOf(proxies, SessionTransport::kNative);
  Trajectory expected;
  absl::StatusOr<VectorEnv> envs = WithReferenceRun(client, kEnvs, &expected);
  ASSERT_TRUE(envs.ok()) << envs.status();
  ExpectOneBoundedPause(*envs, expected, *proxies[1]);
  // The link heals: the server ends the cancelled session.
  proxies[1]->Resume();
  EXPECT_TRUE(HoldsNoEnvWithin(servers[1]->address(), 30));
}

// Failover off and the only server stopped: Step, and Recv, fail with
// DEADLINE_EXCEEDED naming the server and the timeout within the deadline
// (and a margin), on both transports; resumed, the server holds no env.
TEST(StallTest, OffAStoppedServerFailsWithinTheDeadline) {
  constexpr auto kTimeout = std::chrono::milliseconds(1500);
  for (SessionTransport transport :
       {SessionTransport::kSharedMemory, SessionTransport::kNative}) {
    SCOPED_TRACE(SessionTransportName(transport));
    Servers servers = StartServers(1);
    ASSERT_EQ(servers.size(), 1u);
    Client client = ClientOf(servers, transport, kTimeout);
    absl::StatusOr<VectorEnv> envs =
        VectorEnv::Create(client, 4, SmallConfig());
    absl::StatusOr<VectorEnv> async_envs =
        VectorEnv::Create(client, 4, SmallConfig(), /*batch_size=*/2);
    ASSERT_TRUE(envs.ok()) << envs.status();
    ASSERT_TRUE(async_envs.ok()) << async_envs.status();
    EXPECT_FALSE(envs->failover());
    ASSERT_TRUE(envs->Reset(uint64_t{1}).ok());
    ASSERT_TRUE(async_envs->AsyncReset(uint64_t{1}).ok());
    servers[0]->Pause();
    const auto expect_deadline = [&](const absl::Status& status,
                                     absl::Duration took) {
      EXPECT_EQ(status.code(), absl::StatusCode::kDeadlineExceeded) << status;
      EXPECT_THAT(std::string(status.message()),
                  HasSubstr(servers[0]->address()));
      EXPECT_THAT(std::string(status.message()), HasSubstr("1.5s"));
      EXPECT_GE(took, absl::FromChrono(kTimeout));
      EXPECT_LE(took, absl::FromChrono(kTimeout) + absl::Seconds(5));
    };
    absl::Time began = absl::Now();
    const absl::Status status =
        envs->Step(absl::MakeConstSpan(ActionsOf(0, 4)));
    expect_deadline(status, absl::Now() - began);
    // The Recvs of results already received return at once; the first that
    // waits for the server meets its deadline.
    began = absl::Now();
    const absl::Status async_status = RecvAndSendUntilAnError(*async_envs);
    expect_deadline(async_status, absl::Now() - began);
    EXPECT_EQ(envs->failovers(), 0);
    servers[0]->Resume();
    EXPECT_TRUE(HoldsNoEnvWithin(servers[0]->address(), 30));
  }
}

// The snapshot's bytes with `edit` applied and a valid CRC again.
std::string Edited(std::string snapshot,
                   const std::function<void(std::string*)>& edit) {
  snapshot.resize(snapshot.size() - 4);
  edit(&snapshot);
  const uint32_t crc = static_cast<uint32_t>(
      crc32(0L, reinterpret_cast<const Bytef*>(snapshot.data()),
            static_cast<uInt>(snapshot.size())));
  for (int byte = 0; byte < 4; ++byte) {
    snapshot.push_back(static_cast<char>((crc >> (8 * byte)) & 0xff));
  }
  return snapshot;
}

class EnvSnapshotTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() { servers_ = new auto(StartServers(2)); }
  static void TearDownTestSuite() { delete servers_; }
  static Client ClientOn(int server) {
    absl::StatusOr<Client> client =
        Client::Create((*servers_)[server]->address());
    EXPECT_TRUE(client.ok());
    return *std::move(client);
  }
  static inline std::vector<std::unique_ptr<ServerProcess>>* servers_;
};

// A snapshot taken on one server restores on another to the same bits: the
// restored env's snapshot is the same bytes, and both envs go on alike.
TEST_F(EnvSnapshotTest, RestoresOnAnotherServerToTheSameBits) {
  Client first = ClientOn(0);
  Client second = ClientOn(1);
  absl::StatusOr<VectorEnv> source = VectorEnv::Create(first, 3, SmallConfig());
  absl::StatusOr<VectorEnv> target =
      VectorEnv::Create(second, 3, SmallConfig());
  ASSERT_TRUE(source.ok() && target.ok());
  ASSERT_TRUE(source->Reset(uint64_t{5}).ok());
  ASSERT_TRUE(target->Reset(uint64_t{500}).ok());
  for (int step = 0; step < 55; ++step) {
    ASSERT_TRUE(source->Step(absl::MakeConstSpan(ActionsOf(step, 3))).ok());
  }
  ASSERT_TRUE(source->Reset().ok());  // An unseeded reset in the record.
  for (int step = 55; step < 70; ++step) {
    ASSERT_TRUE(source->Step(absl::MakeConstSpan(ActionsOf(step, 3))).ok());
  }
  absl::StatusOr<std::string> snapshot = source->EnvSnapshot(1);
  ASSERT_TRUE(snapshot.ok()) << snapshot.status();
  EXPECT_EQ(snapshot->substr(0, 4), "MLLS");
  const std::string old_name = target->names()[2];
  absl::StatusOr<std::vector<float>> observations =
      target->RestoreEnv(2, *snapshot);
  ASSERT_TRUE(observations.ok()) << observations.status();
  EXPECT_NE(target->names()[2], old_name);
  EXPECT_EQ(*observations, source->Result(1).observations);
  EXPECT_EQ(*target->EnvSnapshot(2), *snapshot);
  for (int step = 70; step < 100; ++step) {
    const std::vector<int32_t> actions = ActionsOf(step, 3);
    std::vector<int32_t> moved(actions);
    std::copy(actions.begin() + 1 * kLanders, actions.begin() + 2 * kLanders,
              moved.begin() + 2 * kLanders);
    ASSERT_TRUE(source->Step(absl::MakeConstSpan(actions)).ok());
    ASSERT_TRUE(target->Step(absl::MakeConstSpan(moved)).ok());
    const StepData want = source->Result(1);
    const StepData got = target->Result(2);
    ASSERT_EQ(got.observations, want.observations) << "step " << step;
    ASSERT_EQ(got.rewards, want.rewards) << "step " << step;
  }
}

// Send/Recv steps are recorded: snapshots taken after them restore on another
// server to the same bits, and the restored envs go on as the originals.
TEST_F(EnvSnapshotTest, SnapshotsAfterSendRecvStepsRestoreToTheSameBits) {
  constexpr int kEnvs = 4;
  Client first = ClientOn(0);
  Client second = ClientOn(1);
  absl::StatusOr<VectorEnv> source =
      VectorEnv::Create(first, kEnvs, SmallConfig(), /*batch_size=*/2);
  absl::StatusOr<VectorEnv> target =
      VectorEnv::Create(second, kEnvs, SmallConfig());
  ASSERT_TRUE(source.ok() && target.ok());
  ASSERT_TRUE(source->AsyncReset(uint64_t{9}).ok());
  ASSERT_TRUE(target->Reset(uint64_t{900}).ok());
  std::vector<int> steps(kEnvs, 0);
  std::vector<std::vector<float>> last(kEnvs);
  const auto receive = [&]() -> std::vector<int> {
    const absl::Status status = source->Recv();
    EXPECT_TRUE(status.ok()) << status;
    const std::vector<int> ids(source->env_ids().begin(),
                               source->env_ids().end());
    for (size_t row = 0; row < ids.size(); ++row) {
      last[ids[row]] = source->Result(static_cast<int>(row)).observations;
    }
    return ids;
  };
  // About 50 steps per env: each crosses an episode end (max_cycles 40).
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(60);
  for (int round = 0; round < 100; ++round) {
    ASSERT_LT(std::chrono::steady_clock::now(), deadline) << "round " << round;
    const std::vector<int> ids = receive();
    std::vector<int32_t> actions;
    for (int env : ids) {
      const std::vector<int32_t> mine = ActionsOfEnv(env, steps[env]++);
      actions.insert(actions.end(), mine.begin(), mine.end());
    }
    ASSERT_TRUE(source->Send(absl::MakeConstSpan(actions), ids).ok());
  }
  // Nothing left in flight: two Recvs without Sends return the four envs.
  receive();
  receive();
  for (int env = 0; env < kEnvs; ++env) {
    SCOPED_TRACE(env);
    absl::StatusOr<std::string> snapshot = source->EnvSnapshot(env);
    ASSERT_TRUE(snapshot.ok()) << snapshot.status();
    absl::StatusOr<std::vector<float>> observations =
        target->RestoreEnv(env, *snapshot);
    ASSERT_TRUE(observations.ok()) << observations.status();
    EXPECT_EQ(*observations, last[env]);
    EXPECT_EQ(*target->EnvSnapshot(env), *snapshot);
  }
  for (int step = 0; step < 20; ++step) {
    const std::vector<int32_t> actions = ActionsOf(step, kEnvs);
    ASSERT_TRUE(source->Step(absl::MakeConstSpan(actions)).ok());
    ASSERT_TRUE(target->Step(absl::MakeConstSpan(actions)).ok());
    ASSERT_TRUE(SameBits(std::vector<float>(target->observations().begin(),
                                            target->observations().end()),
                         std::vector<float>(source->observations().begin(),
                                            source->observations().end())))
        << "step " << step;
  }
}

TEST_F(EnvSnapshotTest,
       DamagedOrForeignSnapshotsAreRefusedAndTheEnvIsUntouched) {
  Client client = ClientOn(0);
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(client, 2, SmallConfig());
  absl::StatusOr<VectorEnv> three =
      VectorEnv::Create(client, 1, SmallConfig(3));
  ASSERT_TRUE(envs.ok() && three.ok());
  ASSERT_TRUE(envs->Reset(uint64_t{8}).ok());
  ASSERT_TRUE(three->Reset(uint64_t{8}).ok());
  for (int step = 0; step < 10; ++step) {
    ASSERT_TRUE(envs->Step(absl::MakeConstSpan(ActionsOf(step, 2))).ok());
  }
  const absl::StatusOr<std::string> snapshot = envs->EnvSnapshot(0);
  const absl::StatusOr<std::string> foreign = three->EnvSnapshot(0);
  ASSERT_TRUE(snapshot.ok() && foreign.ok());
  const std::vector<std::string> names = envs->names();

  struct Refusal {
    const char* label;
    std::string snapshot;
    absl::StatusCode code;
    const char* says;
  };
  std::string flipped = *snapshot;
  flipped[flipped.size() / 2] ^= 0x10;
  const std::vector<Refusal> refusals = {
      {"damaged", flipped, absl::StatusCode::kInvalidArgument,
       "snapshot is damaged: its CRC-32"},
      {"bad magic", "XXXX" + snapshot->substr(4),
       absl::StatusCode::kInvalidArgument, "does not start with \"MLLS\""},
      {"other format version",
       Edited(*snapshot, [](std::string* s) { (*s)[4] = 2; }),
       absl::StatusCode::kInvalidArgument, "format version 2"},
      {"truncated",
       Edited(*snapshot, [](std::string* s) { s->resize(s->size() - 30); }),
       absl::StatusCode::kInvalidArgument, "snapshot is truncated in its"},
      {"other options", *foreign, absl::StatusCode::kInvalidArgument,
       "other options (n_landers: 3"},
      // Bytes 6-7 after the magic and format version: the protocol major.
      {"other protocol major",
       Edited(*snapshot, [](std::string* s) { (*s)[6] += 1; }),
       absl::StatusCode::kInvalidArgument,
       "restore it on a server of protocol "},
      {"other bits",
       Edited(*snapshot, [](std::string* s) { (*s)[s->size() - 1] ^= 0x01; }),
       absl::StatusCode::kDataLoss, "env 1 (restored): replaying its 10"},
  };
  for (const Refusal& refusal : refusals) {
    SCOPED_TRACE(refusal.label);
    absl::StatusOr<std::vector<float>> restored =
        envs->RestoreEnv(1, refusal.snapshot);
    EXPECT_EQ(restored.status().code(), refusal.code) << restored.status();
    EXPECT_THAT(std::string(restored.status().message()),
                HasSubstr(refusal.says));
    EXPECT_EQ(envs->names(), names);
  }
  // Nothing else harmed: the envs step on, their records whole.
  ASSERT_TRUE(envs->Step(absl::MakeConstSpan(ActionsOf(10, 2))).ok());
  EXPECT_TRUE(envs->EnvSnapshot(1).ok());
  EXPECT_EQ(envs->RestoreEnv(2, *snapshot).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_F(EnvSnapshotTest, RecordsThatCannotRecreateTheirEnvSaySo) {
  Client client = ClientOn(0);
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Create(client, 2, SmallConfig(1), /*batch_size=*/1);
  ASSERT_TRUE(envs.ok());
  absl::StatusOr<std::string> snapshot = envs->EnvSnapshot(0);
  EXPECT_EQ(snapshot.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(snapshot.status().message()),
              HasSubstr("env 0 (envs/"));
  EXPECT_THAT(std::string(snapshot.status().message()),
              HasSubstr("never reset (no known seed)"));
  // Not while any env is in flight; Send/Recv steps are recorded.
  ASSERT_TRUE(envs->AsyncReset(uint64_t{2}).ok());
  snapshot = envs->EnvSnapshot(0);
  EXPECT_EQ(snapshot.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(snapshot.status().message()), HasSubstr("Recv them"));
  ASSERT_TRUE(envs->Recv().ok());
  ASSERT_TRUE(envs->Recv().ok());
  ASSERT_TRUE(
      envs->Send(absl::MakeConstSpan(std::vector<int32_t>{1}), {1}).ok());
  ASSERT_TRUE(envs->Recv().ok());
  EXPECT_TRUE(envs->EnvSnapshot(0).ok());
  EXPECT_TRUE(envs->EnvSnapshot(1).ok());
  // Past 100,000 operations since the seeded reset.
  ASSERT_TRUE(envs->Reset(uint64_t{3}).ok());
  const std::vector<int32_t> actions(2, 0);
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::minutes(5);
  for (int step = 0; step <= 100000; ++step) {
    ASSERT_LT(std::chrono::steady_clock::now(), deadline) << "step " << step;
    ASSERT_TRUE(envs->Step(absl::MakeConstSpan(actions)).ok());
  }
  snapshot = envs->EnvSnapshot(1);
  EXPECT_EQ(snapshot.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(snapshot.status().message()),
              HasSubstr("passed 100000 operations"));
  ASSERT_TRUE(envs->Reset(uint64_t{3}).ok());
  EXPECT_TRUE(envs->EnvSnapshot(1).ok());
}

}  // namespace
}  // namespace mll::client

// VectorEnv and the Session stream under it, against real servers: the same
// bits as the core in-process for every env (auto-resets included), whatever
// the transport (shared memory, the gRPC stream) or the number of servers;
// several requests in flight on one stream; and the errors.
#include "mll/vector_env.h"

#include <algorithm>
#include <cstring>
#include <memory>
#include <random>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "channel.h"
#include "core_bridge.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/core/env.h"
#include "server_process.h"
#include "session_stream.h"

namespace mll::client {
namespace {

using ::testing::HasSubstr;
using ::testing::StartsWith;

class VectorEnvTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    for (int i = 0; i < 2; ++i) {
      absl::StatusOr<std::unique_ptr<ServerProcess>> server =
          ServerProcess::Start(MLL_SERVER_PATH, {"--threads=2"});
      ASSERT_TRUE(server.ok()) << server.status();
      servers_.push_back(server->release());
    }
  }
  static void TearDownTestSuite() {
    for (ServerProcess* server : servers_) delete server;
    servers_.clear();
  }

  static Client ClientOf(int n_servers, SessionTransport transport) {
    ClientOptions options;
    options.session_transport = transport;
    std::vector<std::string> addresses;
    for (int i = 0; i < n_servers; ++i) {
      addresses.push_back(servers_[i]->address());
    }
    absl::StatusOr<Client> client = Client::Create(addresses, options);
    EXPECT_TRUE(client.ok()) << client.status();
    return *std::move(client);
  }

  static inline std::vector<ServerProcess*> servers_;
};

template <typename T>
bool SameBits(absl::Span<const T> a, absl::Span<const T> b) {
  return a.size() == b.size() &&
         std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0;
}

struct Flight {
  const char* label;
  int n_servers;
  SessionTransport transport;
  bool continuous;
};

// 6 envs of 2 landers, random actions for 300 steps (several episodes each,
// so auto-resets happen), against 6 core envs stepped in-process: the core
// env of an auto-reset row is reset without a seed, as the server does.
TEST_F(VectorEnvTest, EveryEnvFollowsTheCoreBitForBitOnEveryTransport) {
  for (const Flight& flight :
       {Flight{"shared memory, one server", 1, SessionTransport::kSharedMemory,
               false},
        Flight{"stream, one server", 1, SessionTransport::kNative, false},
        Flight{"shared memory, two servers", 2, SessionTransport::kSharedMemory,
               false},
        Flight{"stream, two servers, continuous", 2, SessionTransport::kNative,
               true}}) {
    SCOPED_TRACE(flight.label);
    constexpr int kEnvs = 6;
    constexpr int kLanders = 2;
    core::EnvConfig config;
    config.n_landers = kLanders;
    config.continuous = flight.continuous;
    config.max_cycles = 120;
    Client client = ClientOf(flight.n_servers, flight.transport);
    absl::StatusOr<VectorEnv> envs =
        VectorEnv::Create(client, kEnvs, RemoteConfigFrom(config));
    ASSERT_TRUE(envs.ok()) << envs.status();
    EXPECT_EQ(envs->transport(), flight.transport == SessionTransport::kNative
                                     ? "native"
                                     : "shared_memory");
    // Placed by load: every server used, each env on one of them.
    std::set<std::string> used;
    for (int env = 0; env < kEnvs; ++env) used.insert(envs->address(env));
    EXPECT_EQ(used.size(), static_cast<size_t>(flight.n_servers));
    for (int server = 0; server < flight.n_servers; ++server) {
      EXPECT_EQ(used.count(servers_[server]->address()), 1u);
    }
    std::vector<std::unique_ptr<core::Env>> cores;
    std::vector<core::StepResult> core_results(kEnvs);
    ASSERT_TRUE(envs->Reset(uint64_t{40}).ok());
    for (int env = 0; env < kEnvs; ++env) {
      cores.push_back(*core::Env::Create(config));
      cores[env]->Reset(40 + env, &core_results[env]);
    }
    std::mt19937_64 rng(7);
    const int per_env = kLanders * (flight.continuous ? 2 : 1);
    std::vector<int32_t> discrete(kEnvs * per_env);
    std::vector<float> continuous(kEnvs * per_env);
    int auto_resets = 0;
    for (int step = 0; step < 300; ++step) {
      for (int32_t& a : discrete) a = static_cast<int32_t>(rng() % 4);
      for (float& a : continuous) {
        a = std::uniform_real_distribution<float>(-1, 1)(rng);
      }
      ASSERT_TRUE((flight.continuous
                       ? envs->Step(absl::MakeConstSpan(continuous))
                       : envs->Step(absl::MakeConstSpan(discrete)))
                      .ok());
      for (int env = 0; env < kEnvs; ++env) {
        SCOPED_TRACE(testing::Message() << "step " << step << ", env " << env);
        const bool was_over = core_results[env].episode_over;
        if (was_over) {
          cores[env]->Reset(std::nullopt, &core_results[env]);
          ++auto_resets;
        } else {
          const absl::Span<const int32_t> d =
              flight.continuous ? absl::Span<const int32_t>()
                                : absl::MakeConstSpan(discrete).subspan(
                                      env * per_env, per_env);
          const absl::Span<const float> c =
              flight.continuous ? absl::MakeConstSpan(continuous)
                                      .subspan(env * per_env, per_env)
                                : absl::Span<const float>();
          ASSERT_TRUE(cores[env]->Step({d, c}, &core_results[env]).ok());
        }
        const StepData remote = envs->Result(env);
        ASSERT_EQ(remote.auto_reset, was_over);
        ASSERT_TRUE(
            SameBits(absl::MakeConstSpan(core_results[env].observations),
                     absl::MakeConstSpan(remote.observations)));
        ASSERT_TRUE(SameBits(absl::MakeConstSpan(core_results[env].rewards),
                             absl::MakeConstSpan(remote.rewards)));
        ASSERT_EQ(remote.episode_over, core_results[env].episode_over);
        for (int a = 0; a < kLanders; ++a) {
          ASSERT_EQ(remote.terminations[a], core_results[env].terminations[a]);
          ASSERT_EQ(remote.stepped[a],
                    was_over ? 0 : core_results[env].stepped[a]);
        }
      }
    }
    EXPECT_GT(auto_resets, kEnvs);  // Every env flew several episodes.
  }
}

// The Session stream itself: three requests sent before any answer is read,
// answers taken out of order (the early ones are kept for their Receive), on
// both transports.
TEST_F(VectorEnvTest, SeveralRequestsAreInFlightOnOneStream) {
  for (SessionTransport transport :
       {SessionTransport::kSharedMemory, SessionTransport::kNative}) {
    SCOPED_TRACE(SessionTransportName(transport));
    internal::SessionStream stream(
        internal::OpenChannel(servers_[0]->address(), ClientOptions()), "",
        "server under test", transport);
    v1::SessionRequest create;
    create.mutable_create_env()->mutable_config()->set_n_landers(2);
    absl::StatusOr<uint64_t> created = stream.Send(create);
    ASSERT_TRUE(created.ok()) << created.status();
    v1::SessionResponse env;
    ASSERT_TRUE(stream.Receive(*created, &env).ok());
    EXPECT_EQ(stream.transport_name(), SessionTransportName(transport));

    v1::SessionRequest reset;
    reset.mutable_reset_env()->set_name(env.env().name());
    reset.mutable_reset_env()->set_seed(5);
    v1::SessionRequest get;
    get.mutable_get_env()->set_name(env.env().name());
    v1::SessionRequest unknown;
    unknown.mutable_get_env()->set_name("envs/unknown");
    const absl::StatusOr<uint64_t> first = stream.Send(reset);
    const absl::StatusOr<uint64_t> second = stream.Send(get);
    const absl::StatusOr<uint64_t> third = stream.Send(unknown);
    ASSERT_TRUE(first.ok() && second.ok() && third.ok());
    EXPECT_EQ(stream.in_flight(), 3);
    v1::SessionResponse answer;
    EXPECT_EQ(stream.Receive(*third, &answer).code(),
              absl::StatusCode::kNotFound);
    ASSERT_TRUE(stream.Receive(*second, &answer).ok());
    EXPECT_TRUE(answer.env().episode_started());
    ASSERT_TRUE(stream.Receive(*first, &answer).ok());
    EXPECT_EQ(answer.reset_env().data().observations().shape(0), 2);
    EXPECT_EQ(stream.in_flight(), 0);
    absl::string_view bytes;
    EXPECT_EQ(stream.ReceiveBytes(&bytes, absl::Seconds(1))->code(),
              absl::StatusCode::kFailedPrecondition);
  }
}

// Requests in flight when the server dies each get its UNAVAILABLE, also
// after a send has tried to reopen the stream and failed (the server is gone).
TEST(SessionStreamTest, RequestsLostWithTheServerStayLostAfterAFailedReopen) {
  for (SessionTransport transport :
       {SessionTransport::kSharedMemory, SessionTransport::kNative}) {
    SCOPED_TRACE(SessionTransportName(transport));
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH, {"--threads=1"});
    ASSERT_TRUE(server.ok()) << server.status();
    internal::SessionStream stream(
        internal::OpenChannel((*server)->address(), ClientOptions()), "",
        "server under test", transport);
    v1::SessionRequest create;
    create.mutable_create_env()->mutable_config()->set_n_landers(1);
    const absl::StatusOr<uint64_t> created = stream.Send(create);
    ASSERT_TRUE(created.ok()) << created.status();
    v1::SessionResponse env;
    ASSERT_TRUE(stream.Receive(*created, &env).ok());
    v1::SessionRequest get;
    get.mutable_get_env()->set_name(env.env().name());

    (*server)->Pause();
    const absl::StatusOr<uint64_t> first = stream.Send(get);
    const absl::StatusOr<uint64_t> second = stream.Send(get);
    ASSERT_TRUE(first.ok() && second.ok());
    (*server)->Kill();
    v1::SessionResponse answer;
    EXPECT_EQ(stream.Receive(*first, &answer).code(),
              absl::StatusCode::kUnavailable);
    EXPECT_FALSE(stream.Send(get).ok());  // No server to reopen the stream on.
    EXPECT_EQ(stream.Receive(*second, &answer).code(),
              absl::StatusCode::kUnavailable);
  }
}

// EnvPool's async API: with batch_size 3 of 7 envs over two servers, every
// env's results equal those of Step for the same actions, through auto-resets.
TEST_F(VectorEnvTest, AsyncApiGivesEachEnvTheSynchronousTrajectory) {
  constexpr int kEnvs = 7;
  constexpr int kBatch = 3;
  constexpr int kSteps = 150;
  RemoteEnvConfig config;
  config.n_landers = 2;
  std::mt19937_64 rng(11);
  std::vector<int32_t> table(3 * kSteps * kEnvs * 2);
  for (int32_t& a : table) a = static_cast<int32_t>(rng() % 4);
  const auto actions_of = [&](int step, int env) {
    return absl::MakeConstSpan(table).subspan((step * kEnvs + env) * 2, 2);
  };
  for (SessionTransport transport :
       {SessionTransport::kSharedMemory, SessionTransport::kNative}) {
    SCOPED_TRACE(SessionTransportName(transport));
    Client client = ClientOf(2, transport);
    // The reference: Step, env by env rows of the table; envs the async
    // API serves first may run ahead, so it goes 3x as far.
    absl::StatusOr<VectorEnv> sync = VectorEnv::Create(client, kEnvs, config);
    ASSERT_TRUE(sync.ok()) << sync.status();
    ASSERT_TRUE(sync->Reset(uint64_t{5}).ok());
    std::vector<std::vector<std::vector<float>>> expected(kEnvs);
    for (int env = 0; env < kEnvs; ++env) {
      expected[env].push_back(sync->Result(env).observations);
    }
    for (int step = 0; step < 3 * kSteps; ++step) {
      ASSERT_TRUE(sync->Step(absl::MakeConstSpan(table).subspan(
                                 step * kEnvs * 2, kEnvs * 2))
                      .ok());
      for (int env = 0; env < kEnvs; ++env) {
        expected[env].push_back(sync->Result(env).observations);
      }
    }
    absl::StatusOr<VectorEnv> envs =
        VectorEnv::Create(client, kEnvs, config, kBatch);
    ASSERT_TRUE(envs.ok()) << envs.status();
    EXPECT_EQ(envs->batch_size(), kBatch);
    ASSERT_TRUE(envs->AsyncReset(uint64_t{5}).ok());
    std::vector<int> sent(kEnvs, 0);
    std::vector<int> received(kEnvs, 0);
    while (*std::min_element(sent.begin(), sent.end()) < kSteps) {
      ASSERT_TRUE(envs->Recv().ok());
      const std::vector<int> ids(envs->env_ids().begin(),
                                 envs->env_ids().end());
      ASSERT_EQ(ids.size(), static_cast<size_t>(kBatch));
      std::vector<int32_t> actions;
      for (int row = 0; row < kBatch; ++row) {
        const int env = ids[row];
        ASSERT_EQ(envs->Result(row).observations,
                  expected[env][received[env]++])
            << "env " << env << ", result " << received[env] - 1;
        for (int32_t a : actions_of(sent[env]++, env)) actions.push_back(a);
      }
      ASSERT_TRUE(envs->Send(absl::MakeConstSpan(actions), ids).ok());
    }
  }
}

TEST_F(VectorEnvTest, AsyncApiMisuseGetsClearErrors) {
  Client client = ClientOf(1, SessionTransport::kAuto);
  RemoteEnvConfig config;
  config.n_landers = 1;
  EXPECT_EQ(VectorEnv::Create(client, 4, config, 5).status().code(),
            absl::StatusCode::kInvalidArgument);
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(client, 4, config, 2);
  ASSERT_TRUE(envs.ok()) << envs.status();
  absl::Status status = envs->Recv();
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(status.message()), HasSubstr("batch_size = 2"));
  ASSERT_TRUE(envs->AsyncReset(uint64_t{0}).ok());
  const std::vector<int32_t> two(2, 0);
  status = envs->Send(absl::MakeConstSpan(two), {0, 1});
  EXPECT_EQ(status.code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(status.message()), HasSubstr("env 0 has a step"));
  ASSERT_TRUE(envs->Recv().ok());
  EXPECT_EQ(envs->Send(absl::MakeConstSpan(two), {0, 4}).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(envs->Send(absl::MakeConstSpan(two), {1, 1}).code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(envs->Step(absl::MakeConstSpan(std::vector<int32_t>(4, 0))).code(),
            absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(envs->Send(absl::MakeConstSpan(two), {0, 1}).ok());
  ASSERT_TRUE(envs->Recv().ok());
  EXPECT_THAT(std::vector<int>(envs->env_ids().begin(), envs->env_ids().end()),
              ::testing::ElementsAre(2, 3));
}

// Opening a shared-memory session races the attach request's write
// completion against the region's first use; many short sessions make a
// mistake there show (as a hang, which ctest's timeout reports).
TEST_F(VectorEnvTest, ManyShortSharedMemorySessionsEachStep) {
  Client client = ClientOf(1, SessionTransport::kSharedMemory);
  RemoteEnvConfig config;
  config.n_landers = 1;
  const std::vector<int32_t> actions(2, 2);
  for (int session = 0; session < 60; ++session) {
    absl::StatusOr<VectorEnv> envs = VectorEnv::Create(client, 2, config);
    ASSERT_TRUE(envs.ok()) << envs.status();
    ASSERT_TRUE(envs->Reset(uint64_t{1}).ok());
    for (int step = 0; step < 3; ++step) {
      ASSERT_TRUE(envs->Step(absl::MakeConstSpan(actions)).ok());
    }
  }
}

TEST_F(VectorEnvTest, BadActionsAreRefusedNamingTheSizeAndType) {
  Client client = ClientOf(1, SessionTransport::kAuto);
  RemoteEnvConfig config;
  config.n_landers = 3;
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(client, 2, config);
  ASSERT_TRUE(envs.ok()) << envs.status();
  ASSERT_TRUE(envs->Reset(uint64_t{0}).ok());
  std::vector<int32_t> five(5, 0);
  absl::Status status = envs->Step(absl::MakeConstSpan(five));
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()), HasSubstr("actions has 5 values"));
  EXPECT_THAT(std::string(status.message()), HasSubstr("= 6"));
  std::vector<float> continuous(12, 0.0f);
  status = envs->Step(absl::MakeConstSpan(continuous));
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()), HasSubstr("discrete"));
  std::vector<int32_t> out_of_range(6, 9);
  status = envs->Step(absl::MakeConstSpan(out_of_range));
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(status.message()), StartsWith("env 0 ("));
  EXPECT_FALSE(VectorEnv::Create(client, 0).ok());
  std::vector<uint64_t> seeds(3, 0);
  EXPECT_EQ(envs->Reset(absl::MakeConstSpan(seeds)).code(),
            absl::StatusCode::kInvalidArgument);
}

// With failover off (on, failover_test.cc: the env is recreated).
TEST_F(VectorEnvTest, AnEnvDeletedBehindItsBackFailsNamingItAndTheOthersStep) {
  Client client = ClientOf(2, SessionTransport::kAuto);
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Create(client, 4, {}, 0, /*failover=*/false);
  ASSERT_TRUE(envs.ok()) << envs.status();
  ASSERT_TRUE(envs->Reset(uint64_t{3}).ok());
  const std::string deleted = envs->names()[3];
  ASSERT_TRUE(client.DeleteEnv(deleted).ok());
  std::vector<int32_t> actions(4 * 3, 0);
  const absl::Status status = envs->Step(absl::MakeConstSpan(actions));
  EXPECT_EQ(status.code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(std::string(status.message()),
              StartsWith("env 3 (" + deleted + "): "));
  EXPECT_EQ(envs->Result(0).episode_lengths[0], 1);
}

TEST_F(VectorEnvTest, SharedMemoryAskedForByNameIsRefusedWithTheReason) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server = ServerProcess::Start(
      MLL_SERVER_PATH, {"--threads=1", "--shared_memory_sessions=0"});
  ASSERT_TRUE(server.ok()) << server.status();
  ClientOptions options;
  options.session_transport = SessionTransport::kSharedMemory;
  absl::StatusOr<Client> client = Client::Create((*server)->address(), options);
  ASSERT_TRUE(client.ok());
  absl::StatusOr<VectorEnv> envs = VectorEnv::Create(*client, 2);
  EXPECT_EQ(envs.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(std::string(envs.status().message()),
              HasSubstr("transport \"shared_memory\": server "));
  EXPECT_THAT(std::string(envs.status().message()),
              HasSubstr("refused shared memory"));
  options.session_transport = SessionTransport::kAuto;
  client = Client::Create((*server)->address(), options);
  ASSERT_TRUE(client.ok());
  envs = VectorEnv::Create(*client, 2);
  ASSERT_TRUE(envs.ok()) << envs.status();
  EXPECT_EQ(envs->transport(), "native");
}

TEST_F(VectorEnvTest, AttachFliesExistingEnvsOfOneShape) {
  absl::StatusOr<Client> client = Client::Create(servers_[0]->address());
  ASSERT_TRUE(client.ok());
  RemoteEnvConfig two;
  two.n_landers = 2;
  absl::StatusOr<RemoteEnv> a = client->CreateEnv(two);
  absl::StatusOr<RemoteEnv> b = client->CreateEnv(two);
  absl::StatusOr<RemoteEnv> c = client->CreateEnv();
  ASSERT_TRUE(a.ok() && b.ok() && c.ok());
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Attach(*client, {a->name(), b->name()});
  ASSERT_TRUE(envs.ok()) << envs.status();
  ASSERT_TRUE(envs->Reset(uint64_t{9}).ok());
  std::vector<int32_t> actions(4, 2);
  ASSERT_TRUE(envs->Step(absl::MakeConstSpan(actions)).ok());
  EXPECT_EQ(envs->rewards().size(), 4u);
  absl::StatusOr<VectorEnv> mixed =
      VectorEnv::Attach(*client, {a->name(), c->name()});
  EXPECT_EQ(mixed.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(std::string(mixed.status().message()), HasSubstr("names[1]"));
}

// The client's batch handles (session_stream.h): a list of envs goes out
// with its names and a handle until a request declaring it is answered OK,
// then as the handle alone with the actions; each list has its own handle;
// past kMaxHandle lists the least recently used handle is declared anew (a
// late answer to its old declaration counts for nothing); a new session
// declares again; a list past kMaxDeclaredEnvs and any other request go out
// as they are; the caller's request is left as it was.
TEST(BatchHandlesTest, DeclaresEachListUntilAnsweredThenSendsTheHandle) {
  internal::BatchHandles handles;
  uint64_t sequence = 0;
  const auto list = [](int first, int count) {
    std::vector<std::string> names;
    for (int k = first; k < first + count; ++k) {
      names.push_back(absl::StrCat("envs/", k));
    }
    return names;
  };
  // Sends a packed batch of `names`; the PackedSteps that went out.
  const auto send = [&](const std::vector<std::string>& names) {
    v1::SessionRequest request;
    request.set_sequence(++sequence);
    v1::PackedSteps* packed = request.mutable_step_batch()->mutable_packed();
    for (const std::string& name : names) packed->add_names(name);
    packed->mutable_actions()->set_data("four");
    const v1::SessionRequest before = request;
    v1::SessionRequest sent;
    EXPECT_TRUE(sent.ParseFromString(handles.Serialize(request)));
    EXPECT_EQ(request.SerializeAsString(), before.SerializeAsString());
    EXPECT_EQ(sent.step_batch().packed().actions().data(), "four");
    return sent.step_batch().packed();
  };
  const std::vector<std::string> a = list(0, 3), b = list(3, 2);
  v1::PackedSteps sent = send(a);
  EXPECT_EQ(sent.handle(), 1u);
  EXPECT_EQ(sent.names_size(), 3);
  const uint64_t declared = sequence;
  EXPECT_EQ(send(a).names_size(), 3);  // Not answered yet: declared again.
  handles.Answered(sequence, /*ok=*/false);
  EXPECT_EQ(send(a).names_size(), 3);
  handles.Answered(declared, /*ok=*/true);
  sent = send(a);
  EXPECT_EQ(sent.handle(), 1u);
  EXPECT_EQ(sent.names_size(), 0);
  sent = send(b);
  EXPECT_EQ(sent.handle(), 2u);
  EXPECT_EQ(sent.names_size(), 2);

  handles.Clear();  // A new session.
  sent = send(a);
  EXPECT_EQ(sent.handle(), 1u);
  EXPECT_EQ(sent.names_size(), 3);
  handles.Answered(sequence, true);
  // Lists 1..63 more take handles 2..64; list a stays the oldest used.
  for (int k = 1; k < static_cast<int>(internal::BatchHandles::kMaxHandle);
       ++k) {
    sent = send(list(100 * k, 1));
    EXPECT_EQ(sent.handle(), static_cast<uint32_t>(k + 1));
    handles.Answered(sequence, true);
  }
  EXPECT_EQ(send(list(100, 1)).names_size(), 0);
  sent = send(b);  // Takes a's handle, the least recently used.
  EXPECT_EQ(sent.handle(), 1u);
  EXPECT_EQ(sent.names_size(), 2);
  const uint64_t b_declared = sequence;
  for (int k = 1; k < static_cast<int>(internal::BatchHandles::kMaxHandle);
       ++k) {
    EXPECT_EQ(send(list(100 * k, 1)).names_size(), 0);
  }
  const std::vector<std::string> c = list(7000, 4);
  sent = send(c);  // Takes b's handle before b's declaration is answered.
  EXPECT_EQ(sent.handle(), 1u);
  EXPECT_EQ(sent.names_size(), 4);
  handles.Answered(b_declared, true);  // Counts for b's list only.
  EXPECT_EQ(send(c).names_size(), 4);

  const v1::PackedSteps huge =
      send(list(0, internal::BatchHandles::kMaxDeclaredEnvs + 1));
  EXPECT_EQ(huge.handle(), 0u);
  EXPECT_EQ(huge.names_size(),
            static_cast<int>(internal::BatchHandles::kMaxDeclaredEnvs) + 1);
  v1::SessionRequest reset;
  reset.mutable_reset_env()->set_name("envs/1");
  EXPECT_EQ(handles.Serialize(reset), reset.SerializeAsString());
}

}  // namespace
}  // namespace mll::client

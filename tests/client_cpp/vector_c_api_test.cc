// The C interface of VectorEnv (client_cpp/native/vector_c_api.h, what the
// Python vector env calls), against real mll_server processes: its column
// table; the same bits as the C++ VectorEnv for the same seed and actions,
// through reset, step_async/step_wait and async_reset/send/recv; waits that
// time out return PENDING and lose nothing; bad input gets its code and a
// message naming it; snapshots restore to the same bits; failover events
// queue for take_events instead of going to stderr.
#include "vector_c_api.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <functional>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_join.h"
#include "absl/types/span.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.pb.h"
#include "mll/vector_env.h"
#include "server_process.h"
#include "suite_server.h"

namespace mll::client {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

constexpr int kLanders = 2;
constexpr int kOk = 0;
constexpr int kInvalidArgument =
    static_cast<int>(absl::StatusCode::kInvalidArgument);
constexpr int kFailedPrecondition =
    static_cast<int>(absl::StatusCode::kFailedPrecondition);

struct HandleDeleter {
  void operator()(mll_vector_env* env) const { mll_vector_env_free(env); }
};
using Handle = std::unique_ptr<mll_vector_env, HandleDeleter>;

// Short episodes, so that every run crosses auto-resets.
v1::EnvConfig SmallConfig() {
  v1::EnvConfig config;
  config.set_n_landers(kLanders);
  config.set_max_cycles(30);
  return config;
}

RemoteEnvConfig SmallRemoteConfig() {
  RemoteEnvConfig config;
  config.n_landers = kLanders;
  config.max_cycles = 30;
  return config;
}

Handle NewHandle(const std::string& addresses, int num_envs, int batch_size = 0,
                 int failover = -1, int transport = MLL_NATIVE_TRANSPORT_AUTO,
                 const std::string& config = SmallConfig().SerializeAsString(),
                 double step_timeout_s = -1,
                 double rediscover_interval_s = -1) {
  return Handle(mll_vector_env_new(
      addresses.c_str(), nullptr, 0, nullptr, nullptr, transport, config.data(),
      config.size(), num_envs, batch_size, failover, step_timeout_s,
      rediscover_interval_s));
}

VectorEnv NewVectorEnv(const std::vector<std::string>& addresses, int num_envs,
                       int batch_size = 0,
                       SessionTransport transport = SessionTransport::kAuto) {
  ClientOptions options;
  options.session_transport = transport;
  absl::StatusOr<Client> client = Client::Create(addresses, options);
  EXPECT_TRUE(client.ok()) << client.status();
  absl::StatusOr<VectorEnv> envs =
      VectorEnv::Create(*client, num_envs, SmallRemoteConfig(), batch_size);
  EXPECT_TRUE(envs.ok()) << envs.status();
  return *std::move(envs);
}

std::vector<int32_t> ActionsOf(int step, int rows) {
  std::mt19937_64 rng(500 + step);
  std::vector<int32_t> actions(rows * kLanders);
  for (int32_t& a : actions) a = static_cast<int32_t>(rng() % 4);
  return actions;
}

// Bytes of one element of a column of dtype `dtype`.
size_t ElementSize(int dtype) { return dtype == v1::DTYPE_UINT8 ? 1 : 4; }

// The latest results of `env`, one byte string per column, in column order,
// sized from the column table.
std::vector<std::string> ResultsOf(const mll_vector_env* env) {
  const int rows = mll_vector_env_rows(env);
  const int count = mll_vector_env_column_count();
  std::vector<std::string> columns(count);
  std::vector<void*> buffers(count);
  for (int c = 0; c < count; ++c) {
    const size_t items =
        static_cast<size_t>(rows) *
        (mll_vector_env_column_per_agent(c) ? mll_vector_env_n_landers(env)
                                            : 1) *
        mll_vector_env_column_width(c);
    columns[c].assign(items * ElementSize(mll_vector_env_column_dtype(c)),
                      '\x55');
    buffers[c] = columns[c].data();
  }
  mll_vector_env_results(env, buffers.data());
  return columns;
}

template <typename T>
std::string BytesOf(absl::Span<const T> values) {
  return std::string(reinterpret_cast<const char*>(values.data()),
                     values.size() * sizeof(T));
}

// The C++ VectorEnv's latest results, in the columns' documented order.
std::vector<std::string> ResultsOf(const VectorEnv& envs) {
  return {BytesOf(envs.observations()),    BytesOf(envs.rewards()),
          BytesOf(envs.terminations()),    BytesOf(envs.truncations()),
          BytesOf(envs.active()),          BytesOf(envs.outcomes()),
          BytesOf(envs.episode_returns()), BytesOf(envs.episode_lengths()),
          BytesOf(envs.auto_reset()),      BytesOf(envs.episode_over()),
          BytesOf(envs.env_ids())};
}

// Waits in slices of `slice_ms` (as the Python client does, to handle its
// signals between them) until `wait` returns something other than PENDING,
// at most `bound` slices; the code it returned.
int WaitInSlices(const std::function<int(int)>& wait, int slice_ms = 100,
                 int bound = 600) {
  int code = MLL_NATIVE_STREAM_PENDING;
  for (int k = 0; k < bound && code == MLL_NATIVE_STREAM_PENDING; ++k) {
    code = wait(slice_ms);
  }
  return code;
}

class VectorCApiTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() { server_ = StartSuiteServer({"--threads=2"}); }
  static void TearDownTestSuite() {
    delete server_;
    server_ = nullptr;
  }

  static inline ServerProcess* server_ = nullptr;
};

TEST(ColumnTableTest, NamesTypesAndShapesOfTheResultColumns) {
  std::vector<std::string> names;
  std::vector<int> dtypes;
  std::vector<int> per_agent;
  std::vector<int> widths;
  for (int c = 0; c < mll_vector_env_column_count(); ++c) {
    names.push_back(mll_vector_env_column_name(c));
    dtypes.push_back(mll_vector_env_column_dtype(c));
    per_agent.push_back(mll_vector_env_column_per_agent(c));
    widths.push_back(mll_vector_env_column_width(c));
  }
  EXPECT_THAT(names, ElementsAre("observations", "rewards", "terminations",
                                 "truncations", "active", "outcomes",
                                 "episode_returns", "episode_lengths",
                                 "auto_reset", "episode_over", "env_ids"));
  const int f = v1::DTYPE_FLOAT32;
  const int u = v1::DTYPE_UINT8;
  const int i = v1::DTYPE_INT32;
  EXPECT_THAT(dtypes, ElementsAre(f, f, u, u, u, u, f, i, u, u, i));
  EXPECT_THAT(per_agent, ElementsAre(1, 1, 1, 1, 1, 1, 1, 1, 0, 0, 0));
  EXPECT_THAT(widths, ElementsAre(kRemoteObservationSize, 1, 1, 1, 1, 1, 1, 1,
                                  1, 1, 1));
  EXPECT_EQ(mll_vector_env_column_name(mll_vector_env_column_count()), nullptr);
  EXPECT_EQ(mll_vector_env_column_name(-1), nullptr);
}

TEST_F(VectorCApiTest, DescribesTheEnvsAndTheirServers) {
  Handle env = NewHandle(server_->address(), 3);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk)
      << mll_vector_env_message(env.get());
  EXPECT_EQ(mll_vector_env_num_envs(env.get()), 3);
  EXPECT_EQ(mll_vector_env_n_landers(env.get()), kLanders);
  EXPECT_EQ(mll_vector_env_continuous(env.get()), 0);
  EXPECT_EQ(mll_vector_env_batch_size(env.get()), 3);
  EXPECT_EQ(mll_vector_env_failover(env.get()), 0);  // One server.
  const char* data = nullptr;
  size_t size = 0;
  ASSERT_EQ(mll_vector_env_spec(env.get(), &data, &size), kOk);
  v1::Env spec;
  ASSERT_TRUE(spec.ParseFromArray(data, static_cast<int>(size)));
  EXPECT_EQ(spec.name(), mll_vector_env_name(env.get(), 0));
  EXPECT_EQ(spec.config().n_landers(), kLanders);
  EXPECT_EQ(spec.config().max_cycles(), 30);
  EXPECT_TRUE(spec.config().auto_reset());   // Forced on.
  EXPECT_TRUE(spec.config().has_gravity());  // The server's default.
  EXPECT_THAT(spec.possible_agents(), ElementsAre("lander_0", "lander_1"));
  EXPECT_GT(spec.idle_timeout_s(), 0);
  EXPECT_EQ(spec.observation_space().shape(0), kRemoteObservationSize);
  for (int i = 0; i < 3; ++i) {
    EXPECT_THAT(mll_vector_env_name(env.get(), i), HasSubstr("envs/"));
    EXPECT_EQ(std::string(mll_vector_env_env_address(env.get(), i)),
              server_->address());
  }
  EXPECT_EQ(mll_vector_env_name(env.get(), 3), nullptr);
  EXPECT_EQ(mll_vector_env_env_address(env.get(), -1), nullptr);
  ASSERT_EQ(mll_vector_env_server_count(env.get()), 1);
  EXPECT_EQ(std::string(mll_vector_env_server_address(env.get(), 0)),
            server_->address());
  ASSERT_EQ(mll_vector_env_server_info(env.get(), 0, &data, &size), kOk);
  v1::ServerInfo info;
  ASSERT_TRUE(info.ParseFromArray(data, static_cast<int>(size)));
  EXPECT_EQ(info.server_version(), Client::Version());
  EXPECT_EQ(mll_vector_env_server_info(env.get(), 1, &data, &size),
            kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(env.get()), HasSubstr("server is 1"));
  EXPECT_EQ(std::string(mll_vector_env_transport(env.get())), "shared_memory");
  EXPECT_EQ(std::string(mll_vector_env_take_events(env.get())), "");
}

// Reset, then steps through step_async/step_wait, against the C++ VectorEnv
// stepped with Step: every column the same bits, over shared memory and
// over the gRPC stream.
TEST_F(VectorCApiTest, StepsGiveTheSameBitsAsTheCppVectorEnv) {
  for (const auto& [transport, cpp_transport] :
       {std::pair{MLL_NATIVE_TRANSPORT_SHARED_MEMORY,
                  SessionTransport::kSharedMemory},
        std::pair{MLL_NATIVE_TRANSPORT_NATIVE, SessionTransport::kNative}}) {
    SCOPED_TRACE(transport);
    constexpr int kEnvs = 5;
    Handle env = NewHandle(server_->address(), kEnvs, 0, -1, transport);
    ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk)
        << mll_vector_env_message(env.get());
    VectorEnv cpp = NewVectorEnv({server_->address()}, kEnvs, 0, cpp_transport);
    ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 11), kOk);
    ASSERT_TRUE(cpp.Reset(uint64_t{11}).ok());
    EXPECT_EQ(mll_vector_env_rows(env.get()), kEnvs);
    EXPECT_EQ(ResultsOf(env.get()), ResultsOf(cpp));
    int auto_resets = 0;
    for (int step = 0; step < 70; ++step) {
      const std::vector<int32_t> actions = ActionsOf(step, kEnvs);
      ASSERT_EQ(mll_vector_env_step_async(env.get(), actions.data(),
                                          actions.size(), 0),
                kOk)
          << mll_vector_env_message(env.get());
      ASSERT_EQ(WaitInSlices([&](int slice) {
                  return mll_vector_env_step_wait(env.get(), slice);
                }),
                kOk)
          << mll_vector_env_message(env.get());
      ASSERT_TRUE(cpp.Step(absl::MakeConstSpan(actions)).ok());
      ASSERT_EQ(ResultsOf(env.get()), ResultsOf(cpp)) << "step " << step;
      for (uint8_t reset : cpp.auto_reset()) auto_resets += reset;
    }
    EXPECT_GT(auto_resets, 0);
  }
}

TEST_F(VectorCApiTest, AsyncSendRecvGiveTheSameBitsAsTheCppVectorEnv) {
  constexpr int kEnvs = 4;
  constexpr int kBatch = 2;
  Handle env = NewHandle(server_->address(), kEnvs, kBatch);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk)
      << mll_vector_env_message(env.get());
  VectorEnv cpp = NewVectorEnv({server_->address()}, kEnvs, kBatch);
  ASSERT_EQ(mll_vector_env_async_reset(env.get(), 1, 3), kOk);
  ASSERT_TRUE(cpp.AsyncReset(uint64_t{3}).ok());
  EXPECT_EQ(mll_vector_env_in_flight(env.get()), kEnvs);
  for (int round = 0; round < 40; ++round) {
    ASSERT_EQ(mll_vector_env_recv(env.get(), -1), kOk)
        << mll_vector_env_message(env.get());
    ASSERT_TRUE(cpp.Recv().ok());
    EXPECT_EQ(mll_vector_env_rows(env.get()), kBatch);
    ASSERT_EQ(ResultsOf(env.get()), ResultsOf(cpp)) << "round " << round;
    const std::vector<int32_t> actions = ActionsOf(round, kBatch);
    const std::vector<int32_t> ids(cpp.env_ids().begin(), cpp.env_ids().end());
    const std::vector<int64_t> wide(ids.begin(), ids.end());
    ASSERT_EQ(mll_vector_env_send(env.get(), actions.data(), actions.size(), 0,
                                  wide.data(), wide.size()),
              kOk)
        << mll_vector_env_message(env.get());
    ASSERT_TRUE(cpp.Send(absl::MakeConstSpan(actions), ids).ok());
  }
}

// A stopped server answers nothing: each timed wait returns PENDING, and
// once it runs again the results are those of the step sent, not lost and
// not repeated.
TEST_F(VectorCApiTest, WaitsThatTimeOutArePendingAndLoseNothing) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> own =
      ServerProcess::Start(MLL_SERVER_PATH, {"--threads=1"});
  ASSERT_TRUE(own.ok()) << own.status();
  ServerProcess& server = **own;
  constexpr int kEnvs = 4;
  // A step timeout far beyond the waits below: a step_async that waited for
  // the stopped server would take that long.
  constexpr double kStepTimeoutS = 30;
  Handle env = NewHandle(server.address(), kEnvs, /*batch_size=*/2, -1,
                         MLL_NATIVE_TRANSPORT_AUTO,
                         SmallConfig().SerializeAsString(), kStepTimeoutS);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk)
      << mll_vector_env_message(env.get());
  VectorEnv cpp = NewVectorEnv({server_->address()}, kEnvs, 2);
  // step_async / step_wait; step_async returns at once, the server's
  // capabilities (batch handles) being known since the envs were created.
  ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 21), kOk);
  ASSERT_TRUE(cpp.Reset(uint64_t{21}).ok());
  const std::vector<int32_t> actions = ActionsOf(0, kEnvs);
  server.Pause();
  ASSERT_EQ(
      mll_vector_env_step_async(env.get(), actions.data(), actions.size(), 0),
      kOk);
  const auto paused = std::chrono::steady_clock::now();
  for (int k = 0; k < 3; ++k) {
    EXPECT_EQ(mll_vector_env_step_wait(env.get(), 50),
              MLL_NATIVE_STREAM_PENDING);
  }
  EXPECT_LT(std::chrono::steady_clock::now() - paused,
            std::chrono::duration<double>(kStepTimeoutS / 2));
  // Still in flight: nothing else may start.
  EXPECT_EQ(mll_vector_env_reset(env.get(), 0, 0), kFailedPrecondition);
  EXPECT_THAT(mll_vector_env_message(env.get()), HasSubstr("step_wait"));
  server.Resume();
  ASSERT_EQ(WaitInSlices([&](int slice) {
              return mll_vector_env_step_wait(env.get(), slice);
            }),
            kOk)
      << mll_vector_env_message(env.get());
  ASSERT_TRUE(cpp.Step(absl::MakeConstSpan(actions)).ok());
  EXPECT_EQ(ResultsOf(env.get()), ResultsOf(cpp));
  // send / recv.
  ASSERT_EQ(mll_vector_env_async_reset(env.get(), 1, 22), kOk);
  ASSERT_TRUE(cpp.AsyncReset(uint64_t{22}).ok());
  for (int k = 0; k < 2; ++k) {
    ASSERT_EQ(mll_vector_env_recv(env.get(), 0), kOk);  // Already there.
    ASSERT_TRUE(cpp.Recv().ok());
  }
  const std::vector<int32_t> ids = {2, 0, 3, 1};
  const std::vector<int64_t> wide(ids.begin(), ids.end());
  server.Pause();
  ASSERT_EQ(
      mll_vector_env_send(env.get(), actions.data(), 4, 0, wide.data(), 2),
      kOk);
  ASSERT_EQ(mll_vector_env_send(env.get(), actions.data() + 4, 4, 0,
                                wide.data() + 2, 2),
            kOk);
  ASSERT_TRUE(cpp.Send(absl::MakeConstSpan(actions.data(), 4),
                       absl::MakeConstSpan(ids.data(), 2))
                  .ok());
  ASSERT_TRUE(cpp.Send(absl::MakeConstSpan(actions.data() + 4, 4),
                       absl::MakeConstSpan(ids.data() + 2, 2))
                  .ok());
  EXPECT_EQ(mll_vector_env_recv(env.get(), 50), MLL_NATIVE_STREAM_PENDING);
  EXPECT_EQ(mll_vector_env_in_flight(env.get()), kEnvs);
  server.Resume();
  for (int k = 0; k < 2; ++k) {
    ASSERT_EQ(WaitInSlices([&](int slice) {
                return mll_vector_env_recv(env.get(), slice);
              }),
              kOk)
        << mll_vector_env_message(env.get());
    ASSERT_TRUE(cpp.Recv().ok());
    EXPECT_EQ(ResultsOf(env.get()), ResultsOf(cpp)) << "recv " << k;
  }
  EXPECT_EQ(mll_vector_env_in_flight(env.get()), 0);
}

// step_timeout_s is the C++ client's step timeout: a stopped server's step
// fails DEADLINE_EXCEEDED naming it (failover is off with one server).
TEST(VectorCApiStepTimeoutTest, IsTheClientsStepTimeout) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server =
      ServerProcess::Start(MLL_SERVER_PATH, {"--threads=1"});
  ASSERT_TRUE(server.ok()) << server.status();
  Handle env =
      NewHandle((*server)->address(), 2, 0, -1, MLL_NATIVE_TRANSPORT_AUTO,
                SmallConfig().SerializeAsString(), 0.5);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk)
      << mll_vector_env_message(env.get());
  ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 0), kOk);
  (*server)->Pause();
  const std::vector<int32_t> actions(2 * kLanders, 0);
  ASSERT_EQ(
      mll_vector_env_step_async(env.get(), actions.data(), actions.size(), 0),
      kOk);
  EXPECT_EQ(WaitInSlices([&](int slice) {
              return mll_vector_env_step_wait(env.get(), slice);
            }),
            static_cast<int>(absl::StatusCode::kDeadlineExceeded));
  EXPECT_THAT(mll_vector_env_message(env.get()),
              HasSubstr("step timeout 500ms"));
  (*server)->Resume();
}

TEST_F(VectorCApiTest, BadInputGetsItsCodeAndAMessageNamingIt) {
  constexpr int kEnvs = 4;
  Handle env = NewHandle(server_->address(), kEnvs, /*batch_size=*/2);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk);
  const auto message = [&] {
    return std::string(mll_vector_env_message(env.get()));
  };
  EXPECT_EQ(mll_vector_env_step_wait(env.get(), -1), kFailedPrecondition);
  EXPECT_THAT(message(), HasSubstr("without a StepAsync (step_async)"));
  ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 0), kOk);
  const std::vector<int32_t> actions(kEnvs * kLanders + 1, 0);
  EXPECT_EQ(mll_vector_env_step_async(env.get(), actions.data(), 7, 0),
            kInvalidArgument);
  EXPECT_THAT(message(), HasSubstr("actions has 7 values; expected num_envs * "
                                   "n_landers = 8"));
  EXPECT_EQ(mll_vector_env_step_async(env.get(), nullptr, 8, 0),
            kInvalidArgument);
  EXPECT_THAT(message(), HasSubstr("actions is NULL"));
  const std::vector<float> continuous(16, 0.0f);
  EXPECT_EQ(mll_vector_env_step_async(env.get(), continuous.data(), 16, 1),
            kInvalidArgument);
  EXPECT_THAT(message(), HasSubstr("the envs take discrete actions"));
  // Nothing was sent: step_wait still has nothing to wait for.
  EXPECT_EQ(mll_vector_env_step_wait(env.get(), -1), kFailedPrecondition);
  const std::vector<int64_t> out_of_range = {0, 9};
  EXPECT_EQ(mll_vector_env_send(env.get(), actions.data(), 4, 0,
                                out_of_range.data(), 2),
            kInvalidArgument);
  EXPECT_THAT(message(), HasSubstr("env_ids holds 9; allowed: 0..3"));
  // An index no int holds is refused as such, not wrapped onto a valid one.
  const std::vector<int64_t> wrapping = {0, (int64_t{1} << 32) + 1};
  EXPECT_EQ(
      mll_vector_env_send(env.get(), actions.data(), 4, 0, wrapping.data(), 2),
      kInvalidArgument);
  EXPECT_THAT(message(), HasSubstr("env_ids holds 4294967297; allowed: 0..3"));
  const char* data = nullptr;
  size_t size = 0;
  EXPECT_EQ(mll_vector_env_snapshot(env.get(), kEnvs, &data, &size),
            kInvalidArgument);
  EXPECT_THAT(message(), HasSubstr("env index is 4; allowed: 0..3"));
  EXPECT_EQ(mll_vector_env_recv(env.get(), -1), kFailedPrecondition);
  EXPECT_THAT(message(), HasSubstr("batch_size = 2"));
  // A step in flight blocks the other operations, as send does.
  ASSERT_EQ(mll_vector_env_step_async(env.get(), actions.data(), 8, 0), kOk);
  EXPECT_EQ(mll_vector_env_step_async(env.get(), actions.data(), 8, 0),
            kFailedPrecondition);
  EXPECT_EQ(mll_vector_env_send(env.get(), actions.data(), 2, 0,
                                out_of_range.data(), 1),
            kFailedPrecondition);
  EXPECT_THAT(message(), HasSubstr("step_wait"));
  EXPECT_EQ(mll_vector_env_snapshot(env.get(), 0, &data, &size),
            kFailedPrecondition);
  ASSERT_EQ(mll_vector_env_step_wait(env.get(), -1), kOk);

  // Creation failures: the handle holds the status and message.
  Handle not_config = NewHandle(server_->address(), 2, 0, -1,
                                MLL_NATIVE_TRANSPORT_AUTO, "\xff\xff\xff");
  EXPECT_EQ(mll_vector_env_create_status(not_config.get()), kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(not_config.get()),
              HasSubstr("not a serialized mll.v1.EnvConfig"));
  EXPECT_EQ(mll_vector_env_reset(not_config.get(), 0, 0), kInvalidArgument);
  EXPECT_EQ(mll_vector_env_num_envs(not_config.get()), 0);
  v1::EnvConfig too_many;
  too_many.set_n_landers(99);
  Handle bad_option =
      NewHandle(server_->address(), 2, 0, -1, MLL_NATIVE_TRANSPORT_AUTO,
                too_many.SerializeAsString());
  EXPECT_EQ(mll_vector_env_create_status(bad_option.get()), kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(bad_option.get()), HasSubstr("n_landers"));
  Handle bad_count = NewHandle(server_->address(), 0);
  EXPECT_EQ(mll_vector_env_create_status(bad_count.get()), kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(bad_count.get()),
              HasSubstr("num_envs is 0"));
  Handle bad_timeout =
      NewHandle(server_->address(), 2, 0, -1, MLL_NATIVE_TRANSPORT_AUTO,
                SmallConfig().SerializeAsString(), std::nan(""));
  EXPECT_EQ(mll_vector_env_create_status(bad_timeout.get()), kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(bad_timeout.get()),
              HasSubstr("step_timeout_s is nan"));
  Handle bad_rediscover =
      NewHandle(server_->address(), 2, 0, -1, MLL_NATIVE_TRANSPORT_AUTO,
                SmallConfig().SerializeAsString(), -1, std::nan(""));
  EXPECT_EQ(mll_vector_env_create_status(bad_rediscover.get()),
            kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(bad_rediscover.get()),
              HasSubstr("rediscover_interval_s is nan"));
  Handle bad_failover = NewHandle(server_->address(), 2, 0, 7);
  EXPECT_EQ(mll_vector_env_create_status(bad_failover.get()), kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(bad_failover.get()),
              HasSubstr("failover is 7"));
}

// Bound buffers get every call's results in place, `*offset` bytes past each
// buffer as the offset stands at that call: a caller that moves the offset
// keeps each call's results where it left them.
TEST_F(VectorCApiTest, BoundResultsGoPastEachBufferByTheBoundOffset) {
  constexpr int kEnvs = 3;
  constexpr int kSlots = 3;
  Handle env = NewHandle(server_->address(), kEnvs);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk);
  const int count = mll_vector_env_column_count();
  // Per column, kSlots slots of one call's results each, the slot's bytes
  // (the same for every column: the widest column's), so that one offset
  // moves every column to its next slot.
  size_t slot_bytes = 0;
  std::vector<size_t> column_bytes(count);
  for (int c = 0; c < count; ++c) {
    column_bytes[c] = kEnvs *
                      (mll_vector_env_column_per_agent(c) ? kLanders : 1) *
                      mll_vector_env_column_width(c) *
                      ElementSize(mll_vector_env_column_dtype(c));
    slot_bytes = std::max(slot_bytes, column_bytes[c]);
  }
  std::vector<std::string> blocks(count, std::string(kSlots * slot_bytes, 0));
  std::vector<void*> buffers(count);
  for (int c = 0; c < count; ++c) buffers[c] = blocks[c].data();
  int64_t offset = 0;
  ASSERT_EQ(mll_vector_env_bind_results(env.get(), kEnvs, buffers.data()), kOk);
  ASSERT_EQ(mll_vector_env_bind_results_offset(env.get(), kEnvs, &offset), kOk);
  // The slot of each call as it was written, by call.
  std::vector<std::vector<std::string>> written;
  const auto slot_of = [&](int slot) {
    std::vector<std::string> columns(count);
    for (int c = 0; c < count; ++c) {
      columns[c] = blocks[c].substr(slot * slot_bytes, column_bytes[c]);
    }
    return columns;
  };
  ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 4), kOk);
  EXPECT_EQ(slot_of(0), ResultsOf(env.get()));
  written.push_back(slot_of(0));
  for (int step = 1; step < kSlots; ++step) {
    offset = static_cast<int64_t>(step * slot_bytes);
    const std::vector<int32_t> actions = ActionsOf(step, kEnvs);
    ASSERT_EQ(
        mll_vector_env_step(env.get(), actions.data(), actions.size(), 0, -1),
        kOk)
        << mll_vector_env_message(env.get());
    EXPECT_EQ(slot_of(step), ResultsOf(env.get()));
    written.push_back(slot_of(step));
  }
  for (int slot = 0; slot < kSlots; ++slot) {
    EXPECT_EQ(slot_of(slot), written[slot]) << "slot " << slot;
  }
  EXPECT_NE(written[1], written[2]);
  // No offset again: the first slot.
  ASSERT_EQ(mll_vector_env_bind_results_offset(env.get(), kEnvs, nullptr), kOk);
  const std::vector<int32_t> actions = ActionsOf(9, kEnvs);
  ASSERT_EQ(
      mll_vector_env_step(env.get(), actions.data(), actions.size(), 0, -1),
      kOk);
  EXPECT_EQ(slot_of(0), ResultsOf(env.get()));
  EXPECT_EQ(slot_of(2), written[2]);

  EXPECT_EQ(mll_vector_env_bind_results_offset(env.get(), 7, &offset),
            kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(env.get()),
              HasSubstr("rows is 7; allowed: num_envs = 3"));
  EXPECT_EQ(mll_vector_env_bind_results(env.get(), 0, buffers.data()),
            kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(env.get()), HasSubstr("rows is 0"));
}

// A snapshot taken mid-episode and restored later puts the env back: the
// observations of that point, then the same results for the same actions.
TEST_F(VectorCApiTest, SnapshotRestoresTheEnvToTheSameBits) {
  constexpr int kEnvs = 3;
  Handle env = NewHandle(server_->address(), kEnvs);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk);
  ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 40), kOk);
  const auto step = [&](int k) {
    const std::vector<int32_t> actions = ActionsOf(k, kEnvs);
    EXPECT_EQ(
        mll_vector_env_step_async(env.get(), actions.data(), actions.size(), 0),
        kOk);
    EXPECT_EQ(mll_vector_env_step_wait(env.get(), -1), kOk);
    return ResultsOf(env.get());
  };
  for (int k = 0; k < 10; ++k) step(k);
  const std::string at_snapshot = ResultsOf(env.get())[0];
  const char* data = nullptr;
  size_t size = 0;
  ASSERT_EQ(mll_vector_env_snapshot(env.get(), 1, &data, &size), kOk)
      << mll_vector_env_message(env.get());
  const std::string snapshot(data, size);
  const std::string old_name = mll_vector_env_name(env.get(), 1);
  std::vector<std::vector<std::string>> after;
  for (int k = 10; k < 15; ++k) after.push_back(step(k));

  std::vector<float> observations(kLanders * kRemoteObservationSize);
  ASSERT_EQ(mll_vector_env_restore(env.get(), 1, snapshot.data(),
                                   snapshot.size(), observations.data()),
            kOk)
      << mll_vector_env_message(env.get());
  const size_t row_bytes = observations.size() * sizeof(float);
  EXPECT_EQ(BytesOf(absl::MakeConstSpan(observations)),
            at_snapshot.substr(row_bytes, row_bytes));
  EXPECT_NE(std::string(mll_vector_env_name(env.get(), 1)), old_name);
  for (int k = 10; k < 15; ++k) {
    const std::string got = step(k)[0];
    EXPECT_EQ(got.substr(row_bytes, row_bytes),
              after[k - 10][0].substr(row_bytes, row_bytes))
        << "step " << k;
  }
  std::string damaged = snapshot;
  damaged[damaged.size() / 2] ^= 1;
  EXPECT_EQ(mll_vector_env_restore(env.get(), 1, damaged.data(), damaged.size(),
                                   observations.data()),
            kInvalidArgument);
  EXPECT_THAT(mll_vector_env_message(env.get()), HasSubstr("CRC"));
}

// A server killed mid-run: its envs move to the other server, the steps go
// on with the same bits as a run without the fault, and the event's line
// waits in take_events (naming the cause and the lost server) instead of
// going to stderr.
TEST(VectorCApiFailoverTest, EventsQueueForTakeEvents) {
  std::vector<std::unique_ptr<ServerProcess>> servers;
  for (int i = 0; i < 2; ++i) {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH, {"--threads=1"});
    ASSERT_TRUE(server.ok()) << server.status();
    servers.push_back(*std::move(server));
  }
  const std::string addresses =
      absl::StrJoin({servers[0]->address(), servers[1]->address()}, ",");
  constexpr int kEnvs = 4;
  Handle env = NewHandle(addresses, kEnvs);
  ASSERT_EQ(mll_vector_env_create_status(env.get()), kOk)
      << mll_vector_env_message(env.get());
  EXPECT_EQ(mll_vector_env_failover(env.get()), 1);  // Several servers.
  ASSERT_EQ(mll_vector_env_server_count(env.get()), 2);
  VectorEnv reference = NewVectorEnv({servers[0]->address()}, kEnvs);
  ASSERT_EQ(mll_vector_env_reset(env.get(), 1, 5), kOk);
  ASSERT_TRUE(reference.Reset(uint64_t{5}).ok());
  ::testing::internal::CaptureStderr();
  for (int step = 0; step < 40; ++step) {
    if (step == 15) servers[1]->Kill();
    const std::vector<int32_t> actions = ActionsOf(step, kEnvs);
    ASSERT_EQ(
        mll_vector_env_step_async(env.get(), actions.data(), actions.size(), 0),
        kOk);
    ASSERT_EQ(mll_vector_env_step_wait(env.get(), -1), kOk)
        << "step " << step << ": " << mll_vector_env_message(env.get());
    ASSERT_TRUE(reference.Step(absl::MakeConstSpan(actions)).ok());
    ASSERT_EQ(ResultsOf(env.get()), ResultsOf(reference)) << "step " << step;
  }
  const std::string stderr_text = ::testing::internal::GetCapturedStderr();
  EXPECT_EQ(mll_vector_env_failovers(env.get()), 1);
  const std::string events = mll_vector_env_take_events(env.get());
  EXPECT_THAT(events, HasSubstr("failover"));
  EXPECT_THAT(events, HasSubstr("UNAVAILABLE"));
  EXPECT_THAT(events, HasSubstr("2 env(s) lost"));
  EXPECT_THAT(events, HasSubstr(servers[0]->address()));  // Recreated there.
  EXPECT_EQ(events.find('\n'), std::string::npos);  // One event, one line.
  EXPECT_THAT(stderr_text, ::testing::Not(HasSubstr("VectorEnv failover")));
  EXPECT_EQ(std::string(mll_vector_env_take_events(env.get())), "");
  for (int i = 0; i < kEnvs; ++i) {
    EXPECT_EQ(std::string(mll_vector_env_env_address(env.get(), i)),
              servers[0]->address());
  }
}

}  // namespace
}  // namespace mll::client

// Sessions attached to shared memory, driven through the region by hand
// against the mll_server binary on loopback: the same bits as the stream,
// errors for bad bytes and sizes that leave the session usable, the stream's
// refusal once attached, the limit and the off switch, and the session's end
// (cancelled stream) deleting its bound envs.
#include <chrono>
#include <string>
#include <thread>
#include <vector>

#include "gtest/gtest.h"
#include "mll/shared_memory_pipe.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

constexpr int kLanders = 3;

class SharedMemorySessionTest : public ::testing::Test {
 protected:
  void Start(std::vector<std::string> flags) {
    flags.push_back("--threads=2");
    process_ = std::make_unique<ServerProcess>(flags);
    const int port = process_->WaitForPort();
    ASSERT_GT(port, 0);
    channel_ = grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                   grpc::InsecureChannelCredentials());
    ASSERT_TRUE(channel_->WaitForConnected(std::chrono::system_clock::now() +
                                           std::chrono::seconds(20)));
    stub_ = v1::MultiLunarLander::NewStub(channel_);
  }

  // `name`'s reset with `seed` and up to `cycles` steps of the action table
  // (until the episode is over), as ResultBits, each operation run by
  // `call`.
  template <typename Call>
  std::vector<std::string> Trajectory(const std::string& name, uint64_t seed,
                                      int cycles, Call call) {
    const auto table = ActionTable(cycles, kLanders, 3);
    v1::SessionRequest reset;
    reset.mutable_reset_env()->set_name(name);
    reset.mutable_reset_env()->set_seed(seed);
    std::vector<std::string> bits = {
        ResultBits(call(reset).reset_env().data())};
    for (int c = 0; c < cycles; ++c) {
      v1::SessionRequest step;
      if (c % 2 == 0) {
        step.mutable_step_env()->set_name(name);
        *step.mutable_step_env()->mutable_actions() = DiscreteActions(table[c]);
        const v1::SessionResponse response = call(step);
        if (response.has_error()) break;  // The episode is over.
        bits.push_back(ResultBits(response.step_env().data()));
      } else {
        v1::StepEnvRequest* item = step.mutable_step_batch()->add_steps();
        item->set_name(name);
        *item->mutable_actions() = DiscreteActions(table[c]);
        const v1::SessionResponse response = call(step);
        if (response.step_batch().results_size() != 1 ||
            !response.step_batch().results(0).has_data()) {
          break;  // The episode is over.
        }
        bits.push_back(ResultBits(response.step_batch().results(0).data()));
      }
    }
    return bits;
  }

  std::unique_ptr<ServerProcess> process_;
  std::shared_ptr<grpc::Channel> channel_;
  std::unique_ptr<v1::MultiLunarLander::Stub> stub_;
};

TEST_F(SharedMemorySessionTest, GivesTheSameBitsAsTheStream) {
  Start({});
  SharedMemorySession shared(*stub_);
  const v1::SessionResponse attached = shared.Attach();
  ASSERT_FALSE(attached.has_error()) << attached.error().message();
  EXPECT_EQ(attached.attach_shared_memory().size(),
            shared_memory::RegionBytes(shared_memory::kCapacity));

  grpc::ClientContext context;
  auto stream = stub_->Session(&context);
  uint64_t sequence = 0;
  auto on_stream = [&](v1::SessionRequest request) {
    request.set_sequence(++sequence);
    EXPECT_TRUE(stream->Write(request));
    v1::SessionResponse response;
    EXPECT_TRUE(stream->Read(&response));
    return response;
  };
  auto on_region = [&](v1::SessionRequest request) {
    return shared.Call(std::move(request));
  };
  v1::SessionRequest create;
  *create.mutable_create_env() = CreateRequest(kLanders);
  // Long episodes in which landers finish at different times.
  create.mutable_create_env()->mutable_config()->set_terminate_on_damage(false);
  const std::string via_region = on_region(create).env().name();
  const std::string via_stream = on_stream(create).env().name();
  ASSERT_FALSE(via_region.empty());
  const auto expected = Trajectory(via_stream, 11, 200, on_stream);
  EXPECT_EQ(Trajectory(via_region, 11, 200, on_region), expected);
  EXPECT_GT(expected.size(), 50u);
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());
}

TEST_F(SharedMemorySessionTest, BadBytesAndSizesAreInvalidAndTheSessionGoesOn) {
  Start({});
  SharedMemorySession shared(*stub_);
  ASSERT_FALSE(shared.Attach().has_error());
  v1::SessionResponse garbage = shared.CallRaw("\xff\xff\xff\xff", 4);
  EXPECT_EQ(garbage.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(garbage.error().message(),
            "request: not a serialized SessionRequest");
  v1::SessionResponse oversized =
      shared.CallRaw("", shared_memory::kCapacity + 1);
  EXPECT_EQ(oversized.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_EQ(oversized.error().message(),
            "request_size: " + std::to_string(shared_memory::kCapacity + 1) +
                " bytes; allowed: 0.." +
                std::to_string(shared_memory::kCapacity) +
                " (the region's capacity)");
  v1::SessionRequest empty;  // No op.
  EXPECT_EQ(shared.Call(empty).error().code(),
            grpc::StatusCode::INVALID_ARGUMENT);
  v1::SessionRequest attach_again;
  attach_again.mutable_attach_shared_memory();
  EXPECT_EQ(shared.Call(attach_again).error().code(),
            grpc::StatusCode::FAILED_PRECONDITION);
  v1::SessionRequest create;
  *create.mutable_create_env() = CreateRequest(2);
  const v1::SessionResponse created = shared.Call(create);
  EXPECT_FALSE(created.has_error()) << created.error().message();
  EXPECT_EQ(created.env().config().n_landers(), 2);
}

TEST_F(SharedMemorySessionTest, TheStreamRefusesRequestsOnceAttached) {
  Start({});
  SharedMemorySession shared(*stub_);
  ASSERT_FALSE(shared.Attach().has_error());
  v1::SessionRequest on_stream;
  on_stream.set_sequence(7);
  *on_stream.mutable_create_env() = CreateRequest(1);
  ASSERT_TRUE(shared.stream().Write(on_stream));
  v1::SessionResponse refused;
  ASSERT_TRUE(shared.stream().Read(&refused));
  EXPECT_EQ(refused.sequence(), 7u);
  EXPECT_EQ(refused.error().code(), grpc::StatusCode::FAILED_PRECONDITION);
  v1::SessionRequest create;
  *create.mutable_create_env() = CreateRequest(1);
  EXPECT_FALSE(shared.Call(create).has_error());  // The region still serves.
}

TEST_F(SharedMemorySessionTest, TheLimitAndTheOffSwitchRefuseTheAttach) {
  Start({"--shared_memory_sessions=1"});
  SharedMemorySession first(*stub_);
  ASSERT_FALSE(first.Attach().has_error());
  SharedMemorySession second(*stub_);
  const v1::SessionResponse refused = second.Attach();
  EXPECT_EQ(refused.error().code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_EQ(refused.error().message(),
            "attach_shared_memory: 1 sessions are attached "
            "(--shared_memory_sessions); allowed: at most 1");
  // Refused, the session goes on over its stream.
  v1::SessionRequest create;
  create.set_sequence(2);
  *create.mutable_create_env() = CreateRequest(1);
  ASSERT_TRUE(second.stream().Write(create));
  v1::SessionResponse created;
  ASSERT_TRUE(second.stream().Read(&created));
  EXPECT_FALSE(created.has_error()) << created.error().message();

  Start({"--shared_memory_sessions=0"});
  SharedMemorySession off(*stub_);
  const v1::SessionResponse denied = off.Attach();
  EXPECT_EQ(denied.error().code(), grpc::StatusCode::PERMISSION_DENIED);
  EXPECT_EQ(denied.error().message(),
            "attach_shared_memory: the server runs with "
            "--shared_memory_sessions=0");
}

TEST_F(SharedMemorySessionTest, ACancelledSessionDeletesItsBoundEnvsAndSlot) {
  Start({"--shared_memory_sessions=1"});
  std::string name;
  {
    SharedMemorySession shared(*stub_);
    ASSERT_FALSE(shared.Attach().has_error());
    v1::SessionRequest create;
    *create.mutable_create_env() = CreateRequest(2);
    name = shared.Call(create).env().name();
    ASSERT_FALSE(name.empty());
    shared.Cancel();
  }
  // Bounded: the server ends the session when it sees the cancellation.
  const auto give_up =
      std::chrono::steady_clock::now() + std::chrono::seconds(10);
  grpc::StatusCode code = grpc::StatusCode::OK;
  while (std::chrono::steady_clock::now() < give_up) {
    grpc::ClientContext context;
    v1::GetEnvRequest get;
    get.set_name(name);
    v1::Env env;
    code = stub_->GetEnv(&context, get, &env).error_code();
    if (code == grpc::StatusCode::NOT_FOUND) break;
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  EXPECT_EQ(code, grpc::StatusCode::NOT_FOUND);
  SharedMemorySession next(*stub_);  // The one slot is free again.
  EXPECT_FALSE(next.Attach().has_error());
}

}  // namespace
}  // namespace mll::service::testing

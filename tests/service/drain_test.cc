// Server::Drain, the first step of mll_server's graceful stop on SIGTERM
// (--drain_s): open Session streams (on the stream or on shared memory) end
// with UNAVAILABLE "draining: ...", new envs and sessions are refused with
// it, the envs left are served, and Drain returns once they are gone or the
// period has passed. Health and the binary's flag: client_py/tests/
// test_drain.py and test_rolling_restart.py.
#include <chrono>
#include <future>
#include <string>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::AllOf;
using ::testing::HasSubstr;
using ::testing::StartsWith;

v1::SessionRequest CreateOnSession(uint64_t sequence) {
  v1::SessionRequest request;
  request.set_sequence(sequence);
  *request.mutable_create_env() = CreateRequest(1);
  return request;
}

grpc::Status Reset(v1::MultiLunarLander::Stub& stub, const std::string& name) {
  grpc::ClientContext context;
  v1::ResetEnvRequest request;
  request.set_name(name);
  v1::ResetEnvResponse response;
  return stub.ResetEnv(&context, request, &response);
}

TEST(DrainTest, EndsSessionsRefusesNewWorkServesEnvsLeftUntilTheyAreGone) {
  InProcess s;
  const std::string kept = CreateEnv(*s.stub, CreateRequest(2));
  grpc::ClientContext context;
  auto stream = s.stub->Session(&context);
  ASSERT_TRUE(stream->Write(CreateOnSession(1)));
  v1::SessionResponse response;
  ASSERT_TRUE(stream->Read(&response));
  const std::string bound = response.env().name();
  ASSERT_FALSE(bound.empty());

  std::future<int> left = std::async(
      std::launch::async, [&s] { return s.server->Drain(absl::Seconds(20)); });
  // The idle stream ends with the status a client moves on.
  EXPECT_FALSE(stream->Read(&response));
  const grpc::Status ended = stream->Finish();
  EXPECT_EQ(ended.error_code(), grpc::StatusCode::UNAVAILABLE);
  EXPECT_THAT(ended.error_message(), StartsWith("draining: "));
  EXPECT_TRUE(s.server->service().draining());

  {
    grpc::ClientContext create_context;
    v1::Env env;
    const grpc::Status refused =
        s.stub->CreateEnv(&create_context, CreateRequest(1), &env);
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::UNAVAILABLE);
    EXPECT_THAT(refused.error_message(),
                AllOf(StartsWith("draining: "),
                      HasSubstr("create environments on another server")));
  }
  {
    grpc::ClientContext new_context;
    auto refused_stream = s.stub->Session(&new_context);
    refused_stream->Write(CreateOnSession(1));
    EXPECT_FALSE(refused_stream->Read(&response));
    const grpc::Status refused = refused_stream->Finish();
    EXPECT_EQ(refused.error_code(), grpc::StatusCode::UNAVAILABLE);
    EXPECT_THAT(refused.error_message(), StartsWith("draining: "));
  }
  // The session's bound env went with it; the other is served until deleted.
  EXPECT_EQ(Reset(*s.stub, bound).error_code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_TRUE(Reset(*s.stub, kept).ok());
  EXPECT_EQ(left.wait_for(std::chrono::milliseconds(100)),
            std::future_status::timeout);
  {
    grpc::ClientContext delete_context;
    v1::DeleteEnvRequest request;
    request.set_name(kept);
    v1::DeleteEnvResponse deleted;
    ASSERT_TRUE(s.stub->DeleteEnv(&delete_context, request, &deleted).ok());
  }
  ASSERT_EQ(left.wait_for(std::chrono::seconds(10)), std::future_status::ready);
  EXPECT_EQ(left.get(), 0);
}

TEST(DrainTest, EndsASessionAttachedToSharedMemory) {
  // Over loopback TCP: only a peer on the server's host may attach.
  ServerOptions options;
  options.address = "127.0.0.1:0";
  absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
  ASSERT_TRUE(server.ok()) << server.status();
  auto stub = v1::MultiLunarLander::NewStub(
      grpc::CreateChannel(absl::StrCat("127.0.0.1:", (*server)->port()),
                          grpc::InsecureChannelCredentials()));
  SharedMemorySession shared(*stub);
  ASSERT_FALSE(shared.Attach().has_error());
  const v1::SessionResponse created = shared.Call(CreateOnSession(0));
  ASSERT_FALSE(created.has_error());
  EXPECT_EQ((*server)->Drain(absl::Seconds(10)), 0);  // Its env went with it.
  // The stream ended (its status is the first test's; the helper's destructor
  // finishes it).
  v1::SessionResponse response;
  EXPECT_FALSE(shared.stream().Read(&response));
}

TEST(DrainTest, ReturnsAfterThePeriodWithTheEnvsLeft) {
  InProcess s;
  CreateEnv(*s.stub, CreateRequest(1));
  const auto began = std::chrono::steady_clock::now();
  EXPECT_EQ(s.server->Drain(absl::Milliseconds(300)), 1);
  EXPECT_GE(std::chrono::steady_clock::now() - began,
            std::chrono::milliseconds(290));
}

}  // namespace
}  // namespace mll::service::testing

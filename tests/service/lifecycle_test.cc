// Environment life cycle: idle envs are reclaimed, a session's envs die with
// it (unless detached), --max_envs bounds the count without disturbing the
// rest. Waits are bounded polls, never fixed sleeps standing in for results.
#include <algorithm>
#include <chrono>
#include <string>
#include <thread>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::HasSubstr;

grpc::StatusCode GetCode(v1::MultiLunarLander::Stub& stub,
                         const std::string& name) {
  grpc::ClientContext context;
  v1::GetEnvRequest request;
  request.set_name(name);
  v1::Env env;
  return stub.GetEnv(&context, request, &env).error_code();
}

// Names of the hosted envs. Unlike GetEnv, listing touches no env.
std::vector<std::string> Listed(v1::MultiLunarLander::Stub& stub) {
  grpc::ClientContext context;
  v1::ListEnvsResponse list;
  EXPECT_TRUE(stub.ListEnvs(&context, {}, &list).ok());
  std::vector<std::string> names;
  for (const v1::Env& env : list.envs()) names.push_back(env.name());
  return names;
}

// Polls until `name` is no longer hosted or `limit` passes.
bool WaitUntilGone(v1::MultiLunarLander::Stub& stub, const std::string& name,
                   std::chrono::milliseconds limit) {
  const auto end = std::chrono::steady_clock::now() + limit;
  while (std::chrono::steady_clock::now() < end) {
    const std::vector<std::string> names = Listed(stub);
    if (std::find(names.begin(), names.end(), name) == names.end()) {
      return true;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
  return false;
}

TEST(LifecycleTest, IdleEnvsAreReclaimedTouchedOnesStay) {
  ServiceOptions options;
  options.idle_timeout = absl::Milliseconds(800);
  InProcess s(options);
  const std::string idle = CreateEnv(*s.stub, {});
  const std::string busy = CreateEnv(*s.stub, {});
  // `busy` is touched every 100 ms for 2.5 timeouts; `idle` never.
  const auto start = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - start <
         std::chrono::milliseconds(2000)) {
    ASSERT_EQ(GetCode(*s.stub, busy), grpc::StatusCode::OK);
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  EXPECT_THAT(Listed(*s.stub), ::testing::ElementsAre(busy));
  EXPECT_EQ(GetCode(*s.stub, idle), grpc::StatusCode::NOT_FOUND);
  // Once untouched, `busy` goes too, within a bounded wait.
  EXPECT_TRUE(WaitUntilGone(*s.stub, busy, std::chrono::milliseconds(5000)));
}

TEST(LifecycleTest, SessionEnvsVanishWhenTheStreamIsCancelled) {
  InProcess s;
  auto context = std::make_unique<grpc::ClientContext>();
  auto stream = s.stub->Session(context.get());
  auto call = [&](uint64_t sequence, v1::SessionRequest request) {
    request.set_sequence(sequence);
    EXPECT_TRUE(stream->Write(request));
    v1::SessionResponse response;
    EXPECT_TRUE(stream->Read(&response));
    EXPECT_EQ(response.sequence(), sequence);
    return response;
  };
  v1::SessionRequest create;
  *create.mutable_create_env() = CreateRequest(2);
  v1::SessionResponse bound = call(1, create);
  ASSERT_FALSE(bound.has_error());
  EXPECT_TRUE(bound.env().session_bound());
  create.mutable_create_env()->set_detached(true);
  v1::SessionResponse detached = call(2, create);
  EXPECT_FALSE(detached.env().session_bound());

  // Errors are per request; the stream goes on.
  v1::SessionRequest bad;
  bad.mutable_step_env()->set_name(bound.env().name());
  *bad.mutable_step_env()->mutable_actions() = DiscreteActions({0, 0});
  v1::SessionResponse error = call(3, bad);
  EXPECT_EQ(error.error().code(), grpc::StatusCode::FAILED_PRECONDITION);
  EXPECT_EQ(error.result_case(), v1::SessionResponse::RESULT_NOT_SET);
  v1::SessionResponse empty = call(4, v1::SessionRequest());
  EXPECT_EQ(empty.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(empty.error().message(), HasSubstr("op: not set"));
  v1::SessionRequest reset;
  reset.mutable_reset_env()->set_name(bound.env().name());
  reset.mutable_reset_env()->set_seed(3);
  EXPECT_TRUE(call(5, reset).has_reset_env());
  v1::SessionRequest render;
  render.mutable_render_env()->set_name(bound.env().name());
  EXPECT_EQ(call(6, render).error().code(),
            grpc::StatusCode::FAILED_PRECONDITION);  // No render mode.
  v1::SessionRequest get;
  get.mutable_get_env()->set_name(detached.env().name());
  EXPECT_EQ(call(7, get).env().name(), detached.env().name());

  EXPECT_EQ(GetCode(*s.stub, bound.env().name()), grpc::StatusCode::OK);
  context->TryCancel();
  EXPECT_TRUE(WaitUntilGone(*s.stub, bound.env().name(),
                            std::chrono::milliseconds(5000)));
  EXPECT_EQ(GetCode(*s.stub, detached.env().name()), grpc::StatusCode::OK);
  EXPECT_FALSE(stream->Finish().ok());
}

TEST(LifecycleTest, SessionEnvsVanishWhenTheStreamEndsNormally) {
  InProcess s;
  std::string name;
  {
    grpc::ClientContext context;
    auto stream = s.stub->Session(&context);
    v1::SessionRequest create;
    create.set_sequence(1);
    *create.mutable_create_env() = CreateRequest(1);
    ASSERT_TRUE(stream->Write(create));
    v1::SessionResponse response;
    ASSERT_TRUE(stream->Read(&response));
    name = response.env().name();
    v1::SessionRequest remove;
    remove.set_sequence(2);
    remove.mutable_delete_env()->set_name("envs/unknown");
    ASSERT_TRUE(stream->Write(remove));
    ASSERT_TRUE(stream->Read(&response));
    EXPECT_EQ(response.error().code(), grpc::StatusCode::NOT_FOUND);
    stream->WritesDone();
    EXPECT_TRUE(stream->Finish().ok());
  }
  EXPECT_TRUE(WaitUntilGone(*s.stub, name, std::chrono::milliseconds(5000)));
}

TEST(LifecycleTest, MaxEnvsIsResourceExhaustedAndTheRestKeepsWorking) {
  ServiceOptions options;
  options.max_envs = 3;
  InProcess s(options);
  std::vector<std::string> names;
  for (int i = 0; i < 3; ++i) names.push_back(CreateEnv(*s.stub, {}));
  {
    grpc::ClientContext context;
    v1::Env env;
    const grpc::Status status =
        s.stub->CreateEnv(&context, v1::CreateEnvRequest(), &env);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
    EXPECT_THAT(status.error_message(), HasSubstr("--max_envs = 3"));
  }
  // The hosted envs still reset and step.
  for (const std::string& name : names) {
    grpc::ClientContext context;
    v1::ResetEnvRequest reset;
    reset.set_name(name);
    v1::ResetEnvResponse reset_response;
    ASSERT_TRUE(s.stub->ResetEnv(&context, reset, &reset_response).ok());
    grpc::ClientContext step_context;
    v1::StepEnvRequest step;
    step.set_name(name);
    *step.mutable_actions() = DiscreteActions({0, 0, 0});
    v1::StepEnvResponse step_response;
    EXPECT_TRUE(s.stub->StepEnv(&step_context, step, &step_response).ok());
  }
  // A freed place can be taken again.
  grpc::ClientContext context;
  v1::DeleteEnvRequest remove;
  remove.set_name(names[0]);
  v1::DeleteEnvResponse removed;
  ASSERT_TRUE(s.stub->DeleteEnv(&context, remove, &removed).ok());
  EXPECT_FALSE(CreateEnv(*s.stub, {}).empty());
}

}  // namespace
}  // namespace mll::service::testing

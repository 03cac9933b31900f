#include "test_util.h"

#include <random>
#include <utility>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/service/convert.h"

namespace mll::service::testing {

namespace {

ServerOptions WithService(ServiceOptions service, int max_message_mb) {
  ServerOptions options;
  options.max_message_mb = max_message_mb;
  options.service = std::move(service);
  return options;
}

}  // namespace

InProcess::InProcess(ServiceOptions options, int max_message_mb)
    : InProcess(WithService(std::move(options), max_message_mb)) {}

InProcess::InProcess(ServerOptions options) {
  options.address = "";
  absl::StatusOr<std::unique_ptr<Server>> started = Server::Start(options);
  EXPECT_TRUE(started.ok()) << started.status();
  if (!started.ok()) return;
  server = *std::move(started);
  stub = v1::MultiLunarLander::NewStub(server->InProcessChannel());
}

void AddToken(const std::string& token, grpc::ClientContext* context) {
  context->AddMetadata("authorization", "Bearer " + token);
}

v1::Array DiscreteActions(const std::vector<int32_t>& actions) {
  v1::Array array;
  const int shape[] = {static_cast<int>(actions.size())};
  FillArray<int32_t>(actions, shape, &array);
  return array;
}

v1::Array ContinuousActions(const std::vector<float>& actions) {
  v1::Array array;
  const int shape[] = {static_cast<int>(actions.size() / 2), 2};
  FillArray<float>(actions, shape, &array);
  return array;
}

v1::CreateEnvRequest CreateRequest(int n_landers) {
  v1::CreateEnvRequest request;
  request.mutable_config()->set_n_landers(n_landers);
  return request;
}

std::string CreateEnv(v1::MultiLunarLander::Stub& stub,
                      const v1::CreateEnvRequest& request) {
  grpc::ClientContext context;
  v1::Env env;
  grpc::Status status = stub.CreateEnv(&context, request, &env);
  EXPECT_TRUE(status.ok()) << status.error_message();
  return env.name();
}

std::vector<float> Observations(const v1::StepData& data, int n) {
  const int shape[] = {n, core::kObservationSize};
  absl::StatusOr<std::vector<float>> values =
      DecodeArray<float>(data.observations(), shape, "observations");
  EXPECT_TRUE(values.ok()) << values.status();
  return values.ok() ? *values : std::vector<float>();
}

std::vector<float> Rewards(const v1::StepData& data, int n) {
  const int shape[] = {n};
  absl::StatusOr<std::vector<float>> values =
      DecodeArray<float>(data.rewards(), shape, "rewards");
  EXPECT_TRUE(values.ok()) << values.status();
  return values.ok() ? *values : std::vector<float>();
}

std::string ResultBits(const v1::StepData& data) {
  return data.observations().data() + "|" + data.rewards().data() + "|" +
         data.terminations().data() + "|" + data.truncations().data() + "|" +
         data.stepped().data() + "|" + data.outcomes().data() + "|" +
         data.episode_returns().data() + "|" + data.episode_lengths().data() +
         (data.episode_over() ? "|over" : "|on");
}

std::vector<std::vector<int32_t>> ActionTable(int cycles, int n_landers,
                                              uint32_t seed) {
  std::mt19937 generator(seed);
  constexpr int32_t kChoices[] = {0, 1, 2, 2, 2, 3};
  std::uniform_int_distribution<int> pick(0, 5);
  std::vector<std::vector<int32_t>> table(cycles,
                                          std::vector<int32_t>(n_landers));
  for (auto& row : table) {
    for (int32_t& action : row) action = kChoices[pick(generator)];
  }
  return table;
}

void ExpectListenerRefusesBadAndBusyAddresses(
    const std::string& flag, std::string ServerOptions::*address,
    int (Server::*port)() const) {
  ServerOptions options;
  options.address = "";
  for (const char* bad : {"8080", "127.0.0.1:http", "127.0.0.1:70000"}) {
    options.*address = bad;
    absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
    EXPECT_EQ(server.status().code(), absl::StatusCode::kInvalidArgument)
        << flag << "=" << bad;
    EXPECT_THAT(server.status().message(),
                ::testing::HasSubstr(
                    absl::StrCat(flag, ": \"", bad, "\" is not host:port")));
  }
  options.*address = "127.0.0.1:0";
  absl::StatusOr<std::unique_ptr<Server>> first = Server::Start(options);
  ASSERT_TRUE(first.ok()) << first.status();
  EXPECT_GT(((**first).*port)(), 0);
  options.*address = absl::StrCat("127.0.0.1:", ((**first).*port)());
  absl::StatusOr<std::unique_ptr<Server>> second = Server::Start(options);
  EXPECT_EQ(second.status().code(), absl::StatusCode::kUnavailable);
  EXPECT_THAT(second.status().message(),
              ::testing::HasSubstr(absl::StrCat(flag, ": cannot listen on")));
}

}  // namespace mll::service::testing

#include "test_util.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <random>
#include <utility>

#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/service/convert.h"
#include "mll/shared_memory_pipe.h"

namespace mll::service::testing {

namespace {

ServerOptions WithService(ServiceOptions service, int max_message_mb) {
  ServerOptions options;
  options.max_message_mb = max_message_mb;
  options.service = std::move(service);
  return options;
}

}  // namespace

SharedMemorySession::SharedMemorySession(v1::MultiLunarLander::Stub& stub)
    : stream_(stub.Session(&context_)) {}

SharedMemorySession::~SharedMemorySession() {
  if (region_ != nullptr) munmap(region_, bytes_);
  context_.TryCancel();
  stream_->Finish().IgnoreError();
}

v1::SessionResponse SharedMemorySession::Attach() {
  v1::SessionRequest request;
  request.set_sequence(++sequence_);
  request.mutable_attach_shared_memory();
  v1::SessionResponse response;
  EXPECT_TRUE(stream_->Write(request));
  EXPECT_TRUE(stream_->Read(&response));
  if (response.has_error()) return response;
  const v1::AttachSharedMemoryResponse& region =
      response.attach_shared_memory();
  const int fd = open(region.path().c_str(), O_RDWR | O_CLOEXEC);
  EXPECT_GE(fd, 0) << region.path() << ": " << std::strerror(errno);
  if (fd < 0) return response;
  region_ =
      mmap(nullptr, region.size(), PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  close(fd);
  EXPECT_NE(region_, MAP_FAILED);
  if (region_ == MAP_FAILED) region_ = nullptr;
  bytes_ = region.size();
  return response;
}

v1::SessionResponse SharedMemorySession::Call(v1::SessionRequest request) {
  request.set_sequence(++sequence_);
  const std::string bytes = request.SerializeAsString();
  v1::SessionResponse response = CallRaw(bytes, bytes.size());
  EXPECT_EQ(response.sequence(), sequence_);
  return response;
}

v1::SessionResponse SharedMemorySession::CallRaw(const std::string& bytes,
                                                 uint64_t size) {
  v1::SessionResponse response;
  EXPECT_NE(region_, nullptr) << "Attach() first";
  if (region_ == nullptr) return response;
  auto& header = *static_cast<shared_memory::Header*>(region_);
  std::memcpy(shared_memory::RequestArea(region_), bytes.data(),
              std::min<uint64_t>(bytes.size(), header.capacity));
  header.request_size.store(size, std::memory_order_release);
  const uint32_t sent = header.request_seq.load(std::memory_order_relaxed) + 1;
  header.request_seq.store(sent, std::memory_order_release);
  shared_memory::Wake(header.request_seq);
  const auto give_up =
      std::chrono::steady_clock::now() + std::chrono::seconds(20);
  while (header.response_seq.load(std::memory_order_acquire) != sent &&
         std::chrono::steady_clock::now() < give_up) {
    shared_memory::WaitWhileEqual(
        header.response_seq,
        header.response_seq.load(std::memory_order_acquire),
        std::chrono::nanoseconds(0), std::chrono::milliseconds(20));
  }
  EXPECT_EQ(header.response_seq.load(std::memory_order_acquire), sent)
      << "no answer within 20 s";
  if (header.response_seq.load(std::memory_order_acquire) != sent) {
    return response;
  }
  const uint64_t answer = header.response_size.load(std::memory_order_acquire);
  EXPECT_TRUE(response.ParseFromArray(
      shared_memory::ResponseArea(region_, header.capacity),
      static_cast<int>(answer)));
  return response;
}

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

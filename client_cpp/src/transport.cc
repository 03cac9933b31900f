#include "transport.h"

#include <algorithm>
#include <future>
#include <string>
#include <utility>
#include <vector>

#include "absl/algorithm/container.h"
#include "absl/base/thread_annotations.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/mutex.h"
#include "channel.h"
#include "google/protobuf/io/coded_stream.h"
#include "google/protobuf/io/zero_copy_stream_impl_lite.h"
#include "google/protobuf/wire_format_lite.h"
#include "grpcpp/completion_queue.h"
#include "grpcpp/generic/generic_stub.h"
#include "grpcpp/support/async_unary_call.h"
#include "grpcpp/support/byte_buffer.h"
#include "mll/session_ops.h"

namespace mll::client {
namespace internal {
namespace {

using ::google::protobuf::internal::WireFormatLite;

constexpr char kHealthCheckMethod[] = "/grpc.health.v1.Health/Check";
// ServerInfo.capabilities: PackedSteps.handle on a Session.
constexpr absl::string_view kCapabilityPackedBatchHandles =
    "packed_batch_handles";
// Lease renewals per idle timeout: two more before a lease could expire.
constexpr int kRenewalsPerTimeout = 3;
// Never more often than this, whatever the server's timeout.
constexpr absl::Duration kMinRenewalPeriod = absl::Milliseconds(50);
// A renewal call waits at most this long (or one period).
constexpr absl::Duration kMaxRenewalWait = absl::Seconds(10);
// The most names the server takes in one KeepAlive call.
constexpr int kMaxKeepAliveNames = 10000;
// grpc.health.v1.HealthCheckResponse.ServingStatus.SERVING.
constexpr uint32_t kServing = 1;

// grpc.health.v1 messages are encoded by hand (two fields), so the client
// registers no second copy of health.proto in the process's descriptor pool,
// which would abort a program that links a server beside the client.
std::string EncodeHealthCheckRequest(absl::string_view service) {
  std::string bytes;
  {
    google::protobuf::io::StringOutputStream output(&bytes);
    google::protobuf::io::CodedOutputStream coded(&output);
    if (!service.empty()) {
      WireFormatLite::WriteString(1, std::string(service), &coded);
    }
  }
  return bytes;
}

// The `status` field (1) of a HealthCheckResponse; 0 (UNKNOWN) if absent.
absl::StatusOr<uint32_t> DecodeHealthStatus(const std::string& bytes) {
  google::protobuf::io::CodedInputStream input(
      reinterpret_cast<const uint8_t*>(bytes.data()),
      static_cast<int>(bytes.size()));
  uint32_t status = 0;
  while (uint32_t tag = input.ReadTag()) {
    const bool ok = WireFormatLite::GetTagFieldNumber(tag) == 1 &&
                            WireFormatLite::GetTagWireType(tag) ==
                                WireFormatLite::WIRETYPE_VARINT
                        ? input.ReadVarint32(&status)
                        : WireFormatLite::SkipField(&input, tag);
    if (!ok) {
      return absl::InternalError(
          "malformed grpc.health.v1.HealthCheckResponse");
    }
  }
  return status;
}

absl::string_view HealthStatusName(uint32_t status) {
  switch (status) {
    case 0:
      return "UNKNOWN";
    case 1:
      return "SERVING";
    case 2:
      return "NOT_SERVING";
    case 3:
      return "SERVICE_UNKNOWN";
    default:
      return "unrecognised";
  }
}

class UnaryTransport final : public Transport {
 public:
  using Transport::Transport;

  absl::Status Call(v1::SessionRequest& request,
                    v1::SessionResponse* response) override {
    using Stub = v1::MultiLunarLander::Stub;
    switch (request.op_case()) {
#define MLL_UNARY_CALL(op_case, request_member, rpc, response_member) \
  case v1::SessionRequest::op_case:                                   \
    return Unary(&Stub::rpc, request, request.request_member(),       \
                 response->mutable_##response_member());
      MLL_SESSION_OPS(MLL_UNARY_CALL)
#undef MLL_UNARY_CALL
      case v1::SessionRequest::kAttachSharedMemory:  // A Session's own.
      case v1::SessionRequest::OP_NOT_SET:
        break;
    }
    return absl::InternalError(
        "client bug: SessionRequest without a unary call's op");
  }

  bool is_session() const override { return false; }

  std::future<absl::Status> CallAsync(v1::SessionRequest& request,
                                      v1::SessionResponse* response) override {
    // StepBatch is the one operation a client fans out over servers.
    if (request.op_case() != v1::SessionRequest::kStepBatch) {
      return Transport::CallAsync(request, response);
    }
    // Started now on a completion queue of its own, and completed by the
    // thread that waits for the future: no thread is made or woken for it.
    struct Pending {
      // Drains the queue, as gRPC requires before destroying it; cancels
      // first if nobody waited for the call.
      ~Pending() {
        if (!completed) context.TryCancel();
        queue.Shutdown();
        void* tag = nullptr;
        bool ok = false;
        while (queue.Next(&tag, &ok)) {
        }
      }
      grpc::ClientContext context;
      grpc::CompletionQueue queue;
      grpc::Status status;
      std::unique_ptr<grpc::ClientAsyncResponseReader<v1::StepBatchResponse>>
          reader;
      bool completed = false;
    };
    auto pending = std::make_shared<Pending>();
    const absl::Duration timeout =
        Prepare(&pending->context, /*unary=*/true, &request);
    pending->reader = stub_->PrepareAsyncStepBatch(
        &pending->context, request.step_batch(), &pending->queue);
    pending->reader->StartCall();
    pending->reader->Finish(response->mutable_step_batch(), &pending->status,
                            pending.get());
    return std::async(std::launch::deferred, [this, pending, timeout] {
      void* tag = nullptr;
      bool ok = false;
      // Finish's tag always comes back, with ok true (the status says how
      // the call ended).
      const bool got = pending->queue.Next(&tag, &ok);
      pending->completed = got;
      if (!got) {
        return absl::InternalError("StepBatch completion queue shut down");
      }
      return FromCall(pending->status, timeout);
    });
  }

 private:
  template <typename Request, typename Response>
  absl::Status Unary(grpc::Status (v1::MultiLunarLander::Stub::*method)(
                         grpc::ClientContext*, const Request&, Response*),
                     const v1::SessionRequest& operation,
                     const Request& request, Response* response) {
    grpc::ClientContext context;
    const absl::Duration timeout =
        Prepare(&context, /*unary=*/true, &operation);
    return FromCall((stub_.get()->*method)(&context, request, response),
                    timeout);
  }
};

}  // namespace

absl::Status FromGrpc(const grpc::Status& status) {
  return absl::Status(static_cast<absl::StatusCode>(status.error_code()),
                      status.error_message());
}

absl::Status FromItemError(const v1::ItemError& error) {
  if (error.code() == 0) {
    return absl::InternalError(absl::StrCat(
        "server reported an error with code OK: ", error.message()));
  }
  return absl::Status(static_cast<absl::StatusCode>(error.code()),
                      error.message());
}

Transport::Transport(std::string address,
                     std::shared_ptr<grpc::Channel> channel,
                     ClientOptions options)
    : address_(std::move(address)),
      channel_(std::move(channel)),
      options_(std::move(options)),
      stub_(v1::MultiLunarLander::NewStub(channel_)) {}

Transport::~Transport() {
  {
    absl::MutexLock lock(&lease_mu_);
    stopping_ = true;
    lease_wake_.Signal();
  }
  if (renewer_.joinable()) renewer_.join();
}

void Transport::Hold(const std::string& name, double idle_timeout_s) {
  if (!(idle_timeout_s > 0)) return;
  absl::MutexLock lock(&lease_mu_);
  ++held_[name];
  lease_period_ =
      std::min(lease_period_,
               std::max(absl::Seconds(idle_timeout_s) / kRenewalsPerTimeout,
                        kMinRenewalPeriod));
  if (!renewer_.joinable()) renewer_ = std::thread([this] { RenewLoop(); });
}

void Transport::Unhold(const std::string& name) {
  absl::MutexLock lock(&lease_mu_);
  auto it = held_.find(name);
  if (it != held_.end() && --it->second == 0) held_.erase(it);
}

void Transport::RenewLoop() {
  absl::MutexLock lock(&lease_mu_);
  while (!stopping_) {
    lease_wake_.WaitWithTimeout(&lease_mu_, lease_period_);
    if (stopping_ || held_.empty()) continue;
    std::vector<v1::KeepAliveRequest> requests(1);
    for (const auto& [name, count] : held_) {
      if (requests.back().names_size() == kMaxKeepAliveNames) {
        requests.emplace_back();
      }
      requests.back().add_names(name);
    }
    const absl::Duration deadline = std::min(lease_period_, kMaxRenewalWait);
    lease_mu_.Unlock();  // A round trip: Hold and Unhold must not wait.
    for (const v1::KeepAliveRequest& request : requests) {
      grpc::ClientContext context;
      Prepare(&context, /*unary=*/false);
      context.set_deadline(absl::ToChronoTime(absl::Now() + deadline));
      v1::KeepAliveResponse response;
      // A failure (server unreachable for now) is retried next period; the
      // names the server no longer knows stay held until their handles go.
      (void)stub_->KeepAlive(&context, request, &response);
    }
    lease_mu_.Lock();
  }
}

std::future<absl::Status> Transport::CallAsync(v1::SessionRequest& request,
                                               v1::SessionResponse* response) {
  return std::async(std::launch::async, [this, &request, response] {
    return Call(request, response);
  });
}

absl::Duration Transport::Prepare(grpc::ClientContext* context, bool unary,
                                  const v1::SessionRequest* request) const {
  AddToken(context, options_.token);
  if (!unary) return absl::InfiniteDuration();
  const absl::Duration timeout =
      options_.call_timeout.count() > 0
          ? absl::FromChrono(options_.call_timeout)
      : request == nullptr ? StepTimeout(options_)
                           : AnswerTimeout(StepTimeout(options_), *request);
  if (timeout != absl::InfiniteDuration()) {
    context->set_deadline(absl::ToChronoTime(absl::Now() + timeout));
  }
  return timeout;
}

absl::Status Transport::FromCall(const grpc::Status& status,
                                 absl::Duration timeout) const {
  if (status.error_code() != grpc::StatusCode::DEADLINE_EXCEEDED) {
    return FromGrpc(status);
  }
  return absl::DeadlineExceededError(absl::StrCat(
      "server ", address_, " did not answer within ",
      absl::FormatDuration(timeout),
      options_.call_timeout.count() > 0 ? " (call timeout)" : " (step timeout)",
      ": ", status.error_message()));
}

absl::Status Transport::ListEnvs(const v1::ListEnvsRequest& request,
                                 v1::ListEnvsResponse* response) const {
  grpc::ClientContext context;
  const absl::Duration timeout = Prepare(&context, /*unary=*/true);
  return FromCall(stub_->ListEnvs(&context, request, response), timeout);
}

absl::Status Transport::CheckHealth(absl::string_view service) const {
  const std::string request_bytes = EncodeHealthCheckRequest(service);
  grpc::Slice request_slice(request_bytes);
  grpc::ByteBuffer request(&request_slice, 1);
  grpc::ByteBuffer response;
  grpc::ClientContext context;
  const absl::Duration timeout = Prepare(&context, /*unary=*/true);
  grpc::GenericStub stub(channel_);
  std::promise<grpc::Status> done;
  stub.UnaryCall(&context, kHealthCheckMethod, grpc::StubOptions(), &request,
                 &response,
                 [&done](grpc::Status status) { done.set_value(status); });
  absl::Status status = FromCall(done.get_future().get(), timeout);
  if (!status.ok()) return status;
  grpc::Slice response_slice;
  status = FromGrpc(response.DumpToSingleSlice(&response_slice));
  if (!status.ok()) return status;
  absl::StatusOr<uint32_t> serving = DecodeHealthStatus(
      std::string(reinterpret_cast<const char*>(response_slice.begin()),
                  response_slice.size()));
  if (!serving.ok()) return serving.status();
  if (*serving != kServing) {
    return absl::UnavailableError(
        absl::StrCat("health of service \"", service, "\" is ",
                     HealthStatusName(*serving), "; expected SERVING"));
  }
  return absl::OkStatus();
}

absl::StatusOr<std::shared_ptr<Transport>> Transport::OpenSession() const {
  auto session =
      std::make_shared<StreamTransport>(address_, channel_, options_);
  {
    absl::MutexLock lock(&server_info_mu_);
    if (server_info_.has_value()) {
      absl::MutexLock session_lock(&session->server_info_mu_);
      session->server_info_ = server_info_;
    }
  }
  // Asked for by name, shared memory is refused here, not at the first call.
  if (options_.session_transport == SessionTransport::kSharedMemory) {
    absl::Status status = session->Open();
    if (!status.ok()) return status;
  }
  return std::shared_ptr<Transport>(std::move(session));
}

StreamTransport::StreamTransport(std::string address,
                                 std::shared_ptr<grpc::Channel> channel,
                                 ClientOptions options)
    : Transport(std::move(address), std::move(channel), std::move(options)),
      stream_(channel_, options_.token, absl::StrCat("server ", address_),
              options_.session_transport, StepTimeout(options_)) {}

// Half-closing is not needed: cancelling the stream ends the session, and
// the server deletes its bound envs as it does.
StreamTransport::~StreamTransport() {
  absl::MutexLock lock(&mu_);
  stream_.Close();
}

absl::Status StreamTransport::Open() {
  absl::MutexLock lock(&mu_);
  return stream_.Open();
}

absl::StatusOr<uint64_t> StreamTransport::Send(v1::SessionRequest& request) {
  DecideBatchHandles(request);
  absl::MutexLock lock(&mu_);
  return stream_.Send(request);
}

void StreamTransport::DecideBatchHandles(const v1::SessionRequest& request) {
  if (batch_handles_decided_.load(std::memory_order_acquire) ||
      !request.step_batch().has_packed()) {
    return;
  }
  const absl::StatusOr<v1::ServerInfo> info = ServerInfo();
  const bool enabled =
      info.ok() && absl::c_linear_search(info->capabilities(),
                                         kCapabilityPackedBatchHandles);
  absl::MutexLock lock(&mu_);
  stream_.EnableBatchHandles(enabled);
  batch_handles_decided_.store(true, std::memory_order_release);
}

bool StreamTransport::batch_handles_in_use() {
  absl::MutexLock lock(&mu_);
  return stream_.batch_handles_enabled();
}

absl::Status StreamTransport::Receive(uint64_t sequence,
                                      v1::SessionResponse* response) {
  absl::MutexLock lock(&mu_);
  return stream_.Receive(sequence, response);
}

std::optional<absl::Status> StreamTransport::Receive(
    uint64_t sequence, v1::SessionResponse* response, absl::Duration timeout) {
  absl::MutexLock lock(&mu_);
  return stream_.Receive(sequence, response, timeout);
}

absl::Status StreamTransport::Call(v1::SessionRequest& request,
                                   v1::SessionResponse* response) {
  DecideBatchHandles(request);
  absl::MutexLock lock(&mu_);
  absl::StatusOr<uint64_t> sequence = stream_.Send(request);
  if (!sequence.ok()) return sequence.status();
  return stream_.Receive(*sequence, response);
}

std::future<absl::Status> StreamTransport::CallAsync(
    v1::SessionRequest& request, v1::SessionResponse* response) {
  absl::StatusOr<uint64_t> sequence = Send(request);
  if (!sequence.ok()) {
    std::promise<absl::Status> failed;
    failed.set_value(sequence.status());
    return failed.get_future();
  }
  return std::async(std::launch::deferred, [this, sequence, response] {
    return Receive(*sequence, response);
  });
}

std::string StreamTransport::transport_name() {
  absl::MutexLock lock(&mu_);
  // The choice is made as the stream opens.
  if (!stream_.Open().ok()) return "native";
  return std::string(stream_.transport_name());
}

absl::StatusOr<std::shared_ptr<Transport>> MakeUnaryTransport(
    absl::string_view address, const ClientOptions& options) {
  absl::StatusOr<std::shared_ptr<grpc::Channel>> channel =
      OpenChannel(address, options);
  if (!channel.ok()) return channel.status();
  return std::shared_ptr<Transport>(std::make_shared<UnaryTransport>(
      std::string(address), *std::move(channel), options));
}

}  // namespace internal
}  // namespace mll::client

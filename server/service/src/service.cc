#include "mll/service/service.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <deque>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "google/protobuf/io/coded_stream.h"
#include "google/protobuf/wire_format_lite.h"
#include "grpcpp/support/byte_buffer.h"
#include "grpcpp/support/slice.h"
#include "mll/service/convert.h"
#include "mll/service/load_meter.h"
#include "mll/service/server_info.h"
#include "mll/session_ops.h"
#include "mll/shared_memory_pipe.h"
#include "shared_memory_region.h"

namespace mll::service {
namespace {

int64_t SteadyNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

// The `authorization` metadata of a call, if present.
std::optional<absl::string_view> Authorization(
    const grpc::CallbackServerContext& context) {
  const auto& metadata = context.client_metadata();
  auto it = metadata.find(
      grpc::string_ref(kAuthorizationKey.data(), kAuthorizationKey.size()));
  if (it == metadata.end()) return std::nullopt;
  return absl::string_view(it->second.data(), it->second.size());
}

// Times one call (or Session request) from construction to Record.
class CallTimer {
 public:
  CallTimer(Metrics* metrics, Method method)
      : metrics_(metrics), method_(method), start_ns_(SteadyNowNs()) {}
  void Restart() { start_ns_ = SteadyNowNs(); }
  void Record(const absl::Status& status) const {
    metrics_->RecordCall(method_, status.code(), SteadyNowNs() - start_ns_);
  }

 private:
  Metrics* const metrics_;
  const Method method_;
  int64_t start_ns_;
};

// THE way each operation runs, whether it came as a unary call or on a
// Session stream: the operation itself (Operations), then, on success, its
// step and episode metrics, filed under `via` (the unary method, or
// kSession). Per-call latency and error counts are the caller's (CallTimer).
// Each operation is a method named after its RPC, taking the RPC's request
// and response messages, so that the Session expands mll/session_ops.h's
// table into calls of them.
class Dispatch {
 public:
  // `batches`: the Session's packed batches (null: a unary call).
  Dispatch(Operations* operations, Metrics* metrics, Method via,
           absl::string_view owner, SessionBatches* batches = nullptr)
      : operations_(operations),
        metrics_(metrics),
        via_(via),
        owner_(owner),
        batches_(batches) {}

  // An env created on a Session is bound to it unless detached.
  absl::Status CreateEnv(const v1::CreateEnvRequest& request,
                         v1::Env* out) const {
    return operations_->CreateEnv(
        request, /*session_bound=*/in_session() && !request.detached(), out,
        owner_);
  }
  absl::Status GetEnv(const v1::GetEnvRequest& request, v1::Env* out) const {
    return operations_->GetEnv(request, out, owner_);
  }
  absl::Status ListEnvs(const v1::ListEnvsRequest& request,
                        v1::ListEnvsResponse* out) const {
    return operations_->ListEnvs(request, out, owner_);
  }
  absl::Status DeleteEnv(const v1::DeleteEnvRequest& request,
                         v1::DeleteEnvResponse* /*out*/) const {
    return operations_->DeleteEnv(request, owner_);
  }
  absl::Status ResetEnv(const v1::ResetEnvRequest& request,
                        v1::ResetEnvResponse* out) const {
    absl::Status status = operations_->ResetEnv(request, out, owner_);
    if (status.ok()) metrics_->RecordReset();
    return status;
  }
  // On a Session, errors name the request's fields under `step_env.`.
  absl::Status StepEnv(const v1::StepEnvRequest& request,
                       v1::StepEnvResponse* out) const {
    v1::StepData* data = out->mutable_data();
    absl::Status status = operations_->StepEnv(
        request, in_session() ? "step_env." : "", data, owner_);
    if (status.ok()) metrics_->RecordStepData(via_, *data);
    return status;
  }
  absl::Status StepAgent(const v1::StepAgentRequest& request,
                         v1::StepAgentResponse* out) const {
    absl::Status status = operations_->StepAgent(request, out, owner_);
    if (status.ok()) metrics_->RecordStepAgent(via_, request.has_action());
    return status;
  }
  absl::Status RenderEnv(const v1::RenderEnvRequest& request,
                         v1::Frame* out) const {
    return operations_->RenderEnv(request, out, owner_);
  }
  absl::Status KeepAlive(const v1::KeepAliveRequest& request,
                         v1::KeepAliveResponse* out) const {
    return operations_->KeepAlive(request, out, owner_);
  }
  // Completes on the worker pool: done(status) runs once every item has its
  // result (see Operations::StepBatch).
  template <typename Done>
  void StepBatch(const v1::StepBatchRequest& request,
                 v1::StepBatchResponse* out, Done done) const {
    const bool packed = request.has_packed();
    const bool by_handle = packed && request.packed().handle() != 0 &&
                           request.packed().names().empty();
    operations_->StepBatch(
        request, out,
        [metrics = metrics_, via = via_, out, packed, by_handle,
         done = std::move(done)](absl::Status status) {
          if (status.ok()) {
            metrics->RecordStepBatch(via, *out);
            if (packed) metrics->RecordPackedBatch(by_handle);
          }
          done(status);
        },
        owner_, batches_);
  }

 private:
  bool in_session() const { return via_ == Method::kSession; }

  Operations* const operations_;
  Metrics* const metrics_;
  const Method via_;
  const absl::string_view owner_;
  SessionBatches* const batches_;
};

// The SessionRequest `op` oneof's members, in the proto's order, as the
// error for a request without one lists them.
const std::string& SessionOpNames() {
  static const std::string* const kNames = [] {
    const google::protobuf::OneofDescriptor* op =
        v1::SessionRequest::descriptor()->FindOneofByName("op");
    std::vector<std::string> names;
    for (int i = 0; i < op->field_count(); ++i) {
      names.push_back(op->field(i)->name());
    }
    return new std::string(absl::StrJoin(names, ", "));
  }();
  return *kNames;
}

// Runs a unary call that completes in the handler, admitted as `owner`: runs
// op(dispatch) -> absl::Status, records and finishes.
template <typename Op>
grpc::ServerUnaryReactor* RunUnary(grpc::CallbackServerContext* context,
                                   absl::StatusOr<absl::string_view> owner,
                                   Operations* operations, Metrics* metrics,
                                   Method method, Op op) {
  const CallTimer timer(metrics, method);
  const absl::Status status =
      owner.ok() ? op(Dispatch(operations, metrics, method, *owner))
                 : owner.status();
  timer.Record(status);
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  reactor->Finish(ToGrpcStatus(status));
  return reactor;
}

// Whether a call's peer (grpc::ServerContext::peer) is on this host: a
// loopback address or a Unix-domain socket. Only such a caller can share
// memory with the server.
// (gRPC may write an IPv6 peer's brackets percent-encoded, and a server on
// [::] sees an IPv4 client as an IPv4-mapped address.)
bool IsLocalPeer(absl::string_view peer) {
  for (absl::string_view local :
       {"unix:", "ipv4:127.", "ipv6:[::1]", "ipv6:%5B::1%5D",
        "ipv6:[::ffff:127.", "ipv6:%5B::ffff:127."}) {
    if (absl::StartsWith(peer, local)) return true;
  }
  return false;
}

// UNAVAILABLE "draining: <the server is shutting down>; <what to do>".
absl::Status DrainingError(absl::string_view what_to_do) {
  return absl::UnavailableError(absl::StrCat(
      kDrainingPrefix, "the server is shutting down (SIGTERM); ", what_to_do));
}

// Something the SessionTracker can end when the server drains.
class DrainableSession {
 public:
  virtual void Drain() = 0;

 protected:
  ~DrainableSession() = default;
};

}  // namespace

// The open Session streams, so that draining can end them. A session adds
// itself before its first read and removes itself in OnDone, before it is
// deleted; Drain runs under the tracker's lock, so no session goes while
// it is being drained.
class SessionTracker {
 public:
  void Add(DrainableSession* session) {
    absl::MutexLock lock(&mu_);
    sessions_.insert(session);
    if (draining_) session->Drain();
  }
  void Remove(DrainableSession* session) {
    absl::MutexLock lock(&mu_);
    sessions_.erase(session);
  }
  void DrainAll() {
    absl::MutexLock lock(&mu_);
    draining_ = true;
    for (DrainableSession* session : sessions_) session->Drain();
  }

 private:
  absl::Mutex mu_;
  absl::flat_hash_set<DrainableSession*> sessions_ ABSL_GUARDED_BY(mu_);
  bool draining_ ABSL_GUARDED_BY(mu_) = false;
};

namespace {

// The bytes of the last occurrence of length-delimited field `field_number`
// at the top level of the serialized message `bytes`; nullopt if it has none
// (or the bytes do not parse that far).
std::optional<absl::string_view> FindSubmessage(absl::string_view bytes,
                                                int field_number) {
  using google::protobuf::internal::WireFormatLite;
  google::protobuf::io::CodedInputStream in(
      reinterpret_cast<const uint8_t*>(bytes.data()),
      static_cast<int>(bytes.size()));
  std::optional<absl::string_view> found;
  for (uint32_t tag = in.ReadTag(); tag != 0; tag = in.ReadTag()) {
    if (WireFormatLite::GetTagFieldNumber(tag) != field_number ||
        WireFormatLite::GetTagWireType(tag) !=
            WireFormatLite::WIRETYPE_LENGTH_DELIMITED) {
      if (!WireFormatLite::SkipField(&in, tag)) break;
      continue;
    }
    uint32_t size;
    if (!in.ReadVarint32(&size)) break;
    const int offset = in.CurrentPosition();
    if (!in.Skip(static_cast<int>(size))) break;
    found = bytes.substr(static_cast<size_t>(offset), size);
  }
  return found;
}

// Takes the sub-message that `has` and `release` name out of `message` (null
// if unset), so that clearing `message` does not free it: a proto3 message's
// Clear frees its sub-messages, and a oneof's Clear frees its member.
template <typename Message, typename Sub>
std::unique_ptr<Sub> Keep(Message& message, bool (Message::*has)() const,
                          Sub* (Message::*release)()) {
  return std::unique_ptr<Sub>((message.*has)() ? (message.*release)()
                                               : nullptr);
}

// A Session's request and response, kept from one request to the next
// together with the storage of a packed StepBatch: parsed into last
// request's emptied messages, the env names reuse their strings and the
// actions their bytes, and the results reuse their columns, where fresh
// messages (what a typed stream reads into) would allocate and free each of
// them on every request. A kept sub-message is put back, empty, only where
// the new request's bytes hold it, so a request parses to exactly what it
// would parse to in a fresh message.
class SessionMessages {
 public:
  const v1::SessionRequest& request() const { return request_; }
  v1::SessionResponse& response() { return response_; }

  // Parses a serialized SessionRequest into request(); false if the bytes
  // are not one.
  bool ParseRequest(absl::string_view bytes) {
    std::unique_ptr<v1::StepBatchRequest> batch =
        Keep(request_, &v1::SessionRequest::has_step_batch,
             &v1::SessionRequest::release_step_batch);
    request_.Clear();
    if (batch != nullptr) {
      const std::optional<absl::string_view> batch_bytes =
          FindSubmessage(bytes, v1::SessionRequest::kStepBatchFieldNumber);
      if (batch_bytes.has_value()) {
        EmptyForParse(*batch_bytes, *batch);
        request_.set_allocated_step_batch(batch.release());
      }
    }
    google::protobuf::io::CodedInputStream in(
        reinterpret_cast<const uint8_t*>(bytes.data()),
        static_cast<int>(bytes.size()));
    return request_.MergeFromCodedStream(&in) && in.ConsumedEntireMessage();
  }

  // Clears response(), keeping its step_batch for StepBatchResponse().
  void ClearResponse() {
    if (response_.has_step_batch()) {
      kept_response_batch_.reset(response_.release_step_batch());
    }
    response_.Clear();
  }

  // response()'s step_batch for the answer to `request`, empty but for the
  // columns of a packed answer, which StepPacked rewrites whole (each one
  // sized and zeroed: PackedColumns).
  v1::StepBatchResponse* StepBatchResponse(
      const v1::StepBatchRequest& request) {
    if (kept_response_batch_ != nullptr) {
      std::unique_ptr<v1::PackedStepData> packed =
          Keep(*kept_response_batch_, &v1::StepBatchResponse::has_packed,
               &v1::StepBatchResponse::release_packed);
      kept_response_batch_->Clear();
      if (packed != nullptr && request.has_packed()) {
        packed->clear_errors();
        kept_response_batch_->set_allocated_packed(packed.release());
      }
      response_.set_allocated_step_batch(kept_response_batch_.release());
    }
    return response_.mutable_step_batch();
  }

 private:
  // Empties `batch` for parsing `bytes` (a serialized StepBatchRequest) into
  // it, keeping its packed names and actions where the bytes hold them.
  static void EmptyForParse(absl::string_view bytes,
                            v1::StepBatchRequest& batch) {
    std::unique_ptr<v1::PackedSteps> packed =
        Keep(batch, &v1::StepBatchRequest::has_packed,
             &v1::StepBatchRequest::release_packed);
    batch.Clear();
    if (packed == nullptr) return;
    const std::optional<absl::string_view> packed_bytes =
        FindSubmessage(bytes, v1::StepBatchRequest::kPackedFieldNumber);
    if (!packed_bytes.has_value()) return;
    std::unique_ptr<v1::Array> actions =
        Keep(*packed, &v1::PackedSteps::has_actions,
             &v1::PackedSteps::release_actions);
    packed->Clear();  // The names' strings stay, for the parser to reuse.
    if (actions != nullptr &&
        FindSubmessage(*packed_bytes, v1::PackedSteps::kActionsFieldNumber)) {
      actions->Clear();
      packed->set_allocated_actions(actions.release());
    }
    batch.set_allocated_packed(packed.release());
  }

  v1::SessionRequest request_;
  v1::SessionResponse response_;
  std::unique_ptr<v1::StepBatchResponse> kept_response_batch_;
};

// One Session stream: runs its requests one at a time, in order, and writes
// their answers in the same order. The stream is pipelined: for a client
// that sends before it has its answers, the next request is read while one
// runs, and starts as soon as the one before it is done, while that one's
// answer is still being written; so a client with several requests in
// flight keeps the workers busy between them (a client that waits for each
// answer gets its next request read once the answer is queued:
// StartNextRead). At most one
// request waits, read but not run, and at most kQueuedAnswers answers wait
// for the client to take them; past that the stream reads no more (the
// client's requests wait in HTTP/2 flow control). Envs it created (not
// detached) are deleted when the stream ends, however it ends. The caller is
// authenticated once, when the stream opens; every request then acts as that
// owner.
//
// After attach_shared_memory succeeds, the requests come through the
// session's shared-memory region instead (mll/shared_memory_pipe.h), served
// by a thread of the session's own; the stream then only marks the
// session's life, and a request sent on it gets FAILED_PRECONDITION.
//
// Draining (Drain, from the tracker) ends the stream with UNAVAILABLE
// "draining: ..." at once when nothing runs or waits to be written, else
// once the running request has answered; a request read but not yet run is
// not run. A client that half-closes gets the answers to everything it sent
// first. gRPC runs no read or write reaction inline, so the stream's
// operations are started under mu_; a request runs outside it.
class SessionReactor final
    : public grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>,
      public DrainableSession {
 public:
  SessionReactor(Operations* operations, Registry* registry, Metrics* metrics,
                 SharedMemorySessions* shared_memory_sessions,
                 SessionTracker* tracker, const std::atomic<bool>* draining,
                 bool local_peer, absl::StatusOr<absl::string_view> owner)
      : operations_(operations),
        registry_(registry),
        metrics_(metrics),
        shared_memory_sessions_(shared_memory_sessions),
        tracker_(tracker),
        draining_(draining),
        local_peer_(local_peer),
        timer_(metrics, Method::kSession) {
    if (!owner.ok()) {
      timer_.Record(owner.status());
      Finish(ToGrpcStatus(owner.status()));
      return;
    }
    owner_ = *owner;
    tracked_ = true;
    {
      absl::MutexLock lock(&mu_);
      reading_ = true;  // The first read is as good as started.
    }
    tracker_->Add(this);  // Drains this stream at once while draining.
    absl::MutexLock lock(&mu_);
    if (!finished_) StartRead(&read_buffer_);
  }

  void Drain() override {
    absl::MutexLock lock(&mu_);
    if (finished_ || drain_asked_) return;
    drain_asked_ = true;
    EndIfDone();
  }

  void OnReadDone(bool ok) override {
    std::optional<ReadRequest> next;
    {
      absl::MutexLock lock(&mu_);
      reading_ = false;
      if (finished_) return;  // Drained: the request, if any, is not run.
      if (!ok) {  // The client half-closed, or the call was cancelled.
        half_closed_ = true;
        EndIfDone();
        return;
      }
      // A request that comes before the last answer was written: the client
      // pipelines.
      pipelined_ = running_ || !answers_.empty();
      waiting_request_.emplace();
      waiting_request_->readable =
          read_buffer_.DumpToSingleSlice(&waiting_request_->bytes).ok();
      read_buffer_.Clear();
      next = TakeNextRequest();
    }
    Drive(std::move(next));
  }

  void OnWriteDone(bool ok) override {
    std::optional<ReadRequest> next;
    {
      absl::MutexLock lock(&mu_);
      writing_ = false;
      answers_.pop_front();
      if (!ok) {  // The stream broke; nobody reads any more answers.
        broken_ = true;
        EndIfDone();
        return;
      }
      if (!answers_.empty()) {
        writing_ = true;
        StartWrite(&answers_.front());
      }
      if (EndIfDone()) return;
      next = TakeNextRequest();
    }
    Drive(std::move(next));
  }

  // Also covers a stream that ended without EndStream (e.g. cancelled while a
  // write was pending). Leaves the tracker first, which waits for a Drain
  // under way.
  void OnDone() override {
    if (tracked_) tracker_->Remove(this);
    StopServingSharedMemory();
    DeleteBoundEnvs();
    delete this;
  }

 private:
  // Answers that may wait to be written, the one being written included.
  static constexpr size_t kQueuedAnswers = 2;

  // A request as read from the stream.
  struct ReadRequest {
    grpc::Slice bytes;
    bool readable = false;  // Its bytes could be taken from gRPC's buffer.
  };

  // The waiting request, to run now if nothing runs and its answer has room;
  // the next read starts once it is taken. Under mu_.
  std::optional<ReadRequest> TakeNextRequest()
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) {
    if (running_ || !waiting_request_.has_value() || finished_ ||
        drain_asked_ || broken_ || answers_.size() >= kQueuedAnswers) {
      return std::nullopt;
    }
    std::optional<ReadRequest> next = std::move(waiting_request_);
    waiting_request_.reset();
    running_ = true;
    if (pipelined_) StartNextRead();
    return next;
  }

  // Starts reading the next request unless one is being read or waits. For
  // a client that pipelines, as soon as a request is taken to run (so the
  // next one is at hand when it is done); for one that waits for each answer
  // before it sends again, once the answer is queued: a read pending while
  // the request runs makes gRPC announce the consumed flow-control window at
  // once, in a write (and a wake-up of the client) of its own, where a read
  // started after the answer's write sends the announcement with the answer.
  // Under mu_.
  void StartNextRead() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) {
    if (reading_ || half_closed_ || finished_ || waiting_request_.has_value()) {
      return;
    }
    reading_ = true;
    StartRead(&read_buffer_);
  }

  // Ends the stream if it is over: broken, drained or half-closed, with no
  // request running and, unless broken, every answer written. Under mu_;
  // true if it ended.
  bool EndIfDone() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) {
    if (finished_ || running_ || writing_) return false;
    if (broken_) {
      EndStream();
      return true;
    }
    if (!answers_.empty()) return false;
    if (drain_asked_) {
      FinishDraining();
      return true;
    }
    // A read starts only once no request waits, so none waits here.
    if (half_closed_) {
      EndStream();
      return true;
    }
    return false;
  }

  // Runs `next` and then each request that waits when the one before it is
  // answered, all on this thread, until none waits. A StepBatch's items run
  // on this thread and the idle workers (WorkerPool::ParallelFor), so the
  // thread waits for the workers before it answers and goes on.
  void Drive(std::optional<ReadRequest> next) {
    while (next.has_value()) next = Answer(RunReadRequest(*next));
  }

  // Runs one serialized request into messages_.response(). Only one runs at
  // a time (running_), so it has messages_ to itself.
  absl::Status RunReadRequest(const ReadRequest& read) {
    timer_.Restart();
    messages_.ClearResponse();
    if (!read.readable || !messages_.ParseRequest(absl::string_view(
                              reinterpret_cast<const char*>(read.bytes.begin()),
                              read.bytes.size()))) {
      return absl::InvalidArgumentError(
          "request: not a serialized SessionRequest");
    }
    const v1::SessionRequest& request = messages_.request();
    messages_.response().set_sequence(request.sequence());
    if (region_ != nullptr) {
      return absl::FailedPreconditionError(absl::StrCat(
          "op: sent on the stream (sequence ", request.sequence(),
          ") of a session attached to shared memory; allowed: requests "
          "through the shared-memory region"));
    }
    if (request.op_case() == v1::SessionRequest::kAttachSharedMemory) {
      return AttachSharedMemory();
    }
    return ExecuteAndWait(messages_);
  }

  // The bound envs go before the final status does, so a client that sees
  // the stream end never finds them still listed. Under mu_.
  void EndStream() {
    finished_ = true;
    StopServingSharedMemory();
    DeleteBoundEnvs();
    Finish(grpc::Status::OK);
  }

  // As EndStream, with the status that tells the client to move. Under mu_,
  // with no request running and no answer waiting.
  void FinishDraining() {
    finished_ = true;
    StopServingSharedMemory();
    DeleteBoundEnvs();
    const absl::Status status =
        DrainingError("move this session's environments to another server");
    timer_.Record(status);
    Finish(ToGrpcStatus(status));
  }

  void DeleteBoundEnvs() {
    for (const std::string& name : bound_envs_) {
      // Already deleted or reclaimed is fine: the goal is that it is gone.
      registry_->Delete(name, "name", owner_).IgnoreError();
    }
    bound_envs_.clear();
  }

  Dispatch dispatch() {
    return Dispatch(operations_, metrics_, Method::kSession, owner_, &batches_);
  }

  // Runs messages.request() into messages.response() and returns its
  // status; a StepBatch's items on this thread and the idle workers, which
  // it waits for.
  absl::Status ExecuteAndWait(SessionMessages& messages) {
    const v1::SessionRequest& request = messages.request();
    if (request.op_case() != v1::SessionRequest::kStepBatch) {
      return Run(request, &messages.response());
    }
    absl::Status status;
    absl::Notification finished;
    dispatch().StepBatch(request.step_batch(),
                         messages.StepBatchResponse(request.step_batch()),
                         [&](absl::Status done) {
                           status = std::move(done);
                           finished.Notify();
                         });
    finished.WaitForNotification();
    return status;
  }

  // Runs a request that completes in the call: its RPC's Dispatch method
  // (mll/session_ops.h), then the session's record of its bound envs.
  absl::Status Run(const v1::SessionRequest& request,
                   v1::SessionResponse* response) {
    if (request.op_case() == v1::SessionRequest::kCreateEnv &&
        draining_->load()) {
      return DrainingError("create environments on another server");
    }
    const Dispatch run = dispatch();
    absl::Status status;
    switch (request.op_case()) {
#define MLL_SESSION_RUN(op_case, request_member, rpc, response_member) \
  case v1::SessionRequest::op_case:                                    \
    status = run.rpc(request.request_member(),                         \
                     response->mutable_##response_member());           \
    break;
      MLL_SESSION_SYNC_OPS(MLL_SESSION_RUN)
#undef MLL_SESSION_RUN
      case v1::SessionRequest::kAttachSharedMemory:
        return absl::FailedPreconditionError(
            "attach_shared_memory: the session is attached already");
      default:
        return absl::InvalidArgumentError(
            absl::StrCat("op: not set (sequence ", request.sequence(),
                         "); allowed: ", SessionOpNames()));
    }
    if (!status.ok()) return status;
    if (request.has_create_env() && !request.create_env().detached()) {
      bound_envs_.insert(response->env().name());
    } else if (request.has_delete_env()) {
      // Forgotten at once: a long session creating and deleting envs must
      // not grow (found by bench/load soak, +39 MB per 1M cycles).
      bound_envs_.erase(request.delete_env().name());
    }
    return status;
  }

  // Queues the running request's answer (messages_.response(), or the
  // error `status`) to be written; returns the next request to run, if one
  // waits and may run now.
  std::optional<ReadRequest> Answer(const absl::Status& status) {
    timer_.Record(status);
    v1::SessionResponse& response = messages_.response();
    if (!status.ok()) {
      response.clear_result();
      FillItemError(status, response.mutable_error());
    }
    grpc::ByteBuffer answer;
    bool own_buffer;
    const grpc::Status serialized =
        grpc::SerializationTraits<v1::SessionResponse>::Serialize(
            response, &answer, &own_buffer);
    if (!serialized.ok()) {
      response.clear_result();
      FillItemError(
          absl::InternalError(absl::StrCat("response: cannot be serialized (",
                                           serialized.error_message(), ")")),
          response.mutable_error());
      answer.Clear();
      (void)grpc::SerializationTraits<v1::SessionResponse>::Serialize(
          response, &answer, &own_buffer);
    }
    absl::MutexLock lock(&mu_);
    running_ = false;
    if (!finished_ && !broken_) {
      answers_.push_back(std::move(answer));
      if (!writing_) {
        writing_ = true;
        StartWrite(&answers_.front());
      }
    }
    if (EndIfDone()) return std::nullopt;
    std::optional<ReadRequest> next = TakeNextRequest();
    if (!next.has_value() && !broken_ && !drain_asked_) StartNextRead();
    return next;
  }

  // Creates the session's region and starts the thread that serves it.
  absl::Status AttachSharedMemory() {
    if (!local_peer_) {
      return absl::PermissionDeniedError(
          "attach_shared_memory: the caller is not on the server's host "
          "(allowed: a loopback address or a Unix-domain socket)");
    }
    absl::StatusOr<SharedMemorySessions::Slot> slot =
        shared_memory_sessions_->Take();
    if (!slot.ok()) return slot.status();
    absl::StatusOr<std::unique_ptr<SharedMemoryRegion>> region =
        SharedMemoryRegion::Create();
    if (!region.ok()) return region.status();
    slot_ = *std::move(slot);
    region_ = *std::move(region);
    v1::AttachSharedMemoryResponse* attached =
        messages_.response().mutable_attach_shared_memory();
    attached->set_path(region_->path());
    attached->set_size(region_->bytes());
    attached->set_nonce(region_->nonce());
    server_thread_ = std::thread([this] { ServeSharedMemory(); });
    return absl::OkStatus();
  }

  // The shared-memory session's loop: waits for each request (spinning
  // briefly first: the client usually sends its next request within a
  // fraction of a millisecond), runs it as a stream's request would run,
  // and answers through the region.
  void ServeSharedMemory() {
    shared_memory::Header& header = region_->header();
    // The region is new: no request yet (the client may write its first
    // before this thread starts).
    uint32_t seen = 0;
    std::string bytes;
    SessionMessages messages;
    v1::SessionResponse& response = messages.response();
    while (!stop_serving_.load(std::memory_order_acquire)) {
      if (!shared_memory::WaitWhileEqual(header.request_seq, seen,
                                         std::chrono::microseconds(100),
                                         std::chrono::milliseconds(50))) {
        continue;
      }
      if (stop_serving_.load(std::memory_order_acquire)) break;
      seen = header.request_seq.load(std::memory_order_acquire);
      CallTimer timer(metrics_, Method::kSession);
      const uint64_t size = header.request_size.load(std::memory_order_acquire);
      messages.ClearResponse();
      absl::Status status;
      // Copied before parsing: the client can write the region at any time.
      if (size > region_->capacity()) {
        status = absl::InvalidArgumentError(
            absl::StrCat("request_size: ", size, " bytes; allowed: 0..",
                         region_->capacity(), " (the region's capacity)"));
      } else {
        bytes.assign(region_->request(), size);
        if (!messages.ParseRequest(bytes)) {
          status = absl::InvalidArgumentError(
              "request: not a serialized SessionRequest");
        } else {
          response.set_sequence(messages.request().sequence());
          status = ExecuteAndWait(messages);
        }
      }
      timer.Record(status);
      if (!status.ok()) {
        response.clear_result();
        FillItemError(status, response.mutable_error());
      }
      uint64_t written = response.ByteSizeLong();
      if (written > region_->capacity()) {
        response.clear_result();
        FillItemError(
            absl::ResourceExhaustedError(absl::StrCat(
                "response: ", written, " bytes; allowed: 0..",
                region_->capacity(), " (the shared-memory region's capacity)")),
            response.mutable_error());
        written = response.ByteSizeLong();
      }
      response.SerializeWithCachedSizesToArray(
          reinterpret_cast<uint8_t*>(region_->response()));
      header.response_size.store(written, std::memory_order_release);
      header.response_seq.store(seen, std::memory_order_release);
      shared_memory::Wake(header.response_seq);
    }
  }

  void StopServingSharedMemory() {
    if (!server_thread_.joinable()) return;
    stop_serving_.store(true, std::memory_order_release);
    // Wakes the thread if it sleeps on the request counter.
    shared_memory::Wake(region_->header().request_seq);
    server_thread_.join();
    region_.reset();
    slot_ = SharedMemorySessions::Slot();
  }

  Operations* const operations_;
  Registry* const registry_;
  Metrics* const metrics_;
  SharedMemorySessions* const shared_memory_sessions_;
  SessionTracker* const tracker_;
  const std::atomic<bool>* const draining_;
  const bool local_peer_;
  bool tracked_ = false;  // Added to tracker_ (an admitted stream).
  absl::Mutex mu_;
  // A read is pending.
  bool reading_ ABSL_GUARDED_BY(mu_) = false;
  // The last request came while one ran or an answer was being written
  // (StartNextRead).
  bool pipelined_ ABSL_GUARDED_BY(mu_) = false;
  // A request runs (from TakeNextRequest to Answer).
  bool running_ ABSL_GUARDED_BY(mu_) = false;
  // The answer at the front of answers_ is being written.
  bool writing_ ABSL_GUARDED_BY(mu_) = false;
  // Finish was called (or is about to be, by EndStream).
  bool finished_ ABSL_GUARDED_BY(mu_) = false;
  // Drain was called: the stream ends once the running request answered.
  bool drain_asked_ ABSL_GUARDED_BY(mu_) = false;
  // The client half-closed: the stream ends once everything is answered.
  bool half_closed_ ABSL_GUARDED_BY(mu_) = false;
  // A write failed: the stream ends once no request runs.
  bool broken_ ABSL_GUARDED_BY(mu_) = false;
  // A request read and not yet run.
  std::optional<ReadRequest> waiting_request_ ABSL_GUARDED_BY(mu_);
  // Answers to write, in request order; the front one is being written.
  std::deque<grpc::ByteBuffer> answers_ ABSL_GUARDED_BY(mu_);
  // Points into the Authenticator, which outlives every call.
  absl::string_view owner_;
  // The running request uses them.
  SessionBatches batches_;
  CallTimer timer_;
  SessionMessages messages_;
  grpc::ByteBuffer read_buffer_;
  absl::flat_hash_set<std::string> bound_envs_;
  // Set while the session is attached to shared memory.
  SharedMemorySessions::Slot slot_;
  std::unique_ptr<SharedMemoryRegion> region_;
  std::thread server_thread_;
  std::atomic<bool> stop_serving_{false};
};

// One call's request and response and the arena they live on, freed
// together when gRPC releases the call.
class StepBatchMessages final
    : public grpc::MessageHolder<v1::StepBatchRequest, v1::StepBatchResponse> {
 public:
  StepBatchMessages() : arena_(Options()) {
    set_request(
        google::protobuf::Arena::CreateMessage<v1::StepBatchRequest>(&arena_));
    set_response(
        google::protobuf::Arena::CreateMessage<v1::StepBatchResponse>(&arena_));
  }
  void Release() override { delete this; }

 private:
  // A first block that holds a 64-env `steps` batch's request and response,
  // so that such a call takes one allocation.
  static google::protobuf::ArenaOptions Options() {
    google::protobuf::ArenaOptions options;
    options.start_block_size = 128 << 10;
    options.max_block_size = 1 << 20;
    return options;
  }

  google::protobuf::Arena arena_;
};

}  // namespace

grpc::MessageHolder<v1::StepBatchRequest, v1::StepBatchResponse>*
MultiLunarLanderService::StepBatchArenas::AllocateMessages() {
  return new StepBatchMessages();
}

absl::StatusOr<SharedMemorySessions::Slot> SharedMemorySessions::Take() {
  if (limit_ == 0) {
    return absl::PermissionDeniedError(
        "attach_shared_memory: the server runs with "
        "--shared_memory_sessions=0");
  }
  if (attached_.fetch_add(1) >= limit_) {
    attached_.fetch_sub(1);
    return absl::ResourceExhaustedError(absl::StrCat(
        "attach_shared_memory: ", limit_,
        " sessions are attached (--shared_memory_sessions); allowed: at most ",
        limit_));
  }
  return Slot(&attached_);
}

int EffectiveMaxEnvsPerToken(const ServiceOptions& options) {
  if (options.max_envs_per_token > 0) return options.max_envs_per_token;
  if (options.auth_tokens.empty()) return 0;
  return std::max(
      1, options.max_envs / static_cast<int>(options.auth_tokens.size()));
}

MultiLunarLanderService::MultiLunarLanderService(const ServiceOptions& options)
    : sessions_(std::make_unique<SessionTracker>()),
      authenticator_(options.auth_tokens),
      registry_(options.max_envs, options.idle_timeout,
                EffectiveMaxEnvsPerToken(options)),
      operations_(&registry_, &pool_),
      pool_(options.threads),
      shared_memory_sessions_(options.shared_memory_sessions),
      server_info_(MakeServerInfo(options)) {
  SetMessageAllocatorFor_StepBatch(&step_batch_arenas_);
  // Session as a raw method: its stream parses requests itself
  // (SessionMessages), in place of the typed handler CallbackService set.
  const int session_method = v1::SessionRequest::descriptor()
                                 ->file()
                                 ->FindServiceByName("MultiLunarLander")
                                 ->FindMethodByName("Session")
                                 ->index();
  MarkMethodRawCallback(
      session_method, new grpc::internal::CallbackBidiHandler<grpc::ByteBuffer,
                                                              grpc::ByteBuffer>(
                          [this](grpc::CallbackServerContext* context) {
                            return OpenSession(context);
                          }));
}

MultiLunarLanderService::~MultiLunarLanderService() = default;

std::string MultiLunarLanderService::MetricsText() {
  return metrics_.Render(registry_.size(), registry_.SizeByOwner());
}

absl::StatusOr<absl::string_view> MultiLunarLanderService::Admit(
    const grpc::CallbackServerContext& context) const {
  if (refusing_.load()) {
    return absl::UnavailableError(
        "the server is shutting down; retry on another server");
  }
  return authenticator_.Authenticate(Authorization(context));
}

absl::StatusOr<absl::string_view> MultiLunarLanderService::AdmitNewWork(
    const grpc::CallbackServerContext& context, absl::string_view what) const {
  if (draining_.load() && !refusing_.load()) return DrainingError(what);
  return Admit(context);
}

void MultiLunarLanderService::StartDraining() {
  draining_.store(true);
  sessions_->DrainAll();
}

grpc::ServerUnaryReactor* MultiLunarLanderService::CreateEnv(
    grpc::CallbackServerContext* context, const v1::CreateEnvRequest* request,
    v1::Env* response) {
  return RunUnary(
      context, AdmitNewWork(*context, "create environments on another server"),
      &operations_, &metrics_, Method::kCreateEnv,
      [&](const Dispatch& run) { return run.CreateEnv(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::GetEnv(
    grpc::CallbackServerContext* context, const v1::GetEnvRequest* request,
    v1::Env* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kGetEnv,
      [&](const Dispatch& run) { return run.GetEnv(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::ListEnvs(
    grpc::CallbackServerContext* context, const v1::ListEnvsRequest* request,
    v1::ListEnvsResponse* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kListEnvs,
      [&](const Dispatch& run) { return run.ListEnvs(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::DeleteEnv(
    grpc::CallbackServerContext* context, const v1::DeleteEnvRequest* request,
    v1::DeleteEnvResponse* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kDeleteEnv,
      [&](const Dispatch& run) { return run.DeleteEnv(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::ResetEnv(
    grpc::CallbackServerContext* context, const v1::ResetEnvRequest* request,
    v1::ResetEnvResponse* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kResetEnv,
      [&](const Dispatch& run) { return run.ResetEnv(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::StepEnv(
    grpc::CallbackServerContext* context, const v1::StepEnvRequest* request,
    v1::StepEnvResponse* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kStepEnv,
      [&](const Dispatch& run) { return run.StepEnv(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::StepAgent(
    grpc::CallbackServerContext* context, const v1::StepAgentRequest* request,
    v1::StepAgentResponse* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kStepAgent,
      [&](const Dispatch& run) { return run.StepAgent(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::StepBatch(
    grpc::CallbackServerContext* context, const v1::StepBatchRequest* request,
    v1::StepBatchResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  const CallTimer timer(&metrics_, Method::kStepBatch);
  absl::StatusOr<absl::string_view> owner = Admit(*context);
  if (!owner.ok()) {
    timer.Record(owner.status());
    reactor->Finish(ToGrpcStatus(owner.status()));
    return reactor;
  }
  Dispatch(&operations_, &metrics_, Method::kStepBatch, *owner)
      .StepBatch(*request, response, [reactor, timer](absl::Status status) {
        timer.Record(status);
        reactor->Finish(ToGrpcStatus(status));
      });
  return reactor;
}

grpc::ServerUnaryReactor* MultiLunarLanderService::RenderEnv(
    grpc::CallbackServerContext* context, const v1::RenderEnvRequest* request,
    v1::Frame* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kRenderEnv,
      [&](const Dispatch& run) { return run.RenderEnv(*request, response); });
}

grpc::ServerUnaryReactor* MultiLunarLanderService::KeepAlive(
    grpc::CallbackServerContext* context, const v1::KeepAliveRequest* request,
    v1::KeepAliveResponse* response) {
  return RunUnary(
      context, Admit(*context), &operations_, &metrics_, Method::kKeepAlive,
      [&](const Dispatch& run) { return run.KeepAlive(*request, response); });
}

// CPU is clamped to the cores available: the interpolated window can
// overshoot them by a sample's rounding, never the process its CPUs.
void MultiLunarLanderService::FillLoad(v1::ServerLoad* load) {
  const LoadMeter::Rates rates = metrics_.RecentLoad();
  const double cores = CoresAvailable();
  load->set_envs_hosted(registry_.size());
  load->set_cpu_cores(std::min(rates.cpu_cores, cores));
  load->set_cores_available(cores);
  load->set_agent_steps_per_s(rates.agent_steps_per_s);
}

// Admitted like every call (a token when the server has tokens): what the
// server is and its limits are for its clients only.
grpc::ServerUnaryReactor* MultiLunarLanderService::GetServerInfo(
    grpc::CallbackServerContext* context,
    const v1::GetServerInfoRequest* /*request*/, v1::ServerInfo* response) {
  return RunUnary(context, AdmitNewWork(*context, "use another server"),
                  &operations_, &metrics_, Method::kGetServerInfo,
                  [&](const Dispatch&) {
                    *response = server_info_;
                    FillLoad(response->mutable_load());
                    return absl::OkStatus();
                  });
}

grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>*
MultiLunarLanderService::OpenSession(grpc::CallbackServerContext* context) {
  return new SessionReactor(
      &operations_, &registry_, &metrics_, &shared_memory_sessions_,
      sessions_.get(), &draining_, IsLocalPeer(context->peer()),
      AdmitNewWork(*context, "open the Session on another server"));
}

}  // namespace mll::service

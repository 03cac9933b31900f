#include "session_stream.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/time/clock.h"
#include "channel.h"
#include "grpc/grpc.h"
#include "mll/shared_memory_pipe.h"
#include "transport.h"

namespace mll::client {

absl::string_view SessionTransportName(SessionTransport transport) {
  switch (transport) {
    case SessionTransport::kAuto:
      return "auto";
    case SessionTransport::kSharedMemory:
      return "shared_memory";
    case SessionTransport::kNative:
      return "native";
  }
  return "unknown";
}

namespace internal {
namespace {

namespace shared_memory = ::mll::shared_memory;

constexpr char kSessionMethod[] = "/mll.v1.MultiLunarLander/Session";
// How long one futex wait on the region lasts before the stream is looked
// at (did the session end?) and the caller's deadline checked.
constexpr auto kRegionWaitSlice = std::chrono::milliseconds(20);
// A StepBatch's answer may take this much longer than step_timeout per
// lander action it carries, so that a slow server with a large batch is not
// taken for a stopped one: eight clients' batches of 1024 3-lander envs on a
// loaded 2-core server took up to 2.5 s each, about 800 us per action of the
// call's own batch at 22,000 actions/s in all (docs/benchmarks.md, "Step
// deadline"), so a batch of any size gets more than that: 1 ms per action.
constexpr absl::Duration kAnswerTimePerAction = absl::Milliseconds(1);

void* TagOf(intptr_t operation) {
  return reinterpret_cast<void*>(operation + 1);
}

intptr_t OperationOf(void* tag) { return reinterpret_cast<intptr_t>(tag) - 1; }

gpr_timespec DeadlineAfter(absl::Duration timeout) {
  if (timeout == absl::InfiniteDuration()) {
    return gpr_inf_future(GPR_CLOCK_MONOTONIC);
  }
  return gpr_time_add(
      gpr_now(GPR_CLOCK_MONOTONIC),
      gpr_time_from_micros(absl::ToInt64Microseconds(timeout), GPR_TIMESPAN));
}

}  // namespace

template <typename Names>
uint32_t BatchHandles::HandleOf(const Names& names) {
  const auto same = [&names](const Declared& declared) {
    return declared.names.size() == static_cast<size_t>(names.size()) &&
           std::equal(declared.names.begin(), declared.names.end(),
                      names.begin());
  };
  Declared* victim = nullptr;
  for (Declared& declared : declared_) {
    if (same(declared)) {
      declared.last_used = ++clock_;
      return static_cast<uint32_t>(&declared - declared_.data()) + 1;
    }
    if (victim == nullptr || declared.last_used < victim->last_used) {
      victim = &declared;
    }
  }
  if (declared_.size() < kMaxHandle) {
    victim = &declared_.emplace_back();
  }
  const size_t held = declared_envs_ - victim->names.size();
  if (held + static_cast<size_t>(names.size()) > kMaxDeclaredEnvs) return 0;
  declared_envs_ = held + static_cast<size_t>(names.size());
  victim->names.assign(names.begin(), names.end());
  victim->version = ++versions_;
  victim->answered = false;
  victim->last_used = ++clock_;
  return static_cast<uint32_t>(victim - declared_.data()) + 1;
}

std::string BatchHandles::Serialize(v1::SessionRequest& request) {
  if (!request.has_step_batch() || !request.step_batch().has_packed() ||
      request.step_batch().packed().handle() != 0 ||
      request.step_batch().packed().names().empty()) {
    return request.SerializeAsString();
  }
  v1::PackedSteps& packed = *request.mutable_step_batch()->mutable_packed();
  const uint32_t handle = HandleOf(packed.names());
  if (handle == 0) return request.SerializeAsString();
  const Declared& declared = declared_[handle - 1];
  packed.set_handle(handle);
  std::string bytes;
  if (declared.answered) {
    // The names are left out for the serialization, and put back.
    google::protobuf::RepeatedPtrField<std::string> names;
    names.Swap(packed.mutable_names());
    bytes = request.SerializeAsString();
    names.Swap(packed.mutable_names());
  } else {
    bytes = request.SerializeAsString();
    declaring_[request.sequence()] = {handle, declared.version};
  }
  packed.set_handle(0);
  return bytes;
}

void BatchHandles::Answered(uint64_t sequence, bool ok) {
  const auto it = declaring_.find(sequence);
  if (it == declaring_.end()) return;
  const auto [handle, version] = it->second;
  declaring_.erase(it);
  Declared& declared = declared_[handle - 1];
  if (ok && declared.version == version) declared.answered = true;
}

void BatchHandles::Clear() {
  declared_.clear();
  declared_envs_ = 0;
  declaring_.clear();
}

SessionStream::SessionStream(
    absl::StatusOr<std::shared_ptr<grpc::Channel>> channel, std::string token,
    std::string what, SessionTransport mode, absl::Duration step_timeout)
    : channel_status_(channel.status()),
      token_(std::move(token)),
      what_(std::move(what)),
      mode_(mode),
      step_timeout_(step_timeout) {
  if (channel.ok()) {
    stub_ = std::make_unique<grpc::GenericStub>(*std::move(channel));
  }
}

SessionStream::~SessionStream() { Close(); }

absl::string_view SessionStream::transport_name() const {
  return attached_ ? "shared_memory" : "native";
}

absl::Status SessionStream::Open() {
  if (stream_ != nullptr) return absl::OkStatus();
  absl::Status status = OpenStream();
  if (status.ok() && mode_ != SessionTransport::kNative) {
    status = NegotiateSharedMemory();
  }
  return Fail(status);
}

absl::Status SessionStream::OpenStream() {
  if (!channel_status_.ok()) return channel_status_;
  batch_handles_.Clear();  // A new session.
  queue_ = std::make_unique<grpc::CompletionQueue>();
  context_ = std::make_unique<grpc::ClientContext>();
  AddToken(context_.get(), token_);
  stream_ = stub_->PrepareCall(context_.get(), kSessionMethod, queue_.get());
  stream_->StartCall(TagOf(kStart));
  const std::optional<bool> started =
      Await(kStart, DeadlineAfter(step_timeout_));
  if (!started.has_value()) {
    return Abandon("the start of its Session stream", step_timeout_);
  }
  if (!*started) return EndStream();
  return absl::OkStatus();
}

// The first exchange of a stream that may use shared memory: the attach
// request (sequence 0, which typed requests never use) and its answer.
absl::Status SessionStream::NegotiateSharedMemory() {
  v1::SessionRequest attach;
  attach.mutable_attach_shared_memory();
  // The attach answer is this stream's first: requests lost with an earlier
  // stream are owed their errors after it, not given it.
  const uint64_t lost_before = std::exchange(lost_, 0);
  absl::Status status = SendBytes(attach.SerializeAsString());
  absl::string_view bytes;
  if (status.ok()) status = *ReceiveBytes(&bytes, absl::InfiniteDuration());
  lost_ += lost_before;
  if (!status.ok()) return status;
  v1::SessionResponse answer;
  if (!answer.ParseFromArray(bytes.data(), static_cast<int>(bytes.size()))) {
    Close();
    return absl::InternalError(
        absl::StrCat(what_,
                     " answered attach_shared_memory with bytes that "
                     "are not a SessionResponse"));
  }
  if (answer.has_error()) {
    if (mode_ == SessionTransport::kAuto) return absl::OkStatus();
    Close();
    return absl::FailedPreconditionError(
        absl::StrCat("transport \"shared_memory\": ", what_,
                     " refused shared memory (", answer.error().message(),
                     "); transport \"auto\" goes on over the stream"));
  }
  // The attach request's write is done before the region is used (its
  // completion is not to be taken later for the session's end).
  if (write_outstanding_) {
    if (!Await(kWrite, DeadlineAfter(step_timeout_)).has_value()) {
      return Abandon("the hand-over of a request", step_timeout_);
    }
    write_outstanding_ = false;
  }
  status = MapRegion(answer.attach_shared_memory());
  if (status.ok()) return absl::OkStatus();
  // The server serves a region this process cannot map (it runs on another
  // host or in another container): this stream is spent, and the next ones
  // ask for none.
  Close();
  if (mode_ == SessionTransport::kSharedMemory) {
    return absl::FailedPreconditionError(
        absl::StrCat("transport \"shared_memory\": ", status.message()));
  }
  mode_ = SessionTransport::kNative;
  return OpenStream();
}

absl::Status SessionStream::MapRegion(
    const v1::AttachSharedMemoryResponse& answer) {
  const std::string& path = answer.path();
  const uint64_t size = answer.size();
  // A regular file of the announced size, looked at before it is opened (a
  // path that names something else here, e.g. a device, is never opened) and
  // again once open (mapping past a file's end would fault).
  const auto is_region = [size](const struct stat& info) {
    return S_ISREG(info.st_mode) &&
           static_cast<uint64_t>(info.st_size) == size &&
           size >= shared_memory::kHeaderBytes;
  };
  const absl::Status not_here = absl::NotFoundError(
      absl::StrCat(path, " is not this session's region here: ", what_,
                   " is on another host or in another container"));
  struct stat info;
  if (stat(path.c_str(), &info) != 0 || !is_region(info)) return not_here;
  const int fd = open(path.c_str(), O_RDWR | O_CLOEXEC | O_NOCTTY);
  if (fd < 0) return not_here;
  if (fstat(fd, &info) != 0 || !is_region(info)) {
    close(fd);
    return not_here;
  }
  void* region = mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  close(fd);
  if (region == MAP_FAILED) {
    return absl::ResourceExhaustedError(
        absl::StrCat(path, " cannot be mapped: ", std::strerror(errno)));
  }
  region_ = region;
  region_bytes_ = size;
  const auto& header = *static_cast<const shared_memory::Header*>(region_);
  if (header.magic != shared_memory::kMagic ||
      header.version != shared_memory::kVersion ||
      header.nonce != answer.nonce() ||
      size != shared_memory::RegionBytes(header.capacity)) {
    DropRegion();
    return not_here;
  }
  capacity_ = header.capacity;
  region_sequence_ = header.request_seq.load(std::memory_order_acquire);
  // The stream keeps a read pending, which completes only when the session
  // ends.
  stream_->Read(&response_buffer_, TagOf(kRead));
  read_outstanding_ = true;
  attached_ = true;
  return absl::OkStatus();
}

void SessionStream::DropRegion() {
  attached_ = false;
  region_busy_ = false;
  region_queue_.clear();
  if (region_ != nullptr) munmap(region_, region_bytes_);
  region_ = nullptr;
}

absl::Status SessionStream::SendBytes(absl::string_view request) {
  return SendWithTimeout(request, step_timeout_);
}

absl::Status SessionStream::SendWithTimeout(absl::string_view request,
                                            absl::Duration timeout) {
  if (stream_ == nullptr) {
    absl::Status status = Open();
    if (!status.ok()) return status;
  }
  if (attached_) {
    if (request.size() > capacity_) {
      return Fail(absl::ResourceExhaustedError(absl::StrCat(
          "request of ", request.size(),
          " bytes; allowed: up to the shared-memory region's ", capacity_)));
    }
    ++sent_;
    timeouts_.emplace_back(absl::Now(), timeout);
    FeedRegion();  // The region is free once the previous answer was taken.
    if (!region_busy_ && region_queue_.empty()) {
      WriteToRegion(request);
    } else {
      region_queue_.emplace_back(request);
    }
    return absl::OkStatus();
  }
  absl::Status status = WriteToStream(request);
  if (status.ok()) {
    ++sent_;
    timeouts_.emplace_back(absl::Now(), timeout);
  }
  return Fail(status);
}

absl::Status SessionStream::WriteToStream(absl::string_view request) {
  // gRPC takes one write at a time: the previous one is handed to the
  // transport first (it does not wait for the server, only for HTTP/2 flow
  // control).
  if (write_outstanding_) {
    const std::optional<bool> written =
        Await(kWrite, DeadlineAfter(step_timeout_));
    if (!written.has_value()) {
      // The server stopped reading (its flow-control window is spent).
      return Abandon("the hand-over of a request", step_timeout_);
    }
    write_outstanding_ = false;
    if (!written.value_or(false)) {
      // Reported here, and to the Receives of the requests in flight.
      lost_status_ = EndStream();
      return lost_status_;
    }
  }
  grpc::Slice slice(request.data(), request.size());
  request_buffer_ = grpc::ByteBuffer(&slice, 1);
  stream_->Write(request_buffer_, TagOf(kWrite));
  write_outstanding_ = true;
  return absl::OkStatus();
}

// Moves the oldest queued request into the region when the region is free.
// Called at the start of each call, never after handing out an answer: the
// answer lies in the region until the caller's next call.
void SessionStream::FeedRegion() {
  if (!attached_ || region_busy_ || region_queue_.empty()) return;
  WriteToRegion(region_queue_.front());
  region_queue_.pop_front();
}

void SessionStream::WriteToRegion(absl::string_view request) {
  auto& header = *static_cast<shared_memory::Header*>(region_);
  std::memcpy(shared_memory::RequestArea(region_), request.data(),
              request.size());
  header.request_size.store(request.size(), std::memory_order_release);
  header.request_seq.store(++region_sequence_, std::memory_order_release);
  shared_memory::Wake(header.request_seq);
  region_busy_ = true;
}

std::optional<absl::Status> SessionStream::ReceiveBytes(
    absl::string_view* response, absl::Duration timeout) {
  if (lost_ > 0) {
    --lost_;
    return Fail(lost_status_);
  }
  if (sent_ == received_) {
    return Fail(
        absl::FailedPreconditionError("receive without a request in flight"));
  }
  // The caller's timeout, or the server's deadline if that comes first.
  if (first_wait_ == absl::InfiniteFuture()) first_wait_ = absl::Now();
  const absl::Time due = AnswerDue();
  const absl::Duration to_due =
      std::max(due - absl::Now(), absl::ZeroDuration());
  const bool due_first = to_due <= timeout;
  std::optional<absl::Status> answer =
      ReceiveWithin(response, DeadlineAfter(std::min(timeout, to_due)));
  if (answer.has_value() || !due_first) return answer;
  absl::Status missed =
      Abandon("the answer to a request", timeouts_.front().second);
  --lost_;  // This request's, reported here.
  return missed;
}

absl::Time SessionStream::AnswerDue() const {
  if (timeouts_.empty()) return absl::InfiniteFuture();
  const auto& [sent, timeout] = timeouts_.front();
  return std::max({sent, last_answer_, first_wait_}) + timeout;
}

std::optional<absl::Status> SessionStream::ReceiveWithin(
    absl::string_view* response, gpr_timespec deadline) {
  if (attached_) return ReceiveFromRegion(response, deadline);
  if (!read_outstanding_) {
    stream_->Read(&response_buffer_, TagOf(kRead));
    read_outstanding_ = true;
  }
  const std::optional<bool> read = Await(kRead, deadline);
  if (!read.has_value()) return std::nullopt;
  read_outstanding_ = false;
  if (!*read) {
    lost_status_ = EndStream();
    --lost_;
    return Fail(lost_status_);
  }
  Answered();
  if (!response_buffer_.DumpToSingleSlice(&response_slice_).ok()) {
    return Fail(absl::InternalError("cannot read the Session answer's bytes"));
  }
  *response =
      absl::string_view(reinterpret_cast<const char*>(response_slice_.begin()),
                        response_slice_.size());
  return absl::OkStatus();
}

// Waits for the server's answer in the region; between futex waits it looks
// whether the stream ended (the server went or ended the session).
std::optional<absl::Status> SessionStream::ReceiveFromRegion(
    absl::string_view* response, gpr_timespec deadline) {
  FeedRegion();
  auto& header = *static_cast<shared_memory::Header*>(region_);
  for (uint32_t seen; (seen = header.response_seq.load(
                           std::memory_order_acquire)) != region_sequence_;) {
    if (shared_memory::WaitWhileEqual(header.response_seq, seen,
                                      std::chrono::nanoseconds(0),
                                      kRegionWaitSlice)) {
      continue;
    }
    if (gpr_time_cmp(gpr_now(GPR_CLOCK_MONOTONIC), deadline) >= 0) {
      return std::nullopt;
    }
    void* tag = nullptr;
    bool ok = false;
    if (queue_->AsyncNext(&tag, &ok, gpr_time_0(GPR_CLOCK_MONOTONIC)) ==
        grpc::CompletionQueue::GOT_EVENT) {
      const intptr_t completed = OperationOf(tag);
      done_[completed] = true;
      ok_[completed] = ok;
      // The pending read completes only when the session ends; anything
      // else (the attach request's write) is recorded and waited past.
      if (completed != kRead) continue;
      read_outstanding_ = false;
      lost_status_ = EndStream();
      --lost_;
      return Fail(lost_status_);
    }
  }
  region_busy_ = false;
  Answered();
  const uint64_t size = header.response_size.load(std::memory_order_acquire);
  if (size > capacity_) {
    return Fail(absl::InternalError(
        absl::StrCat(what_, "'s answer overflows the shared-memory region")));
  }
  *response =
      absl::string_view(shared_memory::ResponseArea(region_, capacity_), size);
  return absl::OkStatus();
}

void SessionStream::Answered() {
  ++received_;
  timeouts_.pop_front();
  last_answer_ = absl::Now();
  first_wait_ = absl::InfiniteFuture();
}

absl::Duration AnswerTimeout(absl::Duration step_timeout,
                             const v1::SessionRequest& request) {
  if (step_timeout == absl::InfiniteDuration() || !request.has_step_batch()) {
    return step_timeout;
  }
  // Discrete actions are 4 bytes each, continuous ones 8: counted as two,
  // which errs on the long side.
  size_t action_bytes = request.step_batch().packed().actions().data().size();
  for (const v1::StepEnvRequest& step : request.step_batch().steps()) {
    action_bytes += step.actions().data().size();
  }
  return step_timeout +
         kAnswerTimePerAction * static_cast<int64_t>(action_bytes / 4);
}

absl::Duration StepTimeout(const ClientOptions& options) {
  if (options.step_timeout.count() <= 0) return absl::InfiniteDuration();
  return absl::FromChrono(options.step_timeout);
}

absl::StatusOr<uint64_t> SessionStream::Send(v1::SessionRequest& request) {
  request.set_sequence(++last_sequence_);
  const absl::Duration timeout = AnswerTimeout(step_timeout_, request);
  if (!batch_handles_enabled_) {
    absl::Status status = SendWithTimeout(request.SerializeAsString(), timeout);
    if (!status.ok()) return status;
    return last_sequence_;
  }
  // The handles are those of the session that gets the request.
  if (absl::Status status = Open(); !status.ok()) return status;
  absl::Status status =
      SendWithTimeout(batch_handles_.Serialize(request), timeout);
  if (!status.ok()) {
    batch_handles_.Answered(last_sequence_, /*ok=*/false);
    return status;
  }
  return last_sequence_;
}

absl::Status SessionStream::Receive(uint64_t sequence,
                                    v1::SessionResponse* response) {
  std::optional<absl::Status> status;
  while (!(status = Receive(sequence, response, absl::InfiniteDuration()))) {
  }
  return *status;
}

std::optional<absl::Status> SessionStream::Receive(
    uint64_t sequence, v1::SessionResponse* response, absl::Duration timeout) {
  const absl::Time deadline = absl::Now() + timeout;
  if (auto early = early_answers_.find(sequence);
      early != early_answers_.end()) {
    *response = std::move(early->second);
    early_answers_.erase(early);
  } else {
    while (true) {
      absl::string_view bytes;
      const std::optional<absl::Status> status = ReceiveBytes(
          &bytes, std::max(deadline - absl::Now(), absl::ZeroDuration()));
      if (!status.has_value()) return std::nullopt;
      if (!status->ok()) return *status;
      v1::SessionResponse answer;
      if (!answer.ParseFromArray(bytes.data(),
                                 static_cast<int>(bytes.size()))) {
        return absl::InternalError(absl::StrCat(
            what_, " answered with bytes that are not a SessionResponse"));
      }
      batch_handles_.Answered(answer.sequence(), !answer.has_error());
      if (answer.sequence() == sequence) {
        *response = std::move(answer);
        break;
      }
      if (answer.sequence() == 0 || answer.sequence() > last_sequence_ ||
          early_answers_.contains(answer.sequence())) {
        return absl::InternalError(absl::StrCat(what_, " answered sequence ",
                                                answer.sequence(), " while ",
                                                sequence, " was awaited"));
      }
      early_answers_[answer.sequence()] = std::move(answer);
    }
  }
  if (response->has_error()) return FromItemError(response->error());
  return absl::OkStatus();
}

void SessionStream::Close() {
  if (stream_ == nullptr) return;
  if (!HalfCloseAndAwaitEnd(std::min(step_timeout_, kCloseGrace))) {
    context_->TryCancel();
  }
  (void)EndStream();
  lost_ = 0;
}

bool SessionStream::HalfCloseAndAwaitEnd(absl::Duration grace) {
  if (sent_ != received_) return false;
  const gpr_timespec deadline = DeadlineAfter(grace);
  if (write_outstanding_) {
    if (!Await(kWrite, deadline).has_value()) return false;
    write_outstanding_ = false;
  }
  stream_->WritesDone(TagOf(kWritesDone));
  if (!Await(kWritesDone, deadline).has_value()) return false;
  // The server's end shows as the read failing: the pending one (a stream
  // attached to shared memory keeps one) or a new one.
  if (!read_outstanding_) {
    stream_->Read(&response_buffer_, TagOf(kRead));
    read_outstanding_ = true;
  }
  const std::optional<bool> read = Await(kRead, deadline);
  if (!read.has_value()) return false;
  read_outstanding_ = false;
  return !*read;  // An answer nobody asked for: cancel.
}

std::optional<bool> SessionStream::Await(Operation operation,
                                         gpr_timespec deadline) {
  while (!done_[operation]) {
    void* tag = nullptr;
    bool ok = false;
    switch (queue_->AsyncNext(&tag, &ok, deadline)) {
      case grpc::CompletionQueue::SHUTDOWN:
        return false;
      case grpc::CompletionQueue::TIMEOUT:
        return std::nullopt;
      case grpc::CompletionQueue::GOT_EVENT:
        break;
    }
    const intptr_t completed = OperationOf(tag);
    done_[completed] = true;
    ok_[completed] = ok;
  }
  done_[operation] = false;
  return ok_[operation];
}

// The stream's final status, once its pending operations are done; the
// stream is forgotten, and what was in flight counted as lost.
absl::Status SessionStream::EndStream() {
  if (write_outstanding_) {
    (void)Await(kWrite, gpr_inf_future(GPR_CLOCK_MONOTONIC));
  }
  grpc::Status final_status;
  stream_->Finish(&final_status, TagOf(kFinish));
  (void)Await(kFinish, gpr_inf_future(GPR_CLOCK_MONOTONIC));
  // Drains the queue, as gRPC requires before it is destroyed.
  queue_->Shutdown();
  void* tag = nullptr;
  bool ok = false;
  while (queue_->Next(&tag, &ok)) {
  }
  stream_.reset();
  context_.reset();
  queue_.reset();
  done_.fill(false);
  write_outstanding_ = false;
  read_outstanding_ = false;
  DropRegion();
  timeouts_.clear();
  first_wait_ = absl::InfiniteFuture();
  // Added: requests lost with an earlier stream stay lost (their Receives
  // still owe them an error) when a reopened stream fails too.
  lost_ += sent_ - received_;
  sent_ = received_ = 0;
  if (final_status.ok()) {
    return absl::UnavailableError(
        absl::StrCat(what_, " ended the Session stream"));
  }
  return FromGrpc(final_status);
}

absl::Status SessionStream::Abandon(absl::string_view waiting_for,
                                    absl::Duration timeout) {
  // Cancelled, the stream's pending operations complete at once.
  context_->TryCancel();
  (void)EndStream();
  lost_status_ = absl::DeadlineExceededError(absl::StrCat(
      what_, " did not answer within ", absl::FormatDuration(timeout),
      " (step timeout ", absl::FormatDuration(step_timeout_), ") waiting for ",
      waiting_for,
      "; its Session stream is cancelled and the requests in flight on it "
      "are lost (a late answer is never taken)"));
  return Fail(lost_status_);
}

absl::Status SessionStream::Fail(absl::Status status) {
  if (!status.ok()) last_message_ = std::string(status.message());
  return status;
}

}  // namespace internal
}  // namespace mll::client

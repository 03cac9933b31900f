#include "native_stream.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <array>
#include <cerrno>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <memory>
#include <optional>
#include <string>
#include <utility>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "channel.h"
#include "grpc/grpc.h"
#include "grpcpp/channel.h"
#include "grpcpp/client_context.h"
#include "grpcpp/completion_queue.h"
#include "grpcpp/generic/generic_stub.h"
#include "grpcpp/support/byte_buffer.h"
#include "grpcpp/support/slice.h"
#include "grpcpp/support/status.h"
#include "mll/client.h"
#include "mll/shared_memory_pipe.h"

namespace {

namespace shared_memory = mll::shared_memory;

constexpr char kSessionMethod[] = "/mll.v1.MultiLunarLander/Session";
// The largest message either way, as the Python client's own channels.
constexpr int kMaxMessageBytes = 64 << 20;

// The stream's operations, as completion queue tags.
enum Operation : intptr_t { kStart, kWrite, kRead, kFinish, kOperations };

void* TagOf(Operation operation) {
  return reinterpret_cast<void*>(static_cast<intptr_t>(operation) + 1);
}

Operation OperationOf(void* tag) {
  return static_cast<Operation>(reinterpret_cast<intptr_t>(tag) - 1);
}

}  // namespace

struct mll_native_stream {
 public:
  mll_native_stream(absl::StatusOr<std::shared_ptr<grpc::Channel>> channel,
                    std::string token)
      : channel_status_(channel.status()), token_(std::move(token)) {
    if (channel.ok()) {
      stub_ = std::make_unique<grpc::GenericStub>(*std::move(channel));
    }
  }

  ~mll_native_stream() { Cancel(); }

  int Write(const char* data, size_t size) {
    if (!channel_status_.ok()) {
      return Fail(static_cast<int>(channel_status_.code()),
                  std::string(channel_status_.message()));
    }
    if (stream_ == nullptr) {
      queue_ = std::make_unique<grpc::CompletionQueue>();
      context_ = std::make_unique<grpc::ClientContext>();
      mll::client::internal::AddToken(context_.get(), token_);
      stream_ =
          stub_->PrepareCall(context_.get(), kSessionMethod, queue_.get());
      stream_->StartCall(TagOf(kStart));
      if (!*Await(kStart)) return Finish();
    }
    if (attached_) {
      if (size > capacity_) {
        return Fail(static_cast<int>(grpc::StatusCode::RESOURCE_EXHAUSTED),
                    "request of " + std::to_string(size) +
                        " bytes; allowed: up to the shared-memory region's " +
                        std::to_string(capacity_));
      }
      shared_memory::Header& header = Header();
      std::memcpy(shared_memory::RequestArea(region_), data, size);
      header.request_size.store(size, std::memory_order_release);
      header.request_seq.store(++sent_, std::memory_order_release);
      shared_memory::Wake(header.request_seq);
      write_pending_ = true;
      return 0;
    }
    grpc::Slice slice(data, size);
    request_ = grpc::ByteBuffer(&slice, 1);
    stream_->Write(request_, TagOf(kWrite));
    write_pending_ = true;
    return 0;
  }

  int Read(const char** data, size_t* size, int timeout_ms) {
    if (stream_ == nullptr) {
      return Fail(static_cast<int>(grpc::StatusCode::FAILED_PRECONDITION),
                  "read without a write in flight");
    }
    const gpr_timespec deadline =
        timeout_ms < 0
            ? gpr_inf_future(GPR_CLOCK_MONOTONIC)
            : gpr_time_add(gpr_now(GPR_CLOCK_MONOTONIC),
                           gpr_time_from_millis(timeout_ms, GPR_TIMESPAN));
    if (attached_) return ReadSharedMemory(data, size, deadline);
    if (!read_started_) {
      stream_->Read(&response_, TagOf(kRead));
      read_started_ = true;
    }
    // The write completes before any answer can come, so it is awaited
    // first; either wait may run out of time and be taken up by the next
    // call.
    if (!written_.has_value()) {
      written_ = Await(kWrite, deadline);
      if (!written_.has_value()) return MLL_NATIVE_STREAM_PENDING;
    }
    const std::optional<bool> read = Await(kRead, deadline);
    if (!read.has_value()) return MLL_NATIVE_STREAM_PENDING;
    const bool written = *written_;
    written_.reset();
    read_started_ = false;
    write_pending_ = false;
    if (!*read || !written) return Finish();
    if (!response_.DumpToSingleSlice(&response_slice_).ok()) {
      return Fail(static_cast<int>(grpc::StatusCode::INTERNAL),
                  "cannot read the Session response's bytes");
    }
    *data = reinterpret_cast<const char*>(response_slice_.begin());
    *size = response_slice_.size();
    return 0;
  }

  const char* message() const { return message_.c_str(); }

  bool is_open() const { return stream_ != nullptr; }

  // Maps the region the server created for this stream's session (its
  // attach_shared_memory answer) and sends every further message through
  // it. The stream keeps a read pending, which completes only when the
  // session ends.
  int AttachSharedMemory(const char* path, uint64_t size, uint64_t nonce) {
    if (stream_ == nullptr || attached_) {
      return Fail(static_cast<int>(grpc::StatusCode::FAILED_PRECONDITION),
                  "attach without an open, unattached stream");
    }
    // A regular file of the announced size, looked at before it is opened
    // (a path that names something else here, e.g. a device, is never
    // opened) and again once open (mapping past a file's end would fault).
    const auto is_region = [size](const struct stat& info) {
      return S_ISREG(info.st_mode) &&
             static_cast<uint64_t>(info.st_size) == size &&
             size >= shared_memory::kHeaderBytes;
    };
    const auto not_here = [&] {
      return Fail(static_cast<int>(grpc::StatusCode::NOT_FOUND),
                  std::string(path) +
                      " is not this session's region here: the server is on "
                      "another host or in another container");
    };
    struct stat info;
    if (stat(path, &info) != 0 || !is_region(info)) return not_here();
    const int fd = open(path, O_RDWR | O_CLOEXEC | O_NOCTTY);
    if (fd < 0) return not_here();
    if (fstat(fd, &info) != 0 || !is_region(info)) {
      close(fd);
      return not_here();
    }
    void* region =
        mmap(nullptr, size, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
    close(fd);
    if (region == MAP_FAILED) {
      return Fail(
          static_cast<int>(grpc::StatusCode::RESOURCE_EXHAUSTED),
          std::string(path) + " cannot be mapped: " + std::strerror(errno));
    }
    region_ = region;
    region_bytes_ = size;
    const shared_memory::Header& header = Header();
    if (header.magic != shared_memory::kMagic ||
        header.version != shared_memory::kVersion || header.nonce != nonce ||
        size != shared_memory::RegionBytes(header.capacity)) {
      DropSharedMemory();
      return not_here();
    }
    capacity_ = header.capacity;
    sent_ = header.request_seq.load(std::memory_order_acquire);
    stream_->Read(&response_, TagOf(kRead));
    attached_ = true;
    return 0;
  }

  // Unmaps the region (it was not the session's, or the stream went).
  void DropSharedMemory() {
    attached_ = false;
    if (region_ != nullptr) munmap(region_, region_bytes_);
    region_ = nullptr;
  }

  // Cancels the open stream and forgets it.
  void Cancel() {
    if (stream_ == nullptr) return;
    context_->TryCancel();
    (void)End();
  }

 private:
  shared_memory::Header& Header() const {
    return *static_cast<shared_memory::Header*>(region_);
  }

  // Waits for the server's answer in the region; between futex waits it
  // looks whether the stream ended (the server went or ended the session).
  int ReadSharedMemory(const char** data, size_t* size, gpr_timespec deadline) {
    if (!write_pending_) {
      return Fail(static_cast<int>(grpc::StatusCode::FAILED_PRECONDITION),
                  "read without a write in flight");
    }
    shared_memory::Header& header = Header();
    for (uint32_t seen; (seen = header.response_seq.load(
                             std::memory_order_acquire)) != sent_;) {
      if (shared_memory::WaitWhileEqual(header.response_seq, seen,
                                        std::chrono::nanoseconds(0),
                                        std::chrono::milliseconds(20))) {
        continue;
      }
      if (gpr_time_cmp(gpr_now(GPR_CLOCK_MONOTONIC), deadline) >= 0) {
        return MLL_NATIVE_STREAM_PENDING;
      }
      void* tag = nullptr;
      bool ok = false;
      if (queue_->AsyncNext(&tag, &ok, gpr_time_0(GPR_CLOCK_MONOTONIC)) ==
          grpc::CompletionQueue::GOT_EVENT) {
        // Only the pending read can complete: the session ended.
        write_pending_ = false;
        return Finish();
      }
    }
    write_pending_ = false;
    const uint64_t answer =
        header.response_size.load(std::memory_order_acquire);
    if (answer > capacity_) {
      return Fail(static_cast<int>(grpc::StatusCode::INTERNAL),
                  "the server's answer overflows the shared-memory region");
    }
    *data = shared_memory::ResponseArea(region_, capacity_);
    *size = answer;
    return 0;
  }

  // Waits for `operation` to complete (recording any other that completes
  // first) and returns its outcome, or nothing if `deadline` came first.
  std::optional<bool> Await(
      Operation operation,
      gpr_timespec deadline = gpr_inf_future(GPR_CLOCK_MONOTONIC)) {
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
      const Operation completed = OperationOf(tag);
      done_[completed] = true;
      ok_[completed] = ok;
    }
    done_[operation] = false;
    return ok_[operation];
  }

  // The stream's final status, once its pending write is done; the stream
  // is forgotten.
  grpc::Status End() {
    // Attached, no write is pending on the stream (the read pending since
    // the attach completes when the call ends).
    if (write_pending_ && !attached_ && !written_.has_value()) Await(kWrite);
    write_pending_ = false;
    grpc::Status status;
    stream_->Finish(&status, TagOf(kFinish));
    Await(kFinish);
    Forget();
    return status;
  }

  // The broken stream's status as a return code, which also forgets it.
  int Finish() {
    const grpc::Status status = End();
    if (status.ok()) {
      return Fail(static_cast<int>(grpc::StatusCode::UNAVAILABLE),
                  "the server ended the Session stream");
    }
    return Fail(static_cast<int>(status.error_code()), status.error_message());
  }

  int Fail(int code, std::string message) {
    message_ = std::move(message);
    return code;
  }

  // Drains the queue, as gRPC requires before it is destroyed, and drops the
  // call: the next write opens a new stream.
  void Forget() {
    queue_->Shutdown();
    void* tag = nullptr;
    bool ok = false;
    while (queue_->Next(&tag, &ok)) {
    }
    stream_.reset();
    context_.reset();
    queue_.reset();
    done_.fill(false);
    read_started_ = false;
    written_.reset();
    DropSharedMemory();
  }

  absl::Status channel_status_;
  std::string token_;
  std::unique_ptr<grpc::GenericStub> stub_;
  std::unique_ptr<grpc::CompletionQueue> queue_;
  std::unique_ptr<grpc::ClientContext> context_;
  std::unique_ptr<grpc::GenericClientAsyncReaderWriter> stream_;
  bool write_pending_ = false;
  // A read that ran out of time (MLL_NATIVE_STREAM_PENDING) is taken up by
  // the next: its stream read is started once, and the write's outcome kept.
  bool read_started_ = false;
  std::optional<bool> written_;
  std::array<bool, kOperations> done_{};
  std::array<bool, kOperations> ok_{};
  // The shared-memory region, once created; attached_ once the server uses
  // it. sent_ counts the requests written into it.
  void* region_ = nullptr;
  uint64_t region_bytes_ = 0;
  uint64_t capacity_ = 0;
  bool attached_ = false;
  uint32_t sent_ = 0;
  grpc::ByteBuffer request_;
  grpc::ByteBuffer response_;
  grpc::Slice response_slice_;
  std::string message_;
};

extern "C" {

mll_native_stream* mll_native_stream_open(const char* address,
                                          const char* root_cert_pem,
                                          size_t root_cert_size,
                                          const char* server_name,
                                          const char* token) {
  // gRPC stays initialised for the life of the process: without a reference
  // of its own, closing the last stream would shut gRPC down (joining its
  // threads, a few hundred milliseconds) and the next open would start it
  // again.
  static const bool initialised = (grpc_init(), true);
  (void)initialised;
  mll::client::ClientOptions options;
  options.use_tls = root_cert_pem != nullptr;
  if (options.use_tls) {
    options.tls_root_certificates.assign(root_cert_pem, root_cert_size);
  }
  if (server_name != nullptr) options.tls_target_name_override = server_name;
  if (token != nullptr) options.token = token;
  options.max_receive_message_bytes = kMaxMessageBytes;
  return new mll_native_stream(
      mll::client::internal::OpenChannel(address, options), options.token);
}

int mll_native_stream_write(mll_native_stream* stream, const char* data,
                            size_t size) {
  return stream->Write(data, size);
}

int mll_native_stream_read(mll_native_stream* stream, const char** data,
                           size_t* size, int timeout_ms) {
  return stream->Read(data, size, timeout_ms);
}

const char* mll_native_stream_message(const mll_native_stream* stream) {
  return stream->message();
}

void mll_native_stream_close(mll_native_stream* stream) { delete stream; }

int mll_native_stream_is_open(const mll_native_stream* stream) {
  return stream->is_open() ? 1 : 0;
}

int mll_native_stream_attach_shared_memory(mll_native_stream* stream,
                                           const char* path, uint64_t size,
                                           uint64_t nonce) {
  return stream->AttachSharedMemory(path, size, nonce);
}

}  // extern "C"

// One Session stream to one server: the client side of the wire protocol's
// Session, the only one in the project. The C++ client's session clients and
// VectorEnv use it typed (SessionRequest / SessionResponse); the Python
// client reaches it through the C interface of client_cpp/native (serialized
// messages), so both languages speak the same protocol through this code.
//
// Requests are pipelined: Send returns once the request is handed to gRPC (it
// does not wait for the server), and several may be in flight; Receive
// returns the answers in request order (the server answers a stream's
// requests in order). All waiting happens in the calling thread, on a
// completion queue of the stream's own: no thread is made. One thread at a
// time uses a stream.
//
// Shared memory: for a server on the same host, the stream can ask for a
// shared-memory region (attach_shared_memory in the proto) and pass every
// further message through it: no socket, one futex wake-up each way. The
// region holds one request at a time, so further requests wait in the
// stream's queue and go in as answers come back.
//
// A broken stream (the server went, or cancelled the session) reports the
// stream's gRPC status to every waiting Receive; the next Send opens a new
// stream (and asks for shared memory again, as the first did).
//
// Deadlines (ClientOptions::step_timeout): the server must start the stream
// and take each write within step_timeout, and answer each request within
// its allowance (AnswerTimeout) from when it was sent or the previous answer
// came, whichever is later (so pipelined requests wait their turn), however
// the caller splits its waiting into timed Receives. A server that misses a
// deadline (stopped, frozen, or cut off with its connection open) fails that
// wait and every request in flight with DEADLINE_EXCEEDED naming the server
// and the timeout, and the stream is cancelled: an answer that comes late
// has no stream to arrive on, so it is never taken for a later request
// (which goes out on a new stream, a new session, whose bound envs are new
// ones), and the server ends the cancelled session, deleting its bound envs,
// when it runs again.
//
// Batch handles (PackedSteps.handle, for a server with the capability
// "packed_batch_handles"; off until EnableBatchHandles): the typed Send gives
// every packed StepBatch that names its envs a handle of the session. The
// first request of a list of envs declares it (names and handle); once its
// answer came back OK, the same list goes out as the handle alone, with the
// actions. A new stream is a new session, with no handles: its first request
// of each list declares it again.
#ifndef MLL_CLIENT_SRC_SESSION_STREAM_H_
#define MLL_CLIENT_SRC_SESSION_STREAM_H_

#include <array>
#include <cstdint>
#include <deque>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/time/time.h"
#include "grpc/support/time.h"
#include "grpcpp/channel.h"
#include "grpcpp/client_context.h"
#include "grpcpp/completion_queue.h"
#include "grpcpp/generic/generic_stub.h"
#include "grpcpp/support/byte_buffer.h"
#include "grpcpp/support/slice.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::client {
namespace internal {

// The batch handles of one Session (see above): which lists of envs the
// client declared under which handle, and which declarations the server
// has answered. The figures are the wire contract's (PackedSteps.handle).
class BatchHandles {
 public:
  static constexpr uint32_t kMaxHandle = 64;
  static constexpr size_t kMaxDeclaredEnvs = 65536;

  // Serializes `request` (numbered) for this session: a packed StepBatch
  // with names and no handle goes out as its declared handle alone when the
  // declaration was answered, else with its names and a handle, declaring
  // it (in place of the least recently used handle when all are taken; with
  // no handle when the declared envs would pass kMaxDeclaredEnvs). Any other
  // request goes out as it is. `request` is left as it was.
  std::string Serialize(v1::SessionRequest& request);
  // The answer to request `sequence` came (`ok`: without an error); a
  // declaration it made counts from now on.
  void Answered(uint64_t sequence, bool ok);
  // A new session: no handles.
  void Clear();

 private:
  struct Declared {
    std::vector<std::string> names;  // Empty: free.
    uint64_t version = 0;            // Of the names, for answers.
    bool answered = false;           // The server has it.
    uint64_t last_used = 0;
  };
  // The handle (1..kMaxHandle) of `names`: their declaration, or a free or
  // least recently used one for them; 0 when they cannot have one.
  template <typename Names>
  uint32_t HandleOf(const Names& names);

  std::vector<Declared> declared_;  // declared_[handle - 1].
  size_t declared_envs_ = 0;
  uint64_t clock_ = 0;
  uint64_t versions_ = 0;
  // Requests in flight that declare a handle: sequence -> (handle, version).
  absl::flat_hash_map<uint64_t, std::pair<uint32_t, uint64_t>> declaring_;
};

// How long a server may take to answer `request`: `step_timeout`, plus 1
// ms for each lander action of a StepBatch (a batch of many envs takes the
// server longer); infinite when `step_timeout` is. The deadline of every
// request of the C++ client (ClientOptions::step_timeout).
absl::Duration AnswerTimeout(absl::Duration step_timeout,
                             const v1::SessionRequest& request);

// ClientOptions::step_timeout as a Duration (zero: infinite, no deadline).
absl::Duration StepTimeout(const ClientOptions& options);

class SessionStream {
 public:
  // A stream to the server of `channel` (an error status there is reported
  // by the first Open or Send), sending `token` on its call. `what` names
  // the server in messages ("server 127.0.0.1:50051"). Nothing is opened
  // until the first Open or Send.
  // `step_timeout`: the deadline of each wait (above); infinite: none.
  SessionStream(absl::StatusOr<std::shared_ptr<grpc::Channel>> channel,
                std::string token, std::string what, SessionTransport mode,
                absl::Duration step_timeout = absl::InfiniteDuration());
  // Cancels the open stream.
  ~SessionStream();
  SessionStream(const SessionStream&) = delete;
  SessionStream& operator=(const SessionStream&) = delete;

  // Opens the stream now if none is open, with shared memory as the mode
  // asks: kAuto uses it where granted and mappable, else goes on over the
  // stream; kSharedMemory fails FAILED_PRECONDITION with the reason instead;
  // kNative never asks.
  absl::Status Open();
  bool is_open() const { return stream_ != nullptr; }
  // Whether the open stream passes its messages through shared memory.
  bool shared_memory_in_use() const { return attached_; }
  // "shared_memory" while it does, else "native".
  absl::string_view transport_name() const;
  // Requests sent and not yet answered (by Receive) on the open stream.
  int in_flight() const { return static_cast<int>(sent_ - received_); }

  // Starts sending one serialized SessionRequest (copied); opens the stream
  // when none is open. A stream that cannot be opened or broke before this
  // request went out fails here, and nothing is in flight for it.
  absl::Status SendBytes(absl::string_view request);
  // Waits for the answer to the oldest request in flight, at most `timeout`:
  // nothing when it ran out (call again: the answer is still due), OK with
  // `*response` set to the serialized SessionResponse (valid until the next
  // call on the stream), or the status of the broken stream (the server's
  // code and message; UNAVAILABLE when it ended the stream cleanly), after
  // which nothing is in flight. FAILED_PRECONDITION when nothing is.
  // DEADLINE_EXCEEDED when the server missed its deadline (Deadlines above)
  // before `timeout` ran out.
  std::optional<absl::Status> ReceiveBytes(absl::string_view* response,
                                           absl::Duration timeout);

  // Typed forms: Send numbers the request (its `sequence`) and returns the
  // number; Receive waits for the answer to request `sequence` (answers to
  // other requests that come first are kept for their own Receive), checks
  // its sequence, and turns a SessionResponse.error into its status. With
  // batch handles enabled, Send sends packed StepBatches by handle
  // (BatchHandles), opening the stream first.
  absl::StatusOr<uint64_t> Send(v1::SessionRequest& request);
  absl::Status Receive(uint64_t sequence, v1::SessionResponse* response);
  // Receive waiting at most `timeout` (until then, not in total, across
  // answers to other requests): nothing when it ran out, and the answer is
  // still due (call again: nothing is lost or repeated).
  std::optional<absl::Status> Receive(uint64_t sequence,
                                      v1::SessionResponse* response,
                                      absl::Duration timeout);
  // Whether the typed Send uses batch handles (the server must have
  // "packed_batch_handles").
  void EnableBatchHandles(bool enabled) { batch_handles_enabled_ = enabled; }
  bool batch_handles_enabled() const { return batch_handles_enabled_; }

  // Ends the open stream, if any; the next Send opens a new one. With
  // nothing in flight it half-closes the stream and waits for the server to
  // end it, which the server does after deleting the session's bound envs,
  // so they are gone when Close returns. With requests in flight, or a
  // server that has not ended the stream within min(step timeout,
  // kCloseGrace), it cancels the stream: what was in flight is lost, and the
  // server deletes the envs when it sees the cancellation.
  void Close();
  static constexpr absl::Duration kCloseGrace = absl::Seconds(2);

  absl::Duration step_timeout() const { return step_timeout_; }

  // The last status message of a failed call, for the C interface.
  const std::string& last_message() const { return last_message_; }

 private:
  // The stream's operations, as completion queue tags.
  enum Operation : intptr_t {
    kStart,
    kWrite,
    kRead,
    kWritesDone,
    kFinish,
    kOperations
  };

  absl::Status OpenStream();
  absl::Status NegotiateSharedMemory();
  absl::Status MapRegion(const v1::AttachSharedMemoryResponse& region);
  void DropRegion();
  absl::Status WriteToStream(absl::string_view request);
  void FeedRegion();
  // Puts `request` in the free region and wakes the server.
  void WriteToRegion(absl::string_view request);
  std::optional<absl::Status> ReceiveFromRegion(absl::string_view* response,
                                                gpr_timespec deadline);
  std::optional<bool> Await(Operation operation, gpr_timespec deadline);
  absl::Status EndStream();
  // Close's graceful path: true once the server has ended the stream after
  // its half-close, within `grace`; false if requests are in flight or the
  // server did not.
  bool HalfCloseAndAwaitEnd(absl::Duration grace);
  // The server missed the deadline `timeout` of `waiting_for` ("its answer",
  // ...): the stream is cancelled and ended, and what was in flight lost
  // with DEADLINE_EXCEEDED naming the server and the timeout (returned).
  absl::Status Abandon(absl::string_view waiting_for, absl::Duration timeout);
  // When the oldest request in flight is due (see Deadlines above).
  absl::Time AnswerDue() const;
  // ReceiveBytes without the step deadline, waiting until `deadline`.
  std::optional<absl::Status> ReceiveWithin(absl::string_view* response,
                                            gpr_timespec deadline);
  // The oldest request in flight is answered.
  void Answered();
  absl::Status SendWithTimeout(absl::string_view request,
                               absl::Duration timeout);
  absl::Status Fail(absl::Status status);

  absl::Status channel_status_;
  std::unique_ptr<grpc::GenericStub> stub_;
  std::string token_;
  std::string what_;
  SessionTransport mode_;
  absl::Duration step_timeout_;

  std::unique_ptr<grpc::CompletionQueue> queue_;
  std::unique_ptr<grpc::ClientContext> context_;
  std::unique_ptr<grpc::GenericClientAsyncReaderWriter> stream_;
  std::array<bool, kOperations> done_{};
  std::array<bool, kOperations> ok_{};
  bool write_outstanding_ = false;
  bool read_outstanding_ = false;
  uint64_t sent_ = 0;
  uint64_t received_ = 0;
  // When each request in flight on the open stream was sent and its
  // AnswerTimeout, oldest first; when the latest answer came.
  std::deque<std::pair<absl::Time, absl::Duration>> timeouts_;
  absl::Time last_answer_ = absl::InfinitePast();
  // When the caller first waited for the oldest request's answer (infinite
  // future: not yet). The deadline counts from then at the earliest: an
  // answer that came while the caller computed (a StepAsync, then a learning
  // step) is read off the connection only when the caller waits.
  absl::Time first_wait_ = absl::InfiniteFuture();
  // Requests lost with a broken stream, whose Receives report lost_status_.
  uint64_t lost_ = 0;
  absl::Status lost_status_;
  grpc::ByteBuffer request_buffer_;
  grpc::ByteBuffer response_buffer_;
  grpc::Slice response_slice_;

  // The shared-memory region while attached: requests not yet written into
  // it wait in region_queue_; region_busy_ while one is in it unanswered.
  void* region_ = nullptr;
  uint64_t region_bytes_ = 0;
  uint64_t capacity_ = 0;
  bool attached_ = false;
  bool region_busy_ = false;
  uint32_t region_sequence_ = 0;
  std::deque<std::string> region_queue_;

  // Typed use: the last number given, and answers that came before their
  // Receive; the open stream's batch handles.
  uint64_t last_sequence_ = 0;
  bool batch_handles_enabled_ = false;
  BatchHandles batch_handles_;
  absl::flat_hash_map<uint64_t, v1::SessionResponse> early_answers_;
  std::string last_message_;
};

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_SESSION_STREAM_H_

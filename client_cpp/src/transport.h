// How the client's operations reach the server: unary RPCs or one Session
// stream. Both take the operation as a SessionRequest (whose oneof names every
// environment operation) and fill a SessionResponse, so that everything above
// (building requests, decoding results, handles) exists once for both modes.
#ifndef MLL_CLIENT_SRC_TRANSPORT_H_
#define MLL_CLIENT_SRC_TRANSPORT_H_

#include <atomic>
#include <future>
#include <memory>
#include <optional>
#include <string>
#include <thread>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "grpcpp/channel.h"
#include "grpcpp/client_context.h"
#include "grpcpp/support/status.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"
#include "session_stream.h"

namespace mll::client {
namespace internal {

// The server's code and message, unchanged (gRPC and absl share the codes).
absl::Status FromGrpc(const grpc::Status& status);
absl::Status FromItemError(const v1::ItemError& error);

class Transport {
 public:
  Transport(std::string address, std::shared_ptr<grpc::Channel> channel,
            ClientOptions options);
  // Stops the lease renewals.
  virtual ~Transport();
  Transport(const Transport&) = delete;
  Transport& operator=(const Transport&) = delete;

  // Runs the operation set in `request.op` and fills the matching member of
  // `response.result`. The returned status is the operation's (a server error
  // or a transport failure such as UNAVAILABLE).
  virtual absl::Status Call(v1::SessionRequest& request,
                            v1::SessionResponse* response) = 0;
  virtual bool is_session() const = 0;

  // Call without waiting: the future holds Call's status, and `request` and
  // `response` must live until it is ready. This base version runs Call on a
  // thread of its own (a session's stream is synchronous); a unary StepBatch
  // is started at once on a completion queue that the waiting thread drains,
  // so calls to several servers are in flight together without a thread
  // each (the cheapest of the three ways measured, bench/client_cpp).
  virtual std::future<absl::Status> CallAsync(v1::SessionRequest& request,
                                              v1::SessionResponse* response);

  // The address the transport was made for (the same for its sessions).
  const std::string& address() const { return address_; }
  // The options it was made with (for a new channel to the same address).
  const ClientOptions& options() const { return options_; }

  // Operations that exist only as unary RPCs, whatever the mode.
  absl::Status ListEnvs(const v1::ListEnvsRequest& request,
                        v1::ListEnvsResponse* response) const;
  absl::Status CheckHealth(absl::string_view service) const;

  // A new session stream on the same channel.
  absl::StatusOr<std::shared_ptr<Transport>> OpenSession() const;

  // Leases (EnvInfo::idle_timeout_s): while `name` is held (once per Hold,
  // until as many Unholds), a thread of this transport renews it with a
  // KeepAlive call carrying every held name, every third of the timeout.
  // idle_timeout_s <= 0 (a server without KeepAlive) holds nothing.
  void Hold(const std::string& name, double idle_timeout_s);
  void Unhold(const std::string& name);

  // GetServerInfo (server_info.cc): asked by the first call, remembered for
  // the transport's life; a server without the RPC (UNIMPLEMENTED) is
  // remembered as protocol 1.0. Failures are not remembered. `fresh` asks
  // again (the load figures change) and remembers the new answer.
  absl::StatusOr<v1::ServerInfo> ServerInfo(bool fresh = false);

 protected:
  // Adds the token and, for unary calls, the deadline: call_timeout, or
  // else the step timeout's answer time for `request` (when given).
  // Returns the deadline's timeout (infinite: none).
  absl::Duration Prepare(grpc::ClientContext* context, bool unary,
                         const v1::SessionRequest* request = nullptr) const;
  // A unary call's status; a missed deadline `timeout` (Prepare's) says
  // which server missed what timeout.
  absl::Status FromCall(const grpc::Status& status,
                        absl::Duration timeout) const;

  std::string address_;
  std::shared_ptr<grpc::Channel> channel_;
  ClientOptions options_;
  std::unique_ptr<v1::MultiLunarLander::Stub> stub_;

 private:
  void RenewLoop();

  absl::Mutex lease_mu_;
  absl::CondVar lease_wake_;
  absl::flat_hash_map<std::string, int> held_ ABSL_GUARDED_BY(lease_mu_);
  absl::Duration lease_period_ ABSL_GUARDED_BY(lease_mu_) =
      absl::InfiniteDuration();
  bool stopping_ ABSL_GUARDED_BY(lease_mu_) = false;
  std::thread renewer_;  // Started by the first Hold.

  mutable absl::Mutex server_info_mu_;
  std::optional<v1::ServerInfo> server_info_ ABSL_GUARDED_BY(server_info_mu_);
};

// A session: one Session stream (SessionStream), shared by the threads
// using it. Call sends and waits; Send and Receive let several requests be
// in flight (pipelined on the stream), as CallAsync does.
class StreamTransport final : public Transport {
 public:
  StreamTransport(std::string address, std::shared_ptr<grpc::Channel> channel,
                  ClientOptions options);
  ~StreamTransport() override;

  absl::Status Call(v1::SessionRequest& request,
                    v1::SessionResponse* response) override;
  std::future<absl::Status> CallAsync(v1::SessionRequest& request,
                                      v1::SessionResponse* response) override;
  bool is_session() const override { return true; }

  // Opens the stream now (shared memory as ClientOptions::session_transport
  // asks).
  absl::Status Open();
  // As SessionStream::Send and Receive, each under the transport's lock.
  absl::StatusOr<uint64_t> Send(v1::SessionRequest& request);
  absl::Status Receive(uint64_t sequence, v1::SessionResponse* response);
  std::optional<absl::Status> Receive(uint64_t sequence,
                                      v1::SessionResponse* response,
                                      absl::Duration timeout);
  // "shared_memory" or "native" (opening the stream when none is open).
  std::string transport_name();

  // Whether the server was found to have "packed_batch_handles" (asked
  // before the first packed StepBatch goes out), so that packed StepBatches
  // go out by handle (SessionStream).
  bool batch_handles_in_use();

 private:
  friend class Transport;  // OpenSession hands its ServerInfo down.
  // Enables the stream's batch handles before the first packed StepBatch,
  // when the server has them; a server that cannot be asked (GetServerInfo
  // failed) gets none on this stream transport.
  void DecideBatchHandles(const v1::SessionRequest& request);

  std::atomic<bool> batch_handles_decided_{false};
  absl::Mutex mu_;
  SessionStream stream_ ABSL_GUARDED_BY(mu_);
};

// A unary transport for `address`.
absl::StatusOr<std::shared_ptr<Transport>> MakeUnaryTransport(
    absl::string_view address, const ClientOptions& options);

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_TRANSPORT_H_

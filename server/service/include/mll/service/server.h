// A running Multi Lunar Lander server: the service plus gRPC's health
// service and server reflection, listening on a TCP address (plaintext or
// TLS) and/or reachable in-process, and optionally a Prometheus endpoint.
// Used by mll_server and by the tests.
#ifndef MLL_SERVICE_SERVER_H_
#define MLL_SERVICE_SERVER_H_

#include <memory>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/time/time.h"
#include "grpcpp/grpcpp.h"
#include "mll/service/dashboard.h"
#include "mll/service/service.h"

namespace mll::service {

class MetricsHttpServer;

struct ServerOptions {
  // host:port to listen on (--address); port 0 picks a free port;
  // unix:PATH listens on a Unix-domain socket; empty listens nowhere
  // (in-process channels only).
  std::string address = "127.0.0.1:50051";
  // Largest message received or sent, in MiB (--max_message_mb). 1..2047.
  int max_message_mb = 64;
  // PEM files of the server's certificate chain and private key (--tls_cert,
  // --tls_key): both set, the address serves TLS only; both empty,
  // plaintext. One without the other is INVALID_ARGUMENT.
  std::string tls_cert_file;
  std::string tls_key_file;
  // host:port of the Prometheus endpoint GET /metrics (--metrics_address);
  // port 0 picks a free port; empty: no endpoint.
  std::string metrics_address;
  // host:port of the web dashboard (--http_address, dashboard.h); port 0
  // picks a free port; empty: off.
  std::string http_address;
  ServiceOptions service;
};

// INVALID_ARGUMENT naming the flag unless every option is in its range.
absl::Status ValidateServerOptions(const ServerOptions& options);

class Server {
 public:
  // Validates the options, builds and starts the server. INVALID_ARGUMENT
  // for a malformed or out-of-range address; UNAVAILABLE when the address
  // cannot be bound (in use: gRPC's SO_REUSEPORT is off) or gRPC bound
  // another port than the one asked for.
  static absl::StatusOr<std::unique_ptr<Server>> Start(
      const ServerOptions& options);

  // Shuts down with a short grace period if Shutdown was not called.
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  // The bound TCP port (0 when not listening, or on a unix: socket).
  int port() const { return port_; }
  // The bound port of the metrics endpoint (0 when off).
  int metrics_port() const;
  // The bound port of the dashboard (0 when off).
  int http_port() const;
  // The dashboard, or nullptr when off.
  DashboardServer* dashboard() { return dashboard_.get(); }
  bool tls() const { return tls_; }
  // A channel to this server that bypasses the network.
  std::shared_ptr<grpc::Channel> InProcessChannel();
  MultiLunarLanderService& service() { return *service_; }

  // The first step of a graceful stop (mll_server on SIGTERM, --drain_s):
  // health answers NOT_SERVING; CreateEnv, GetServerInfo and new Session
  // streams get UNAVAILABLE "draining: ..." (kDrainingPrefix); every open
  // Session stream is ended with that status, so that its client moves its
  // envs; calls on the envs still here are served. Returns when no env is
  // left or `period` has passed, whichever comes first, with the count of
  // envs left. Shutdown follows.
  int Drain(absl::Duration period);

  // Stops accepting calls, lets in-flight calls finish until `grace` has
  // passed, then cancels the rest. Returns when every call has ended.
  void Shutdown(absl::Duration grace);

 private:
  Server() = default;

  std::unique_ptr<MultiLunarLanderService> service_;
  std::unique_ptr<grpc::Server> server_;
  std::unique_ptr<MetricsHttpServer> metrics_http_;
  std::unique_ptr<DashboardServer> dashboard_;
  int port_ = 0;
  bool tls_ = false;
  bool shut_down_ = false;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_SERVER_H_

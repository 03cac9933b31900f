// The Prometheus scrape endpoint: GET /metrics over plain HTTP on its own
// address (--metrics_address), served by cpp-httplib on two threads of its
// own so that scrapes never wait behind RPCs and RPCs never wait for them.
#ifndef MLL_SERVICE_METRICS_HTTP_H_
#define MLL_SERVICE_METRICS_HTTP_H_

#include <atomic>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "absl/status/statusor.h"

namespace httplib {
class Server;
}  // namespace httplib

namespace mll {

class MetricsHttpServer {
 public:
  // Listens on `address` (host:port; port 0 picks a free one) and answers
  // GET /metrics with render(). INVALID_ARGUMENT naming --metrics_address for
  // a malformed address, UNAVAILABLE when it cannot be bound.
  static absl::StatusOr<std::unique_ptr<MetricsHttpServer>> Start(
      const std::string& address, std::function<std::string()> render);

  // Stops listening and waits for the serving thread.
  ~MetricsHttpServer();
  MetricsHttpServer(const MetricsHttpServer&) = delete;
  MetricsHttpServer& operator=(const MetricsHttpServer&) = delete;

  int port() const { return port_; }

 private:
  MetricsHttpServer();

  std::unique_ptr<httplib::Server> http_;
  std::thread thread_;
  int port_ = 0;
  // From the start of the serving thread until it leaves the listen loop.
  std::atomic<bool> listening_{false};
};

}  // namespace mll

#endif  // MLL_SERVICE_METRICS_HTTP_H_

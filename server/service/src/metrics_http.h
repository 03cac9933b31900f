// The Prometheus scrape endpoint: GET /metrics over plain HTTP on its own
// address (--metrics_address), served by cpp-httplib on two threads of its
// own so that scrapes never wait behind RPCs and RPCs never wait for them.
#ifndef MLL_SERVICE_SRC_METRICS_HTTP_H_
#define MLL_SERVICE_SRC_METRICS_HTTP_H_

#include <functional>
#include <memory>
#include <string>
#include <utility>

#include "absl/status/statusor.h"
#include "http_listener.h"

namespace mll::service {

class MetricsHttpServer {
 public:
  // Listens on `address` (host:port; port 0 picks a free one) and answers
  // GET /metrics with render(). INVALID_ARGUMENT naming --metrics_address for
  // a malformed address, UNAVAILABLE when it cannot be bound.
  static absl::StatusOr<std::unique_ptr<MetricsHttpServer>> Start(
      const std::string& address, std::function<std::string()> render);

  int port() const { return listener_->port(); }

 private:
  explicit MetricsHttpServer(std::unique_ptr<HttpListener> listener)
      : listener_(std::move(listener)) {}

  std::unique_ptr<HttpListener> listener_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_SRC_METRICS_HTTP_H_

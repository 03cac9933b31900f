// One cpp-httplib server on its own address and threads: the address is
// checked and bound the same way for every HTTP listener of mll_server
// (--metrics_address, --http_address), so a malformed or busy address fails
// with one line naming the flag.
#ifndef MLL_SERVICE_SRC_HTTP_LISTENER_H_
#define MLL_SERVICE_SRC_HTTP_LISTENER_H_

#include <atomic>
#include <functional>
#include <memory>
#include <string>
#include <thread>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace httplib {
class Server;
}  // namespace httplib

namespace mll::service {

class HttpListener {
 public:
  // Listens on `address` (host:port, [v6]:port; port 0 picks a free one)
  // with `threads` worker threads, after `routes` has registered the
  // handlers. INVALID_ARGUMENT naming `flag` for a malformed address (its
  // examples show `example_port`), UNAVAILABLE when it cannot be bound (e.g.
  // in use).
  static absl::StatusOr<std::unique_ptr<HttpListener>> Start(
      absl::string_view flag, const std::string& address, int example_port,
      int threads, const std::function<void(httplib::Server&)>& routes);

  // Stops listening and waits for the serving thread and its workers
  // (handlers still running must return on their own).
  ~HttpListener();
  HttpListener(const HttpListener&) = delete;
  HttpListener& operator=(const HttpListener&) = delete;

  int port() const { return port_; }

 private:
  HttpListener();

  std::unique_ptr<httplib::Server> http_;
  std::thread thread_;
  int port_ = 0;
  // From the start of the serving thread until it leaves the listen loop.
  std::atomic<bool> listening_{false};
};

}  // namespace mll::service

#endif  // MLL_SERVICE_SRC_HTTP_LISTENER_H_

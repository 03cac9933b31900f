#include "http_listener.h"

#include <sys/socket.h>

#include <chrono>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "httplib.h"
#include "listen_address.h"

namespace mll::service {
namespace {

constexpr int kIoTimeoutS = 5;

}  // namespace

HttpListener::HttpListener() : http_(std::make_unique<httplib::Server>()) {}

absl::StatusOr<std::unique_ptr<HttpListener>> HttpListener::Start(
    absl::string_view flag, const std::string& address, int example_port,
    int threads, const std::function<void(httplib::Server&)>& routes) {
  absl::StatusOr<ListenAddress> parsed =
      ParseListenAddress(flag, address, example_port);
  if (!parsed.ok()) return parsed.status();
  const int port = parsed->port;
  std::string host = parsed->host;
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }

  std::unique_ptr<HttpListener> listener(new HttpListener());
  httplib::Server& http = *listener->http_;
  http.new_task_queue = [threads] { return new httplib::ThreadPool(threads); };
  // SO_REUSEADDR only: httplib's default adds SO_REUSEPORT, with which a
  // second server would share a port in use instead of failing to bind.
  http.set_socket_options([](socket_t sock) {
    const int yes = 1;
    setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
  });
  http.set_read_timeout(kIoTimeoutS);
  http.set_write_timeout(kIoTimeoutS);
  routes(http);
  listener->port_ = port == 0 ? http.bind_to_any_port(host)
                              : (http.bind_to_port(host, port) ? port : -1);
  if (listener->port_ <= 0) {
    return absl::UnavailableError(
        absl::StrCat(flag, ": cannot listen on ", address,
                     " (in use, or not host:port of a local interface)"));
  }
  HttpListener* self = listener.get();
  listener->listening_ = true;
  listener->thread_ = std::thread([self] {
    self->http_->listen_after_bind();
    self->listening_ = false;
  });
  return listener;
}

HttpListener::~HttpListener() {
  // stop() only acts on a listener that has started its loop; until the
  // thread has returned, it is repeated.
  while (listening_) {
    http_->stop();
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  if (thread_.joinable()) thread_.join();
}

}  // namespace mll::service

#include "mll/service/metrics_http.h"

#include <sys/socket.h>

#include <chrono>
#include <utility>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/string_view.h"
#include "httplib.h"
#include "mll/service/listen_address.h"

namespace mll {
namespace {

constexpr char kContentType[] = "text/plain; version=0.0.4; charset=utf-8";
// A scraper or two: more threads would only idle.
constexpr int kHttpThreads = 2;
constexpr int kIoTimeoutS = 5;
constexpr int kExamplePort = 9464;

}  // namespace

MetricsHttpServer::MetricsHttpServer()
    : http_(std::make_unique<httplib::Server>()) {}

absl::StatusOr<std::unique_ptr<MetricsHttpServer>> MetricsHttpServer::Start(
    const std::string& address, std::function<std::string()> render) {
  absl::StatusOr<ListenAddress> parsed =
      ParseListenAddress("--metrics_address", address, kExamplePort);
  if (!parsed.ok()) return parsed.status();
  const int port = parsed->port;
  std::string host = parsed->host;
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  }

  std::unique_ptr<MetricsHttpServer> server(new MetricsHttpServer());
  httplib::Server& http = *server->http_;
  http.new_task_queue = [] { return new httplib::ThreadPool(kHttpThreads); };
  // SO_REUSEADDR only: httplib's default adds SO_REUSEPORT, with which a
  // second server would share a port in use instead of failing to bind.
  http.set_socket_options([](socket_t sock) {
    const int yes = 1;
    setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof(yes));
  });
  http.set_read_timeout(kIoTimeoutS);
  http.set_write_timeout(kIoTimeoutS);
  http.Get("/metrics", [render = std::move(render)](
                           const httplib::Request&, httplib::Response& res) {
    res.set_content(render(), kContentType);
  });
  server->port_ = port == 0 ? http.bind_to_any_port(host)
                            : (http.bind_to_port(host, port) ? port : -1);
  if (server->port_ <= 0) {
    return absl::UnavailableError(absl::StrCat(
        "--metrics_address: cannot listen on ", address,
        " (in use, or not host:port of a local interface)"));
  }
  MetricsHttpServer* self = server.get();
  server->listening_ = true;
  server->thread_ = std::thread([self] {
    self->http_->listen_after_bind();
    self->listening_ = false;
  });
  return server;
}

MetricsHttpServer::~MetricsHttpServer() {
  // stop() only acts on a listener that has started its loop; until the
  // thread has returned, it is repeated.
  while (listening_) {
    http_->stop();
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  if (thread_.joinable()) thread_.join();
}

}  // namespace mll

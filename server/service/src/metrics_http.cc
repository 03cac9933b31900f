#include "metrics_http.h"

#include <utility>

#include "httplib.h"

namespace mll::service {
namespace {

// The port the address error's examples show.
constexpr int kExamplePort = 9464;

constexpr char kContentType[] = "text/plain; version=0.0.4; charset=utf-8";
// A scraper or two: more threads would only idle.
constexpr int kHttpThreads = 2;

}  // namespace

absl::StatusOr<std::unique_ptr<MetricsHttpServer>> MetricsHttpServer::Start(
    const std::string& address, std::function<std::string()> render) {
  absl::StatusOr<std::unique_ptr<HttpListener>> listener = HttpListener::Start(
      "--metrics_address", address, kExamplePort, kHttpThreads,
      [&render](httplib::Server& http) {
        http.Get("/metrics",
                 [render = std::move(render)](const httplib::Request&,
                                              httplib::Response& res) {
                   res.set_content(render(), kContentType);
                 });
      });
  if (!listener.ok()) return listener.status();
  return std::unique_ptr<MetricsHttpServer>(
      new MetricsHttpServer(*std::move(listener)));
}

}  // namespace mll::service

// The web dashboard (--http_address): a page listing the hosted environments
// that refreshes itself, and a live view of any of them, its frames streamed
// as server-sent events carrying PNGs. Plain HTML/CSS/JS served from the
// binary.
//
// Watching is read-only: a frame is drawn from a copy of the env's Scene
// taken under the env's lock (no generator draw, no particle ageing, no
// lease touched), outside the lock, and only when the env has stepped or
// reset since the last one; viewers of one env share each frame. A stream
// lives in one HTTP worker thread and ends with its connection: nothing is
// left running for a viewer that has gone.
//
// With authentication on, every /api call needs the token as `Authorization:
// Bearer <token>` or the cookie `mll_token` (which the page sets, for the
// browser's EventSource), and shows only that token's environments.
#ifndef MLL_SERVICE_DASHBOARD_H_
#define MLL_SERVICE_DASHBOARD_H_

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/statusor.h"
#include "absl/synchronization/mutex.h"
#include "mll/service/auth.h"
#include "mll/service/registry.h"

namespace httplib {
class Server;
struct Request;
struct Response;
}  // namespace httplib

namespace mll::service {

class HttpListener;

class DashboardServer {
 public:
  // Viewers streaming at once, over all envs; more get 503.
  static constexpr int kMaxViewers = 16;
  // Frames per second of a stream, at most (and the default).
  static constexpr int kMaxFps = 30;

  // Serves the dashboard of `registry`'s envs on `address` (host:port; port
  // 0 picks a free one). INVALID_ARGUMENT naming --http_address for a
  // malformed address, UNAVAILABLE when it cannot be bound. `registry` and
  // `authenticator` must outlive the server.
  static absl::StatusOr<std::unique_ptr<DashboardServer>> Start(
      const std::string& address, Registry* registry,
      const Authenticator* authenticator);

  // Ends every stream and stops listening.
  ~DashboardServer();
  DashboardServer(const DashboardServer&) = delete;
  DashboardServer& operator=(const DashboardServer&) = delete;

  int port() const;
  // Streams open now.
  int viewers() const { return viewers_.load(); }
  // Frames drawn since the start (shared frames count once).
  int64_t frames_rendered() const { return frames_rendered_.load(); }

 private:
  struct FrameCache;
  class Stream;

  DashboardServer(Registry* registry, const Authenticator* authenticator);
  void AddRoutes(httplib::Server& http);
  // The caller's owner, or nullopt (the response is then set to 401).
  std::optional<std::string> Owner(const httplib::Request& req,
                                   httplib::Response& res) const;
  void ListEnvs(const httplib::Request& req, httplib::Response& res);
  void StreamFrames(const httplib::Request& req, httplib::Response& res);
  // The cache shared by the viewers of env `name`.
  std::shared_ptr<FrameCache> CacheFor(const std::string& name);

  Registry* const registry_;
  const Authenticator* const authenticator_;
  std::atomic<bool> stopping_{false};
  std::atomic<int> viewers_{0};
  std::atomic<int64_t> frames_rendered_{0};
  absl::Mutex caches_mu_;
  absl::flat_hash_map<std::string, std::weak_ptr<FrameCache>> caches_
      ABSL_GUARDED_BY(caches_mu_);
  // Last member: destroyed (its threads joined) before the rest.
  std::unique_ptr<HttpListener> listener_;
};

// The dashboard's single page (dashboard_page.cc).
const char* DashboardPage();

}  // namespace mll::service

#endif  // MLL_SERVICE_DASHBOARD_H_

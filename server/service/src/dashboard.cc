#include "mll/service/dashboard.h"

#include <algorithm>
#include <chrono>
#include <csignal>
#include <cstdio>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/escaping.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "http_listener.h"
#include "httplib.h"
#include "mll/core/renderer.h"

namespace mll::service {
namespace {

// The port the address error's examples show.
constexpr int kExamplePort = 8080;

// Viewers plus a few threads for the page and the list it polls.
constexpr int kHttpThreads = DashboardServer::kMaxViewers + 4;
// An idle stream (the env does not step) still writes a comment this often,
// so that a viewer that has gone is noticed and its thread freed.
constexpr auto kKeepAlive = std::chrono::seconds(1);
// Envs listed at most, per caller.
constexpr int kMaxListed = 1000;
constexpr char kTokenCookie[] = "mll_token";
constexpr auto kMinFramePeriod =
    std::chrono::microseconds(1000000 / DashboardServer::kMaxFps);

// What identifies a frame: the same (episode, step) draws the same picture.
struct Version {
  int64_t episode = -1;
  int cycles = -1;
  bool operator==(const Version& o) const {
    return episode == o.episode && cycles == o.cycles;
  }
  bool operator!=(const Version& o) const { return !(*this == o); }
};

std::string JsonString(absl::string_view text) {
  std::string out = "\"";
  for (char c : text) {
    if (c == '"' || c == '\\') {
      out += '\\';
      out += c;
    } else if (static_cast<unsigned char>(c) < 0x20) {
      char escaped[8];
      std::snprintf(escaped, sizeof(escaped), "\\u%04x", c);
      out += escaped;
    } else {
      out += c;
    }
  }
  return out + "\"";
}

void SetError(httplib::Response& res, int status, absl::string_view message) {
  res.status = status;
  res.set_content(absl::StrCat("{\"error\":", JsonString(message), "}"),
                  "application/json");
}

// The env's version, under its lock; nullopt when it is gone.
std::optional<Version> ReadVersion(EnvSlot& slot) {
  absl::MutexLock lock(&slot.mu);
  if (slot.env == nullptr) return std::nullopt;
  return Version{slot.episodes, slot.env->cycles()};
}

// The slot of env `name` if `owner` may see it, without touching its lease.
std::shared_ptr<EnvSlot> FindListed(Registry& registry, absl::string_view name,
                                    absl::string_view owner) {
  absl::StatusOr<Registry::Page> page = registry.List(kMaxListed, "", owner);
  if (!page.ok()) return nullptr;
  for (std::shared_ptr<EnvSlot>& slot : page->slots) {
    if (slot->name == name) return std::move(slot);
  }
  return nullptr;
}

}  // namespace

// The latest frame of one env, shared by its viewers: the first viewer to
// need a newer version draws it while the others wait on `mu`. Time is cut
// in slots of 1 / kMaxFps s and a frame drawn in the current slot is served
// even if the env has moved on, so an env is drawn at most kMaxFps times a
// second however many viewers it has, and a viewer ticking at kMaxFps still
// gets a new frame at each tick.
struct DashboardServer::FrameCache {
  absl::Mutex mu;
  Version version ABSL_GUARDED_BY(mu);
  int64_t time_slot ABSL_GUARDED_BY(mu) = -1;
  // The whole server-sent event: "event: frame", the version and the PNG.
  std::shared_ptr<const std::string> event ABSL_GUARDED_BY(mu);
};

DashboardServer::DashboardServer(Registry* registry,
                                 const Authenticator* authenticator)
    : registry_(registry), authenticator_(authenticator) {}

absl::StatusOr<std::unique_ptr<DashboardServer>> DashboardServer::Start(
    const std::string& address, Registry* registry,
    const Authenticator* authenticator) {
  // A viewer that closes its tab makes the next write fail with EPIPE; the
  // signal would end the process.
  std::signal(SIGPIPE, SIG_IGN);
  std::unique_ptr<DashboardServer> server(
      new DashboardServer(registry, authenticator));
  DashboardServer* self = server.get();
  absl::StatusOr<std::unique_ptr<HttpListener>> listener = HttpListener::Start(
      "--http_address", address, kExamplePort, kHttpThreads,
      [self](httplib::Server& http) { self->AddRoutes(http); });
  if (!listener.ok()) return listener.status();
  server->listener_ = *std::move(listener);
  return server;
}

DashboardServer::~DashboardServer() {
  stopping_ = true;  // Streams return within one frame period.
  listener_.reset();
}

int DashboardServer::port() const { return listener_->port(); }

void DashboardServer::AddRoutes(httplib::Server& http) {
  http.Get("/", [](const httplib::Request&, httplib::Response& res) {
    res.set_header("Cache-Control", "no-store");
    res.set_content(DashboardPage(), "text/html; charset=utf-8");
  });
  http.Get("/api/envs", [this](const httplib::Request& req,
                               httplib::Response& res) { ListEnvs(req, res); });
  http.Get("/api/frames",
           [this](const httplib::Request& req, httplib::Response& res) {
             StreamFrames(req, res);
           });
}

std::optional<std::string> DashboardServer::Owner(
    const httplib::Request& req, httplib::Response& res) const {
  if (!authenticator_->enabled()) return std::string(kAnonymousOwner);
  std::optional<std::string> authorization;
  if (req.has_header("Authorization")) {
    authorization = req.get_header_value("Authorization");
  } else {
    for (absl::string_view cookie :
         absl::StrSplit(req.get_header_value("Cookie"), ';')) {
      cookie = absl::StripAsciiWhitespace(cookie);
      if (absl::ConsumePrefix(&cookie, kTokenCookie) &&
          absl::ConsumePrefix(&cookie, "=")) {
        std::string token;
        // The page stores the token URI-encoded.
        token = httplib::detail::decode_url(std::string(cookie), false);
        authorization = absl::StrCat("Bearer ", token);
      }
    }
  }
  absl::StatusOr<absl::string_view> owner =
      authenticator_->Authenticate(authorization);
  if (!owner.ok()) {
    SetError(res, 401, owner.status().message());
    return std::nullopt;
  }
  return std::string(*owner);
}

void DashboardServer::ListEnvs(const httplib::Request& req,
                               httplib::Response& res) {
  std::optional<std::string> owner = Owner(req, res);
  if (!owner.has_value()) return;
  absl::StatusOr<Registry::Page> page = registry_->List(kMaxListed, "", *owner);
  if (!page.ok()) {
    SetError(res, 500, page.status().message());
    return;
  }
  std::string json = "{\"envs\":[";
  bool first = true;
  for (const std::shared_ptr<EnvSlot>& slot : page->slots) {
    std::string entry;
    {
      absl::MutexLock lock(&slot->mu);
      if (slot->env == nullptr) continue;
      const core::Env& env = *slot->env;
      const bool started = env.episode_started();
      absl::StrAppend(
          &entry, "{\"name\":", JsonString(slot->name),
          ",\"landers\":", slot->config.n_landers,
          ",\"continuous\":", slot->config.continuous ? "true" : "false",
          ",\"episode\":", slot->episodes,
          ",\"step\":", started ? env.cycles() : 0,
          ",\"active\":", started ? env.num_active() : 0, ",\"returns\":[");
      for (int i = 0; i < slot->config.n_landers; ++i) {
        char value[32];
        std::snprintf(value, sizeof(value), "%.2f",
                      started ? env.episode_return(i) : 0.0);
        absl::StrAppend(&entry, i > 0 ? "," : "", value);
      }
      absl::StrAppend(&entry, "],\"outcomes\":[");
      for (int i = 0; i < slot->config.n_landers; ++i) {
        absl::StrAppend(
            &entry, i > 0 ? "," : "",
            JsonString(started ? core::OutcomeName(env.outcome(i)) : "none"));
      }
      absl::StrAppend(&entry, "]}");
    }
    absl::StrAppend(&json, first ? "" : ",", entry);
    first = false;
  }
  absl::StrAppend(
      &json, "],\"auth\":", authenticator_->enabled() ? "true" : "false", "}");
  res.set_header("Cache-Control", "no-store");
  res.set_content(json, "application/json");
}

std::shared_ptr<DashboardServer::FrameCache> DashboardServer::CacheFor(
    const std::string& name) {
  absl::MutexLock lock(&caches_mu_);
  // Caches of envs nobody watches any more go here.
  for (auto it = caches_.begin(); it != caches_.end();) {
    if (it->second.expired()) {
      caches_.erase(it++);
    } else {
      ++it;
    }
  }
  std::shared_ptr<FrameCache> cache = caches_[name].lock();
  if (cache == nullptr) {
    cache = std::make_shared<FrameCache>();
    caches_[name] = cache;
  }
  return cache;
}

void DashboardServer::StreamFrames(const httplib::Request& req,
                                   httplib::Response& res) {
  std::optional<std::string> owner = Owner(req, res);
  if (!owner.has_value()) return;
  const std::string name = req.get_param_value("name");
  std::shared_ptr<EnvSlot> found = FindListed(*registry_, name, *owner);
  if (found == nullptr) {
    SetError(res, 404,
             absl::StrCat("name: no env ", JsonString(name),
                          " (allowed: a name from /api/envs)"));
    return;
  }
  int fps = kMaxFps;
  if (req.has_param("fps") &&
      (!absl::SimpleAtoi(req.get_param_value("fps"), &fps) || fps < 1 ||
       fps > kMaxFps)) {
    SetError(res, 400,
             absl::StrCat("fps: \"", req.get_param_value("fps"),
                          "\" is out of range (allowed: 1..", kMaxFps, ")"));
    return;
  }
  if (viewers_.fetch_add(1) >= kMaxViewers) {
    viewers_.fetch_sub(1);
    SetError(res, 503,
             absl::StrCat("too many viewers (at most ", kMaxViewers,
                          " streams at once); close one and retry"));
    return;
  }
  // Counts the viewer until the provider below is destroyed, which happens
  // when the response ends, whatever ends it.
  struct ViewerSlot {
    explicit ViewerSlot(std::atomic<int>* viewers) : viewers(viewers) {}
    ~ViewerSlot() { viewers->fetch_sub(1); }
    std::atomic<int>* viewers;
  };
  auto viewer = std::make_shared<ViewerSlot>(&viewers_);
  std::weak_ptr<EnvSlot> watched = found;
  found.reset();  // The stream must not keep a deleted env alive.
  std::shared_ptr<FrameCache> cache = CacheFor(name);
  const auto period = std::chrono::microseconds(1000000 / fps);

  res.set_header("Cache-Control", "no-store");
  res.set_header("X-Accel-Buffering", "no");
  res.set_chunked_content_provider(
      "text/event-stream", [this, viewer, watched, cache, name, period](
                               size_t, httplib::DataSink& sink) {
        Version sent;
        auto last_write = std::chrono::steady_clock::now();
        auto next = last_write;
        while (!stopping_) {
          std::shared_ptr<EnvSlot> slot = watched.lock();
          std::optional<Version> version;
          if (slot != nullptr) version = ReadVersion(*slot);
          if (!version.has_value()) {
            sink.write("event: gone\ndata: {}\n\n", 22);
            sink.done();
            return true;
          }
          std::shared_ptr<const std::string> event;
          if (*version != sent) {
            absl::MutexLock lock(&cache->mu);
            const int64_t time_slot =
                std::chrono::steady_clock::now().time_since_epoch() /
                kMinFramePeriod;
            if (cache->event == nullptr ||
                (cache->version != *version && cache->time_slot != time_slot)) {
              core::Scene scene;
              Version drawn;
              {
                absl::MutexLock env_lock(&slot->mu);
                if (slot->env == nullptr) continue;  // Gone: said next turn.
                scene = slot->env->scene();
                drawn = {slot->episodes, slot->env->cycles()};
              }
              core::RenderOptions options;
              options.overlay = true;
              options.caption = absl::StrCat(name, "  episode ", drawn.episode);
              absl::StatusOr<std::string> png =
                  core::EncodePng(core::RenderScene(scene, options));
              if (!png.ok()) return false;
              cache->event = std::make_shared<const std::string>(absl::StrCat(
                  "event: frame\nid: ", drawn.episode, ".", drawn.cycles,
                  "\ndata: ", absl::Base64Escape(*png), "\n\n"));
              cache->version = drawn;
              cache->time_slot = time_slot;
              frames_rendered_.fetch_add(1);
            }
            if (cache->version != sent) event = cache->event;
            sent = cache->version;
          }
          slot.reset();
          const auto now = std::chrono::steady_clock::now();
          if (event != nullptr) {
            if (!sink.write(event->data(), event->size())) return false;
            last_write = now;
          } else if (now - last_write >= kKeepAlive) {
            if (!sink.write(": keep-alive\n\n", 14)) return false;
            last_write = now;
          }
          next = std::max(next + period, now);
          std::this_thread::sleep_until(next);
        }
        return false;
      });
}

}  // namespace mll::service

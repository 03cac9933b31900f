// What watching costs: one client steps one env (3 landers, unary StepEnv
// over loopback TCP, as fast as it can) on a server with --threads=2 and the
// dashboard on, in rounds of `--round_s` seconds that alternate between no
// viewer and `--viewers` viewers streaming that env's frames (at up to 30
// FPS each). The floor is the same client in the same run with no viewer;
// the figure is the median ratio of steps/s with viewers to steps/s
// without, over `--pairs` pairs of rounds. The viewers run in this process
// too (their reading is counted against the client, a conservative setup).
// Beside the ratio: the process's CPU time per second in each kind of round,
// whose difference is what the viewers cost in CPU (on a loaded machine a
// ping-pong client can even run faster beside busy threads, whose activity
// keeps cores awake).
// Run: build/bench/dashboard/dashboard_bench [--viewers=8] [--pairs=5]
//      [--round_s=3]
#include <sys/resource.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "grpcpp/grpcpp.h"
#include "httplib.h"
#include "mll/service/convert.h"
#include "mll/service/server.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"

namespace mll::service {
namespace {

constexpr int kLanders = 3;

struct Flags {
  int viewers = 8;
  int pairs = 5;
  double round_s = 3.0;
};

Flags ParseFlags(int argc, char** argv) {
  Flags flags;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    auto value = [&](const char* name) -> const char* {
      const std::string prefix = absl::StrCat("--", name, "=");
      return arg.rfind(prefix, 0) == 0 ? argv[i] + prefix.size() : nullptr;
    };
    if (const char* v = value("viewers")) {
      flags.viewers = std::atoi(v);
    } else if (const char* v = value("pairs")) {
      flags.pairs = std::atoi(v);
    } else if (const char* v = value("round_s")) {
      flags.round_s = std::atof(v);
    } else {
      std::fprintf(stderr, "dashboard_bench: unknown flag %s\n", argv[i]);
      std::exit(2);
    }
  }
  if (flags.viewers < 1 || flags.viewers > DashboardServer::kMaxViewers ||
      flags.pairs < 1 || flags.pairs > 100 || !(flags.round_s > 0) ||
      flags.round_s > 60) {
    std::fprintf(stderr,
                 "dashboard_bench: allowed --viewers=1..%d --pairs=1..100 "
                 "--round_s=(0, 60]\n",
                 DashboardServer::kMaxViewers);
    std::exit(2);
  }
  return flags;
}

// Steps `name` for `seconds`, resetting when the episode ends; steps/s.
double StepFor(v1::MultiLunarLander::Stub& stub, const std::string& name,
               double seconds) {
  v1::StepEnvRequest request;
  request.set_name(name);
  int64_t steps = 0;
  const auto start = std::chrono::steady_clock::now();
  const auto end = start + std::chrono::duration<double>(seconds);
  while (std::chrono::steady_clock::now() < end) {
    std::vector<int32_t> actions(kLanders);
    for (int agent = 0; agent < kLanders; ++agent) {
      actions[agent] = (steps + agent) % 4 == 1 ? 0 : 2;
    }
    v1::Array* array = request.mutable_actions();
    array->set_dtype(v1::DTYPE_INT32);
    array->clear_shape();
    array->add_shape(kLanders);
    array->set_data(actions.data(), actions.size() * sizeof(int32_t));
    grpc::ClientContext context;
    v1::StepEnvResponse response;
    const grpc::Status status = stub.StepEnv(&context, request, &response);
    if (!status.ok()) {
      std::fprintf(stderr, "StepEnv: %s\n", status.error_message().c_str());
      std::exit(1);
    }
    ++steps;
    if (response.data().episode_over()) {
      grpc::ClientContext reset_context;
      v1::ResetEnvRequest reset;
      reset.set_name(name);
      v1::ResetEnvResponse reset_response;
      if (!stub.ResetEnv(&reset_context, reset, &reset_response).ok()) {
        std::exit(1);
      }
    }
  }
  const double elapsed =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  return steps / elapsed;
}

// `count` viewers of `name` until `stop`; counts the frames they receive.
class Viewers {
 public:
  Viewers(int port, const std::string& name, int count) {
    for (int i = 0; i < count; ++i) {
      threads_.emplace_back([this, port, name] {
        httplib::Client http("127.0.0.1", port);
        http.set_read_timeout(10);
        const std::string path = absl::StrCat("/api/frames?name=", name);
        http.Get(path.c_str(), [this](const char* data, size_t size) {
          // Each event starts with this line; chunks end on event borders.
          static constexpr char kMark[] = "event: frame";
          const char* end = data + size;
          for (const char* p = data;
               (p = static_cast<const char*>(
                    memmem(p, end - p, kMark, sizeof(kMark) - 1))) != nullptr;
               p += sizeof(kMark) - 1) {
            frames_.fetch_add(1);
          }
          return !stop_.load();
        });
      });
    }
  }
  // Joins the viewers once each has received its next chunk.
  void Stop() {
    stop_ = true;
    for (std::thread& t : threads_) t.join();
  }
  int64_t frames() const { return frames_.load(); }

 private:
  std::atomic<bool> stop_{false};
  std::atomic<int64_t> frames_{0};
  std::vector<std::thread> threads_;
};

// User + system CPU seconds of this process so far.
double CpuSeconds() {
  rusage usage;
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
         1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

double Median(std::vector<double> values) {
  std::sort(values.begin(), values.end());
  const size_t n = values.size();
  return n % 2 ? values[n / 2] : (values[n / 2 - 1] + values[n / 2]) / 2;
}

int Run(const Flags& flags) {
  ServerOptions options;
  options.address = "127.0.0.1:0";
  options.http_address = "127.0.0.1:0";
  options.service.threads = 2;
  absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
  if (!server.ok()) {
    std::fprintf(stderr, "%s\n",
                 std::string(server.status().message()).c_str());
    return 1;
  }
  auto channel =
      grpc::CreateChannel(absl::StrCat("127.0.0.1:", (*server)->port()),
                          grpc::InsecureChannelCredentials());
  auto stub = v1::MultiLunarLander::NewStub(channel);
  std::string name;
  {
    grpc::ClientContext context;
    v1::CreateEnvRequest request;
    request.mutable_config()->set_n_landers(kLanders);
    v1::Env env;
    if (!stub->CreateEnv(&context, request, &env).ok()) return 1;
    name = env.name();
    grpc::ClientContext reset_context;
    v1::ResetEnvRequest reset;
    reset.set_name(name);
    reset.set_seed(1);
    v1::ResetEnvResponse reset_response;
    if (!stub->ResetEnv(&reset_context, reset, &reset_response).ok()) return 1;
  }
  StepFor(*stub, name, 0.5);  // Warm-up.

  DashboardServer& dashboard = *(*server)->dashboard();
  std::vector<double> alone, watched, ratios, fps, drawn_per_s;
  std::vector<double> cpu_alone, cpu_watched;
  for (int pair = 0; pair < flags.pairs; ++pair) {
    double cpu = CpuSeconds();
    auto start = std::chrono::steady_clock::now();
    alone.push_back(StepFor(*stub, name, flags.round_s));
    cpu_alone.push_back(
        (CpuSeconds() - cpu) /
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
            .count());
    const int64_t drawn_before = dashboard.frames_rendered();
    Viewers viewers((*server)->http_port(), name, flags.viewers);
    while (dashboard.viewers() < flags.viewers) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    const int64_t frames_before = viewers.frames();
    cpu = CpuSeconds();
    start = std::chrono::steady_clock::now();
    watched.push_back(StepFor(*stub, name, flags.round_s));
    const double elapsed =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
            .count();
    cpu_watched.push_back((CpuSeconds() - cpu) / elapsed);
    fps.push_back((viewers.frames() - frames_before) / elapsed / flags.viewers);
    drawn_per_s.push_back((dashboard.frames_rendered() - drawn_before) /
                          elapsed);
    viewers.Stop();
    while (dashboard.viewers() > 0) {
      std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    ratios.push_back(watched.back() / alone.back());
    std::printf(
        "pair %d: %.0f steps/s alone, %.0f with %d viewers (%.3f), %.1f "
        "frames/s per viewer, %.1f frames drawn/s, CPU %.2f / %.2f cores\n",
        pair + 1, alone.back(), watched.back(), flags.viewers, ratios.back(),
        fps.back(), drawn_per_s.back(), cpu_alone.back(), cpu_watched.back());
  }
  std::printf(
      "\n| what | median over %d pairs of %.0f s rounds |\n|---|---|\n"
      "| steps/s, no viewer (floor) | %.0f |\n"
      "| steps/s, %d viewers of the same env | %.0f |\n"
      "| ratio with / without viewers | %.3f (target >= 0.90, a slowdown "
      "of at most 10%%: %s) |\n"
      "| frames/s received per viewer | %.1f |\n"
      "| frames drawn/s (shared by the viewers) | %.1f |\n"
      "| process CPU, cores: no viewer / with viewers | %.2f / %.2f |\n"
      "| CPU per step, us: no viewer / with viewers | %.0f / %.0f |\n",
      flags.pairs, flags.round_s, Median(alone), flags.viewers, Median(watched),
      Median(ratios), Median(ratios) >= 0.9 ? "met" : "NOT met", Median(fps),
      Median(drawn_per_s), Median(cpu_alone), Median(cpu_watched),
      1e6 * Median(cpu_alone) / Median(alone),
      1e6 * Median(cpu_watched) / Median(watched));
  stub.reset();
  channel.reset();
  (*server)->Shutdown(absl::Seconds(1));
  return 0;
}

}  // namespace
}  // namespace mll::service

int main(int argc, char** argv) {
  return mll::service::Run(mll::service::ParseFlags(argc, argv));
}

// The server's recent load as GetServerInfo reports it (ServerInfo.load):
// CPU used by the process and agent-steps per second over the last 10 s, and
// the cores the process may use. No thread of its own: calls that finish take
// a sample at most once a second (LoadMeter::Due is one relaxed load), and
// GetServerInfo takes one at the time of its answer, so the window is right
// however rarely it is asked.
#ifndef MLL_SERVICE_LOAD_METER_H_
#define MLL_SERVICE_LOAD_METER_H_

#include <array>
#include <atomic>
#include <cstdint>
#include <optional>
#include <string>

#include "absl/base/thread_annotations.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"

namespace mll::service {

class LoadMeter {
 public:
  // The window cpu_cores and agent_steps_per_s cover (the proto's 10 s).
  static constexpr int64_t kWindowNs = 10'000'000'000;
  // Samples are at least this far apart; kSamples of them span more than
  // the window, so one at or before its start is always kept.
  static constexpr int64_t kSampleEveryNs = 1'000'000'000;
  static constexpr int kSamples = 16;

  // Cumulative counters at a time on the steady clock.
  struct Reading {
    int64_t time_ns = 0;
    int64_t cpu_ns = 0;        // The process's user + system CPU time.
    uint64_t agent_steps = 0;  // Agent-steps served since the start.
  };
  struct Rates {
    double cpu_cores = 0;  // CPU time per wall time: 1.0 is one core busy.
    double agent_steps_per_s = 0;
  };

  // `start`: the counters when the server started (the window's earliest
  // possible beginning).
  explicit LoadMeter(Reading start);
  LoadMeter(const LoadMeter&) = delete;
  LoadMeter& operator=(const LoadMeter&) = delete;

  // Whether a sample is due at `now_ns` (a second since the last).
  bool Due(int64_t now_ns) const {
    return now_ns >= next_sample_ns_.load(std::memory_order_relaxed);
  }
  // Keeps `reading` unless another sample was kept less than a second before.
  void Add(const Reading& reading);
  // The rates over the 10 s before `now` (since the start, when sooner):
  // the counters at the window's start are interpolated between the samples
  // around it, so an idle gap without samples adds nothing to the window.
  Rates Over(const Reading& now) const;

 private:
  mutable absl::Mutex mu_;
  std::array<Reading, kSamples> ring_ ABSL_GUARDED_BY(mu_);
  int count_ ABSL_GUARDED_BY(mu_) = 0;  // Samples kept, at most kSamples.
  int next_ ABSL_GUARDED_BY(mu_) = 0;   // Where the next sample goes.
  std::atomic<int64_t> next_sample_ns_{0};
};

// The process's user + system CPU time so far (getrusage), in nanoseconds.
int64_t ProcessCpuNs();

// The CPU limit a cgroup v2 hierarchy mounted at `cgroup_root` (e.g.
// "/sys/fs/cgroup") puts on the cgroup named in `proc_self_cgroup` (the text
// of /proc/self/cgroup, whose "0::/path" line names it): the lowest
// quota / period of the cpu.max files from that cgroup up to the root, in
// cores; nullopt when none sets a quota ("max") or none can be read (cgroup
// v1, no cpu controller).
std::optional<double> CgroupCpuLimitCores(absl::string_view cgroup_root,
                                          absl::string_view proc_self_cgroup);

// Cores this process may use: the CPUs of its affinity mask
// (sched_getaffinity), lowered to its cgroup v2 CPU quota when that is lower
// (a container's CPU limit).
double CoresAvailable();

}  // namespace mll::service

#endif  // MLL_SERVICE_LOAD_METER_H_

#include "mll/service/load_meter.h"

#include <sched.h>
#include <sys/resource.h>

#include <algorithm>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"

namespace mll::service {
namespace {

// The counter a reading holds, as a double: `cpu` picks cpu_ns, else
// agent_steps.
double Counter(const LoadMeter::Reading& reading, bool cpu) {
  return cpu ? static_cast<double>(reading.cpu_ns)
             : static_cast<double>(reading.agent_steps);
}

// A cgroup's cpu.max ("QUOTA PERIOD", or "max PERIOD"): quota / period in
// cores, nullopt for "max" or an unreadable file.
std::optional<double> ReadCpuMax(const std::string& path) {
  std::ifstream file(path);
  std::string quota;
  std::string period;
  if (!(file >> quota >> period)) return std::nullopt;
  double quota_us = 0;
  double period_us = 0;
  if (quota == "max" || !absl::SimpleAtod(quota, &quota_us) ||
      !absl::SimpleAtod(period, &period_us) || quota_us <= 0 ||
      period_us <= 0) {
    return std::nullopt;
  }
  return quota_us / period_us;
}

std::string ReadFile(const char* path) {
  std::ifstream file(path);
  std::stringstream text;
  text << file.rdbuf();
  return text.str();
}

}  // namespace

LoadMeter::LoadMeter(Reading start) { Add(start); }

void LoadMeter::Add(const Reading& reading) {
  absl::MutexLock lock(&mu_);
  if (count_ > 0) {
    const Reading& last = ring_[(next_ + kSamples - 1) % kSamples];
    if (reading.time_ns < last.time_ns + kSampleEveryNs) return;
  }
  ring_[next_] = reading;
  next_ = (next_ + 1) % kSamples;
  count_ = std::min(count_ + 1, kSamples);
  next_sample_ns_.store(reading.time_ns + kSampleEveryNs,
                        std::memory_order_relaxed);
}

LoadMeter::Rates LoadMeter::Over(const Reading& now) const {
  absl::MutexLock lock(&mu_);
  // The kept samples oldest first, then `now`: increasing times.
  std::vector<Reading> samples;
  samples.reserve(count_ + 1);
  for (int i = 0; i < count_; ++i) {
    const Reading& sample = ring_[(next_ - count_ + i + kSamples) % kSamples];
    if (sample.time_ns < now.time_ns) samples.push_back(sample);
  }
  samples.push_back(now);
  const int64_t start_ns =
      std::max(now.time_ns - kWindowNs, samples.front().time_ns);
  const int64_t span_ns = now.time_ns - start_ns;
  if (span_ns <= 0) return Rates();
  // The last sample at or before the window's start and the one after it.
  size_t after = 1;
  while (after + 1 < samples.size() && samples[after].time_ns <= start_ns) {
    ++after;
  }
  const Reading& a = samples[after - 1];
  const Reading& b = samples[after];
  const double fraction =
      b.time_ns > a.time_ns
          ? static_cast<double>(start_ns - a.time_ns) / (b.time_ns - a.time_ns)
          : 1.0;
  auto rate = [&](bool cpu) {
    const double at_start =
        Counter(a, cpu) + (Counter(b, cpu) - Counter(a, cpu)) * fraction;
    return std::max(0.0, Counter(now, cpu) - at_start) / span_ns;
  };
  Rates rates;
  rates.cpu_cores = rate(true);
  rates.agent_steps_per_s = rate(false) * 1e9;
  return rates;
}

int64_t ProcessCpuNs() {
  rusage usage = {};
  getrusage(RUSAGE_SELF, &usage);
  return (int64_t{usage.ru_utime.tv_sec} + usage.ru_stime.tv_sec) *
             1'000'000'000 +
         (int64_t{usage.ru_utime.tv_usec} + usage.ru_stime.tv_usec) * 1'000;
}

std::optional<double> CgroupCpuLimitCores(absl::string_view cgroup_root,
                                          absl::string_view proc_self_cgroup) {
  std::optional<std::string> path;
  for (absl::string_view line : absl::StrSplit(proc_self_cgroup, '\n')) {
    if (absl::ConsumePrefix(&line, "0::")) path = std::string(line);
  }
  if (!path.has_value()) return std::nullopt;  // Not cgroup v2.
  std::optional<double> lowest;
  // From the process's cgroup up to the root: the lowest quota binds.
  std::string dir = *path;
  while (true) {
    while (!dir.empty() && dir.back() == '/') dir.pop_back();
    const std::optional<double> limit =
        ReadCpuMax(absl::StrCat(cgroup_root, dir, "/cpu.max"));
    if (limit.has_value()) lowest = std::min(lowest.value_or(*limit), *limit);
    if (dir.empty()) break;
    dir.resize(dir.rfind('/') == std::string::npos ? 0 : dir.rfind('/'));
  }
  return lowest;
}

double CoresAvailable() {
  cpu_set_t set;
  CPU_ZERO(&set);
  double cores = sched_getaffinity(0, sizeof(set), &set) == 0
                     ? CPU_COUNT(&set)
                     : std::thread::hardware_concurrency();
  const std::optional<double> quota =
      CgroupCpuLimitCores("/sys/fs/cgroup", ReadFile("/proc/self/cgroup"));
  if (quota.has_value()) cores = std::min(cores, *quota);
  return cores;
}

}  // namespace mll::service

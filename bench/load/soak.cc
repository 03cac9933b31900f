// mll_soak: many create/reset/step/delete cycles against one running
// mll_server, while sampling the server's resident memory (VmRSS) and open
// descriptors from /proc/<pid>. Passes when the mean RSS of the last tenth
// of the run is within --max_drift_percent of the first tenth's, the
// descriptor count did not grow, and no call failed. Bounded by --cycles and
// --time_limit_s.
//
//   mll_soak --address=127.0.0.1:PORT --server_pid=PID [--cycles=1000000]
//            [--clients=4] [--time_limit_s=3600]
// bench/load/run.sh soak starts the server and runs this against it.
#include <algorithm>
#include <atomic>
#include <cstdio>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/synchronization/notification.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "load_common.h"
#include "mll/client.h"

ABSL_FLAG(std::string, address, "", "host:port of a running mll_server");
ABSL_FLAG(int32_t, server_pid, 0, "the server's pid, for /proc/<pid>");
ABSL_FLAG(int64_t, cycles, 1000000, "create/reset/step/delete cycles in all");
ABSL_FLAG(int32_t, clients, 4, "concurrent clients (threads)");
ABSL_FLAG(double, time_limit_s, 3600, "the run stops after this long");
ABSL_FLAG(double, sample_ms, 200, "period of the RSS / fd samples");
ABSL_FLAG(double, max_drift_percent, 2,
          "allowed RSS drift, first to last tenth");
ABSL_FLAG(double, progress_s, 60,
          "period of the progress line on stderr (0: none)");

namespace mll::client::load {
namespace {

struct Sample {
  int64_t cycles;
  int64_t rss_kib;
  int fds;
};

int Main() {
  const std::string address = absl::GetFlag(FLAGS_address);
  const int pid = absl::GetFlag(FLAGS_server_pid);
  const int64_t cycles = absl::GetFlag(FLAGS_cycles);
  const int clients = absl::GetFlag(FLAGS_clients);
  if (address.empty() || pid <= 0 || ResidentKib(pid) < 0 || clients < 1 ||
      cycles < 10 * clients) {
    std::fprintf(stderr,
                 "mll_soak: need --address, a readable --server_pid, "
                 "--clients >= 1 and --cycles >= 10 * clients\n");
    return 2;
  }
  const absl::Time start = absl::Now();
  const absl::Time deadline =
      start + absl::Seconds(absl::GetFlag(FLAGS_time_limit_s));
  std::atomic<int64_t> done{0};
  std::atomic<int64_t> errors{0};

  std::vector<Sample> samples;
  absl::Notification stop;
  std::thread sampler([&] {
    const absl::Duration period =
        absl::Milliseconds(absl::GetFlag(FLAGS_sample_ms));
    // A run takes up to an hour: say where it is, so a slow machine shows
    // before the time limit does.
    const absl::Duration progress =
        absl::Seconds(absl::GetFlag(FLAGS_progress_s));
    absl::Time next_progress = start + progress;
    do {
      samples.push_back(
          {std::min(done.load(), cycles), ResidentKib(pid), OpenFds(pid)});
      if (progress > absl::ZeroDuration() && absl::Now() >= next_progress) {
        next_progress += progress;
        const Sample& s = samples.back();
        std::fprintf(stderr,
                     "mll_soak: %.0f s, %lld cycles, RSS %lld KiB, %d fds, "
                     "%lld errors\n",
                     absl::ToDoubleSeconds(absl::Now() - start),
                     static_cast<long long>(s.cycles),
                     static_cast<long long>(s.rss_kib), s.fds,
                     static_cast<long long>(errors.load()));
      }
    } while (!stop.WaitForNotificationWithTimeout(period));
    samples.push_back(
        {std::min(done.load(), cycles), ResidentKib(pid), OpenFds(pid)});
  });

  std::vector<std::thread> threads;
  for (int i = 0; i < clients; ++i) {
    threads.emplace_back([&, i] {
      absl::StatusOr<Client> client = ConnectClient(address, i);
      if (!client.ok()) {
        NoteError("connect", client.status());
        ++errors;
        return;
      }
      const int32_t actions[] = {2, 0, 3};
      // Claims cycles one at a time, so the total is exact.
      while (done.fetch_add(1) < cycles) {
        if (absl::Now() > deadline) {
          --done;
          break;
        }
        absl::StatusOr<RemoteEnv> env = client->CreateEnv();
        absl::Status status = env.status();
        if (status.ok()) status = env->Reset().status();
        if (status.ok())
          status = env->Step(Actions::Discrete(actions)).status();
        if (env.ok()) {
          const absl::Status deleted = env->Delete();
          if (status.ok()) status = deleted;
        }
        if (!status.ok()) {
          NoteError("cycle", status);
          ++errors;
        }
      }
    });
  }
  for (std::thread& thread : threads) thread.join();
  const int64_t total = std::min(done.load(), cycles);
  stop.Notify();
  sampler.join();
  const double seconds = absl::ToDoubleSeconds(absl::Now() - start);

  // Mean RSS and most descriptors over the samples of the first and the
  // last tenth of the cycles.
  double rss_first = 0, rss_last = 0;
  int n_first = 0, n_last = 0, fds_first = 0, fds_last = 0;
  for (const Sample& s : samples) {
    if (s.cycles <= total / 10) {
      rss_first += s.rss_kib;
      ++n_first;
      fds_first = std::max(fds_first, s.fds);
    }
    if (s.cycles >= total - total / 10) {
      rss_last += s.rss_kib;
      ++n_last;
      fds_last = std::max(fds_last, s.fds);
    }
  }
  rss_first /= std::max(n_first, 1);
  rss_last /= std::max(n_last, 1);
  const double drift = 100.0 * (rss_last - rss_first) / rss_first;
  int64_t peak = 0;
  for (const Sample& s : samples) peak = std::max(peak, s.rss_kib);

  std::printf(
      "mll_soak: %lld cycles (create, reset, step, delete) by %d "
      "clients in %.1f s (%.0f cycles/s), %lld errors\n",
      static_cast<long long>(total), clients, seconds, total / seconds,
      static_cast<long long>(errors.load()));
  std::printf(
      "RSS first tenth %.0f KiB (%d samples), last tenth %.0f KiB "
      "(%d samples): drift %+.2f%% (limit %.1f%%), peak %lld KiB\n",
      rss_first, n_first, rss_last, n_last, drift,
      absl::GetFlag(FLAGS_max_drift_percent), static_cast<long long>(peak));
  std::printf("open fds first tenth %d, last tenth %d\n", fds_first, fds_last);
  std::printf("%s", NotedErrors().c_str());
  bool ok = errors == 0;
  if (total < cycles) {
    std::printf("INCOMPLETE: %lld of %lld cycles before the time limit\n",
                static_cast<long long>(total), static_cast<long long>(cycles));
    ok = false;
  }
  if (n_first == 0 || n_last == 0 ||
      drift > absl::GetFlag(FLAGS_max_drift_percent)) {
    std::printf("FAIL: resident memory drift\n");
    ok = false;
  }
  if (fds_last > fds_first) {
    std::printf("FAIL: descriptors grew\n");
    ok = false;
  }
  return ok ? 0 : 1;
}

}  // namespace
}  // namespace mll::client::load

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "Soak test: create/reset/step/delete cycles against a running "
      "mll_server, checking its memory and descriptors.");
  absl::ParseCommandLine(argc, argv);
  return mll::client::load::Main();
}

// mll_load: concurrent clients against one running mll_server, each on its
// own channel (even clients, unary calls) or Session stream (odd clients),
// mixing create, reset, step, batch, render and delete for a fixed number of
// operations, bounded by a time limit too. Prints per-operation latency
// percentiles; exits 1 on any error or if the time limit cut the run short.
//
//   mll_load --address=127.0.0.1:PORT [--clients=64] [--operations=64000]
//            [--time_limit_s=600]
// bench/load/run.sh starts the server and runs this against it.
#include <algorithm>
#include <array>
#include <atomic>
#include <cstdio>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "load_common.h"
#include "mll/client.h"

ABSL_FLAG(std::string, address, "", "host:port of a running mll_server");
ABSL_FLAG(int32_t, clients, 64, "concurrent clients (threads)");
ABSL_FLAG(int64_t, operations, 64000, "operations in total, over all clients");
ABSL_FLAG(double, time_limit_s, 600, "the run stops after this long");
ABSL_FLAG(int32_t, server_pid, 0,
          "if set, the server's RSS and open fds are reported before/after");

namespace mll::client::load {
namespace {

enum Op { kCreate, kReset, kStep, kBatch, kRender, kDelete, kOps };
constexpr std::array<const char*, kOps> kOpNames = {
    "create", "reset", "step", "batch", "render", "delete"};
// Steps per env between its creation and deletion.
constexpr int kStepsPerEnv = 8;
constexpr int kBatchesPerEnv = 2;

struct ClientRun {
  std::array<Latencies, kOps> ops;
  int64_t done = 0;
};

// Times `call` (returning absl::Status or StatusOr) as one `op`.
template <typename Call>
bool Timed(ClientRun& run, Op op, Call&& call) {
  const absl::Time start = absl::Now();
  const auto result = call();
  const absl::Status status = [&] {
    if constexpr (std::is_same_v<std::decay_t<decltype(result)>,
                                 absl::Status>) {
      return result;
    } else {
      return result.status();
    }
  }();
  run.ops[op].micros.push_back(absl::ToDoubleMicroseconds(absl::Now() - start));
  ++run.done;
  if (!status.ok()) {
    ++run.ops[op].errors;
    NoteError(kOpNames[op], status);
  }
  return status.ok();
}

// Environments of 1..4 landers, a quarter of them rendering, discrete or
// continuous; auto_reset so that no step ever meets a finished episode.
RemoteEnvConfig ConfigFor(int client, int64_t cycle) {
  RemoteEnvConfig config;
  config.n_landers = 1 + (client + cycle) % 4;
  config.continuous = (client / 2 + cycle) % 3 == 0;
  config.render_rgb_array = (client + cycle) % 4 == 0;
  config.auto_reset = true;
  return config;
}

// Random actions valid for `env`, in `discrete` or `continuous`.
Actions RandomActions(const RemoteEnv& env, std::mt19937& random,
                      std::vector<int32_t>& discrete,
                      std::vector<float>& continuous) {
  if (env.continuous()) {
    std::uniform_real_distribution<float> value(-1.0f, 1.0f);
    continuous.resize(2 * env.n_landers());
    for (float& v : continuous) v = value(random);
    return Actions::Continuous(continuous);
  }
  std::uniform_int_distribution<int32_t> action(0, 3);
  discrete.resize(env.n_landers());
  for (int32_t& a : discrete) a = action(random);
  return Actions::Discrete(discrete);
}

void RunClient(const std::string& address, int index, int64_t quota,
               absl::Time deadline, ClientRun* run) {
  absl::StatusOr<Client> client = ConnectClient(address, index);
  if (!client.ok()) {
    NoteError("connect", client.status());
    ++run->ops[kCreate].errors;
    return;
  }
  std::mt19937 random(index);
  std::vector<int32_t> discrete, partner_discrete;
  std::vector<float> continuous, partner_continuous;
  // A long-lived second env that joins every batch.
  absl::StatusOr<RemoteEnv> partner = client->CreateEnv(ConfigFor(index, 1));
  if (!partner.ok() || !partner->Reset(index).ok()) {
    NoteError("partner", partner.status());
    ++run->ops[kCreate].errors;
    return;
  }
  for (int64_t cycle = 0; run->done < quota && absl::Now() < deadline;
       ++cycle) {
    absl::StatusOr<RemoteEnv> env;
    if (!Timed(*run, kCreate, [&] {
          env = client->CreateEnv(ConfigFor(index, cycle));
          return env.status();
        })) {
      continue;
    }
    Timed(*run, kReset, [&] { return env->Reset(cycle); });
    for (int s = 0; s < kStepsPerEnv && run->done < quota; ++s) {
      Timed(*run, kStep, [&] {
        return env->Step(RandomActions(*env, random, discrete, continuous));
      });
    }
    for (int b = 0; b < kBatchesPerEnv && run->done < quota; ++b) {
      const BatchStep steps[] = {
          {&*env, RandomActions(*env, random, discrete, continuous)},
          {&*partner, RandomActions(*partner, random, partner_discrete,
                                    partner_continuous)}};
      Timed(*run, kBatch, [&]() -> absl::Status {
        absl::StatusOr<std::vector<absl::StatusOr<StepData>>> results =
            client->StepBatch(steps);
        if (!results.ok()) return results.status();
        for (const absl::StatusOr<StepData>& item : *results) {
          if (!item.ok()) return item.status();
        }
        return absl::OkStatus();
      });
    }
    if (env->info().config.render_rgb_array) {
      Timed(*run, kRender, [&] { return env->Render(FrameFormat::kRgb); });
    }
    Timed(*run, kDelete, [&] { return env->Delete(); });
  }
}

int Main() {
  const std::string address = absl::GetFlag(FLAGS_address);
  const int clients = absl::GetFlag(FLAGS_clients);
  const int64_t operations = absl::GetFlag(FLAGS_operations);
  if (address.empty() || clients < 1 || operations < clients) {
    std::fprintf(stderr,
                 "mll_load: need --address, --clients >= 1 and "
                 "--operations >= --clients\n");
    return 2;
  }
  const int pid = absl::GetFlag(FLAGS_server_pid);
  const int64_t rss_before = pid > 0 ? ResidentKib(pid) : -1;
  const int fds_before = pid > 0 ? OpenFds(pid) : -1;
  const absl::Time start = absl::Now();
  const absl::Time deadline =
      start + absl::Seconds(absl::GetFlag(FLAGS_time_limit_s));
  std::vector<ClientRun> runs(clients);
  std::vector<std::thread> threads;
  for (int i = 0; i < clients; ++i) {
    const int64_t quota = operations / clients + (i < operations % clients);
    threads.emplace_back(RunClient, address, i, quota, deadline, &runs[i]);
  }
  for (std::thread& thread : threads) thread.join();
  const double seconds = absl::ToDoubleSeconds(absl::Now() - start);

  std::array<Latencies, kOps> all;
  int64_t done = 0, errors = 0;
  for (const ClientRun& run : runs) {
    done += run.done;
    for (int op = 0; op < kOps; ++op) all[op].Merge(run.ops[op]);
  }
  std::printf(
      "mll_load: %d clients (%d unary, %d session), %lld operations "
      "in %.1f s (%.0f ops/s)\n\n",
      clients, (clients + 1) / 2, clients / 2, static_cast<long long>(done),
      seconds, done / seconds);
  std::printf(
      "| operation | count | errors | p50 us | p90 us | p99 us | max us |\n"
      "|---|---|---|---|---|---|---|\n");
  for (int op = 0; op < kOps; ++op) {
    Latencies& l = all[op];
    errors += l.errors;
    std::printf("| %s | %zu | %lld | %.0f | %.0f | %.0f | %.0f |\n",
                kOpNames[op], l.micros.size(), static_cast<long long>(l.errors),
                l.Quantile(0.5), l.Quantile(0.9), l.Quantile(0.99),
                l.Quantile(1.0));
  }
  if (pid > 0) {
    std::printf("\nserver RSS %lld -> %lld KiB, open fds %d -> %d\n",
                static_cast<long long>(rss_before),
                static_cast<long long>(ResidentKib(pid)), fds_before,
                OpenFds(pid));
  }
  std::printf("\nerrors: %lld\n%s", static_cast<long long>(errors),
              NotedErrors().c_str());
  if (done < operations) {
    std::printf("INCOMPLETE: %lld of %lld operations before the time limit\n",
                static_cast<long long>(done),
                static_cast<long long>(operations));
  }
  return errors == 0 && done >= operations ? 0 : 1;
}

}  // namespace
}  // namespace mll::client::load

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "Load test: concurrent clients mixing create/reset/step/batch/render/"
      "delete against a running mll_server.");
  absl::ParseCommandLine(argc, argv);
  return mll::client::load::Main();
}

// The in-process floor of bench/python/bench_client.py: steps --envs
// environments of --n_landers landers with the core alone on --threads
// threads, with uniformly random actions, resetting an environment on the step
// after its episode ended (what the server's auto_reset does), and prints
// agent-steps per second as one JSON line. Bounded by --steps and --seconds.
//
// Each thread steps its share of the envs over and over. With --lockstep the
// threads wait for each other after every round, so every env is stepped once
// before any is stepped again, as a server's clients step them (each env
// once per call, its next step only after the answer); without it a thread
// that holds a core steps its share several times in a row, which on fewer
// cores than threads keeps that share in the core's cache.
//
// The client benchmark compares the Python vector env against this figure
// measured in the same run, on the same machine and load.
#include <algorithm>
#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <cstdio>
#include <memory>
#include <mutex>
#include <optional>
#include <random>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/status/status.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"

ABSL_FLAG(int, envs, 64, "Environments, >= 1.");
ABSL_FLAG(int, n_landers, 3, "Landers per environment, 1..32.");
ABSL_FLAG(int, threads, 2, "Worker threads; environments are split evenly.");
ABSL_FLAG(int, steps, 2000, "Steps per environment at most.");
ABSL_FLAG(double, seconds, 20.0, "Wall-time bound in seconds.");
ABSL_FLAG(uint64_t, seed, 0, "Env i is first reset with seed + i.");
ABSL_FLAG(bool, lockstep, false,
          "Threads wait for each other after every round: each env is stepped "
          "once before any is stepped again.");
ABSL_FLAG(
    bool, rotate, false,
    "With --lockstep: in round r thread t steps share (t + r) mod threads, "
    "so each env moves to another thread (and core) every round.");

namespace mll::core {
namespace {

using Clock = std::chrono::steady_clock;

struct Slot {
  std::unique_ptr<Env> env;
  StepResult result;
  std::vector<int32_t> actions;
};

// Where --lockstep's threads wait for each other after each round; a round
// goes on only if the first thread to arrive saw time left, so every thread
// stops after the same round.
class RoundBarrier {
 public:
  RoundBarrier(int threads, Clock::time_point deadline)
      : threads_(threads), deadline_(deadline) {}

  // Whether another round follows.
  bool Arrive() {
    std::unique_lock<std::mutex> lock(mu_);
    if (arrived_ == 0) go_on_ = Clock::now() < deadline_;
    const bool go_on = go_on_;
    if (++arrived_ == threads_) {
      arrived_ = 0;
      ++round_;
      all_arrived_.notify_all();
    } else {
      const uint64_t round = round_;
      all_arrived_.wait(lock, [&] { return round_ != round; });
    }
    return go_on;
  }

 private:
  const int threads_;
  const Clock::time_point deadline_;
  std::mutex mu_;
  std::condition_variable all_arrived_;
  int arrived_ = 0;
  uint64_t round_ = 0;
  bool go_on_ = true;
};

// Thread `thread` steps its share of `shards` (with `rotate`, share
// (thread + round) mod shards in each round) until `steps` or `deadline`
// (with `barrier`: until the barrier says stop); returns the agent-steps
// taken.
int64_t StepSlots(const std::vector<std::vector<Slot*>>& shards, int thread,
                  bool rotate, int steps, Clock::time_point deadline,
                  uint64_t seed, RoundBarrier* barrier) {
  std::mt19937_64 rng(seed);
  int64_t agent_steps = 0;
  const int count = static_cast<int>(shards.size());
  for (int step = 0;
       step < steps && (barrier != nullptr || Clock::now() < deadline);
       ++step) {
    if (barrier != nullptr && step > 0 && !barrier->Arrive()) break;
    const int shard = rotate ? (thread + step) % count : thread;
    for (Slot* slot : shards[shard]) {
      if (slot->env->episode_over()) {
        slot->env->Reset(std::nullopt, &slot->result);
        continue;
      }
      for (int32_t& action : slot->actions) {
        action = static_cast<int32_t>(rng() % kDiscreteActionCount);
      }
      ActionsView view;
      view.discrete = slot->actions;
      absl::Status status = slot->env->Step(view, &slot->result);
      if (!status.ok()) {
        std::fprintf(stderr, "step failed: %s\n", status.ToString().c_str());
        std::exit(1);
      }
      agent_steps += std::count(slot->result.stepped.begin(),
                                slot->result.stepped.end(), 1);
    }
  }
  return agent_steps;
}

int Run() {
  const int envs = absl::GetFlag(FLAGS_envs);
  const int threads = std::max(1, absl::GetFlag(FLAGS_threads));
  EnvConfig config;
  config.n_landers = absl::GetFlag(FLAGS_n_landers);
  std::vector<Slot> slots(std::max(envs, 0));
  for (int i = 0; i < envs; ++i) {
    absl::StatusOr<std::unique_ptr<Env>> env = Env::Create(config);
    if (!env.ok()) {
      std::fprintf(stderr, "%s\n", env.status().ToString().c_str());
      return 2;
    }
    slots[i].env = *std::move(env);
    slots[i].actions.assign(config.n_landers, 0);
    slots[i].env->Reset(absl::GetFlag(FLAGS_seed) + i, &slots[i].result);
  }
  std::vector<std::vector<Slot*>> shards(threads);
  for (int i = 0; i < envs; ++i) shards[i % threads].push_back(&slots[i]);

  const auto start = Clock::now();
  const auto deadline =
      start + std::chrono::duration_cast<Clock::duration>(
                  std::chrono::duration<double>(absl::GetFlag(FLAGS_seconds)));
  std::vector<int64_t> counts(threads, 0);
  std::optional<RoundBarrier> barrier;
  if (absl::GetFlag(FLAGS_lockstep)) barrier.emplace(threads, deadline);
  const bool rotate = absl::GetFlag(FLAGS_rotate);
  if (rotate && !barrier.has_value()) {
    std::fprintf(stderr, "--rotate needs --lockstep\n");
    return 2;
  }
  std::vector<std::thread> workers;
  for (int t = 0; t < threads; ++t) {
    workers.emplace_back([&, t] {
      counts[t] = StepSlots(shards, t, rotate, absl::GetFlag(FLAGS_steps),
                            deadline, absl::GetFlag(FLAGS_seed) + 1000 + t,
                            barrier.has_value() ? &*barrier : nullptr);
    });
  }
  for (std::thread& worker : workers) worker.join();
  const double seconds =
      std::chrono::duration<double>(Clock::now() - start).count();
  int64_t agent_steps = 0;
  for (int64_t count : counts) agent_steps += count;
  std::printf(
      "{\"envs\": %d, \"n_landers\": %d, \"threads\": %d, \"lockstep\": %s, "
      "\"rotate\": %s, \"agent_steps\": "
      "%lld, "
      "\"seconds\": %.6f, \"agent_steps_per_s\": %.1f}\n",
      envs, config.n_landers, threads,
      absl::GetFlag(FLAGS_lockstep) ? "true" : "false",
      rotate ? "true" : "false", static_cast<long long>(agent_steps), seconds,
      agent_steps / seconds);
  return 0;
}

}  // namespace
}  // namespace mll::core

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  return mll::core::Run();
}

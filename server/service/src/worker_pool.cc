#include "mll/service/worker_pool.h"

#include <sched.h>

#include <algorithm>
#include <atomic>
#include <memory>
#include <utility>

#include "absl/container/inlined_vector.h"

namespace mll::service {
namespace {

// The cores this process may run on (its affinity mask, e.g. from taskset or
// a container's cpuset), at least 1.
int AllowedCores() {
  cpu_set_t set;
  CPU_ZERO(&set);
  if (sched_getaffinity(0, sizeof(set), &set) != 0) {
    return std::max(1, static_cast<int>(std::thread::hardware_concurrency()));
  }
  return std::max(1, CPU_COUNT(&set));
}

}  // namespace

// Runner 0 of a batch is the calling thread, so `threads` runners need one
// worker fewer.
WorkerPool::WorkerPool(int threads, int cores)
    : queues_(std::max(threads, 1) - 1),
      cores_(cores > 0 ? cores : AllowedCores()) {
  const int count = static_cast<int>(queues_.size());
  workers_.reserve(count);
  for (int w = 0; w < count; ++w) {
    workers_.emplace_back([this, w] { Run(w); });
  }
}

WorkerPool::~WorkerPool() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
  }
  for (WorkerQueue& queue : queues_) queue.wake.Signal();
  for (std::thread& worker : workers_) worker.join();
}

void WorkerPool::Run(int worker) {
  WorkerQueue& queue = queues_[worker];
  for (;;) {
    std::function<void()> task;
    {
      absl::MutexLock lock(&mu_);
      queue.running = false;
      // Sleeps (no CPU) until there is work or the pool stops.
      while (queue.tasks.empty() && !stopping_) queue.wake.Wait(&mu_);
      if (queue.tasks.empty()) return;  // Stopping, and the queue is drained.
      task = std::move(queue.tasks.front());
      queue.tasks.pop_front();
      queue.running = true;
    }
    task();
  }
}

void WorkerPool::ParallelFor(int count, std::function<void(int)> body,
                             std::function<void()> done, int min_per_runner) {
  if (count <= 0) {
    done();
    return;
  }
  // Runner r owns share r = [r * count / runners, (r + 1) * count / runners)
  // and pulls its next index from that share's counter; when its share is
  // used up it pulls from the other shares' counters, so a slow item or a
  // preempted worker does not hold back the batch.
  //
  // The runners are the caller and workers that are idle now (nothing queued
  // or running): a busy worker would start its share only once its other
  // batches are done, by when the caller and the idle workers have taken it,
  // so waking it would only cost a wake-up. And with B batches in flight
  // (their callers run too) a batch takes about threads / B runners, not
  // every thread: the cores are shared out by batches instead of every batch
  // being split T ways, each share paying a wake-up. So the wake-ups per
  // batch, and the CPU per item, stay flat as --threads grows under many
  // concurrent calls, while a lone batch still gets every thread.
  // Nor more runners than the cores this process may run on: with more,
  // they would take turns on the cores, not step the batch any sooner; nor
  // than shares of at least `min_per_runner` items: a smaller share is not
  // worth the hand-off.
  const int in_flight = in_flight_.fetch_add(1) + 1;
  const int parallel = std::min(threads(), cores_);
  const int most_runners =
      std::max(1, std::min({count / std::max(1, min_per_runner),
                            (parallel + in_flight - 1) / in_flight}));
  struct Shared {
    std::function<void(int)> body;
    std::function<void()> done;
    std::vector<int> share_end;
    std::unique_ptr<std::atomic<int>[]> share_next;
    int runners = 0;
    // Items not yet run to the end. The runner that runs the last one calls
    // done(), so the batch never waits for a woken worker that has not got a
    // core yet: the caller and the others take its share, and the worker,
    // when it runs, finds nothing left and goes back to sleep.
    std::atomic<int> remaining{0};
  };
  auto shared = std::make_shared<Shared>();
  shared->body = std::move(body);
  shared->done = std::move(done);
  shared->share_next = std::make_unique<std::atomic<int>[]>(most_runners);
  shared->share_end.reserve(most_runners);
  shared->remaining = count;
  auto run_share = [this, shared](int r) {
    const int runners = shared->runners;
    int ran = 0;
    for (int k = 0; k < runners; ++k) {
      const int share = (r + k) % runners;
      std::atomic<int>& next = shared->share_next[share];
      for (int i = next.fetch_add(1); i < shared->share_end[share];
           i = next.fetch_add(1)) {
        shared->body(i);
        ++ran;
      }
    }
    if (ran > 0 && shared->remaining.fetch_sub(ran) == ran) {
      // Before done(): the caller's next batch must not count this one.
      in_flight_.fetch_sub(1);
      shared->done();
    }
  };
  // The workers woken, runner r >= 1 being woken[r - 1].
  absl::InlinedVector<WorkerQueue*, 16> woken;
  {
    absl::MutexLock lock(&mu_);
    for (WorkerQueue& queue : queues_) {
      if (static_cast<int>(woken.size()) + 1 >= most_runners) break;
      if (queue.tasks.empty() && !queue.running) woken.push_back(&queue);
    }
    // Set before any task is queued: a worker may run its task as soon as
    // the lock is released.
    const int runners = static_cast<int>(woken.size()) + 1;
    for (int r = 0; r < runners; ++r) {
      shared->share_next[r] = static_cast<int>(int64_t{r} * count / runners);
      shared->share_end.push_back(
          static_cast<int>(int64_t{r + 1} * count / runners));
    }
    shared->runners = runners;
    for (int r = 1; r < runners; ++r) {
      woken[r - 1]->tasks.push_back([run_share, r] { run_share(r); });
    }
  }
  // Each worker is woken by this thread directly, after the lock is released
  // (not one after another through the mutex's waiter queue).
  for (WorkerQueue* queue : woken) queue->wake.Signal();
  run_share(0);
}

}  // namespace mll::service

#include "mll/service/worker_pool.h"

#include <algorithm>
#include <atomic>
#include <memory>
#include <utility>

namespace mll::service {

// Runner 0 of a batch is the calling thread, so `threads` runners need one
// worker fewer.
WorkerPool::WorkerPool(int threads) : queues_(std::max(threads, 1) - 1) {
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
      // Sleeps (no CPU) until there is work or the pool stops.
      while (queue.tasks.empty() && !stopping_) queue.wake.Wait(&mu_);
      if (queue.tasks.empty()) return;  // Stopping, and the queue is drained.
      task = std::move(queue.tasks.front());
      queue.tasks.pop_front();
    }
    task();
  }
}

void WorkerPool::ParallelFor(int count, std::function<void(int)> body,
                             std::function<void()> done) {
  if (count <= 0) {
    done();
    return;
  }
  // Runner r owns share r = [r * count / runners, (r + 1) * count / runners)
  // and pulls its next index from that share's counter; when its share is
  // used up it pulls from the other shares' counters, so a slow item or a
  // preempted worker does not hold back the batch.
  const int runners = std::min(count, threads());
  struct Shared {
    std::function<void(int)> body;
    std::function<void()> done;
    std::vector<int> share_end;
    std::unique_ptr<std::atomic<int>[]> share_next;
    std::atomic<int> running{0};
  };
  auto shared = std::make_shared<Shared>();
  shared->body = std::move(body);
  shared->done = std::move(done);
  shared->share_next = std::make_unique<std::atomic<int>[]>(runners);
  for (int r = 0; r < runners; ++r) {
    shared->share_next[r] = static_cast<int>(int64_t{r} * count / runners);
    shared->share_end.push_back(
        static_cast<int>(int64_t{r + 1} * count / runners));
  }
  shared->running = runners;
  auto run_share = [shared, runners](int r) {
    for (int k = 0; k < runners; ++k) {
      const int share = (r + k) % runners;
      std::atomic<int>& next = shared->share_next[share];
      for (int i = next.fetch_add(1); i < shared->share_end[share];
           i = next.fetch_add(1)) {
        shared->body(i);
      }
    }
    if (shared->running.fetch_sub(1) == 1) shared->done();
  };
  // Runner r >= 1 is worker r - 1.
  {
    absl::MutexLock lock(&mu_);
    for (int r = 1; r < runners; ++r) {
      queues_[r - 1].tasks.push_back([run_share, r] { run_share(r); });
    }
  }
  // Each worker is woken by this thread directly, after the lock is released
  // (not one after another through the mutex's waiter queue).
  for (int r = 1; r < runners; ++r) queues_[r - 1].wake.Signal();
  run_share(0);
}

}  // namespace mll::service

#include "mll/service/worker_pool.h"

#include <algorithm>
#include <atomic>
#include <memory>
#include <utility>

namespace mll {

WorkerPool::WorkerPool(int threads) {
  const int count = std::max(threads, 1);
  {
    absl::MutexLock lock(&mu_);
    own_tasks_.resize(count);
  }
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
  for (std::thread& worker : workers_) worker.join();
}

void WorkerPool::Post(std::function<void()> task) {
  absl::MutexLock lock(&mu_);
  tasks_.push_back(std::move(task));
}

void WorkerPool::PostTo(int worker, std::function<void()> task) {
  absl::MutexLock lock(&mu_);
  own_tasks_[worker].push_back(std::move(task));
}

void WorkerPool::Run(int worker) {
  const auto has_work_or_stopping = [this, worker]()
                                        ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_) {
                                          return stopping_ || !tasks_.empty() ||
                                                 !own_tasks_[worker].empty();
                                        };
  for (;;) {
    std::function<void()> task;
    {
      absl::MutexLock lock(&mu_);
      // Sleeps (no CPU) until there is work or the pool stops.
      mu_.Await(absl::Condition(&has_work_or_stopping));
      std::deque<std::function<void()>>& own = own_tasks_[worker];
      std::deque<std::function<void()>>& queue = own.empty() ? tasks_ : own;
      if (queue.empty()) return;  // Stopping, and the queues are drained.
      task = std::move(queue.front());
      queue.pop_front();
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
  for (int r = 0; r < runners; ++r) {
    PostTo(r, [shared, r, runners] {
      for (int k = 0; k < runners; ++k) {
        const int share = (r + k) % runners;
        std::atomic<int>& next = shared->share_next[share];
        for (int i = next.fetch_add(1); i < shared->share_end[share];
             i = next.fetch_add(1)) {
          shared->body(i);
        }
      }
      if (shared->running.fetch_sub(1) == 1) shared->done();
    });
  }
}

}  // namespace mll

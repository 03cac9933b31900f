#include "mll/service/worker_pool.h"

#include <algorithm>
#include <atomic>
#include <memory>
#include <utility>

namespace mll {

WorkerPool::WorkerPool(int threads) {
  workers_.reserve(std::max(threads, 1));
  for (int i = 0; i < std::max(threads, 1); ++i) {
    workers_.emplace_back([this] { Run(); });
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

void WorkerPool::Run() {
  for (;;) {
    std::function<void()> task;
    {
      absl::MutexLock lock(&mu_);
      // Sleeps (no CPU) until there is work or the pool stops.
      mu_.Await(absl::Condition(
          +[](WorkerPool* pool) ABSL_EXCLUSIVE_LOCKS_REQUIRED(pool->mu_) {
            return pool->stopping_ || !pool->tasks_.empty();
          },
          this));
      if (tasks_.empty()) return;  // Stopping, and the queue is drained.
      task = std::move(tasks_.front());
      tasks_.pop_front();
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
  // Each runner pulls the next index, so a slow item does not hold back the
  // items behind it on the same runner.
  struct Shared {
    std::function<void(int)> body;
    std::function<void()> done;
    int count;
    std::atomic<int> next{0};
    std::atomic<int> running{0};
  };
  auto shared = std::make_shared<Shared>();
  shared->body = std::move(body);
  shared->done = std::move(done);
  shared->count = count;
  const int runners = std::min(count, threads());
  shared->running = runners;
  for (int r = 0; r < runners; ++r) {
    Post([shared] {
      for (int i = shared->next.fetch_add(1); i < shared->count;
           i = shared->next.fetch_add(1)) {
        shared->body(i);
      }
      if (shared->running.fetch_sub(1) == 1) shared->done();
    });
  }
}

}  // namespace mll

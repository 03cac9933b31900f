// A fixed pool of worker threads (sized by --threads) that runs the
// environment steps of StepBatch, so that a batch uses every core without the
// gRPC threads ever waiting for it.
#ifndef MLL_SERVICE_WORKER_POOL_H_
#define MLL_SERVICE_WORKER_POOL_H_

#include <deque>
#include <functional>
#include <thread>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/synchronization/mutex.h"

namespace mll::service {

class WorkerPool {
 public:
  // Starts `threads` (>= 1) workers.
  explicit WorkerPool(int threads);
  // Runs every task already posted, then joins the workers.
  ~WorkerPool();
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  int threads() const { return static_cast<int>(workers_.size()); }

  // Calls body(i) for i in [0, count) spread over the workers, then calls
  // done() on the worker that finished last. Returns at once: the caller
  // (often a gRPC reaction) never waits. count == 0 calls done() at once.
  // Worker w starts on the w-th contiguous share of [0, count), so with the
  // same count an index goes to the same worker batch after batch (its
  // environment stays warm in that core's cache); a worker that finishes its
  // share early takes the remaining indices of the others' shares.
  void ParallelFor(int count, std::function<void(int)> body,
                   std::function<void()> done);

 private:
  // One worker's queue and the condition it sleeps on.
  struct WorkerQueue {
    absl::CondVar wake;
    std::deque<std::function<void()>> tasks;
  };

  void Run(int worker);

  absl::Mutex mu_;
  // Worker w takes tasks from queues_[w] only (guarded by mu_).
  std::vector<WorkerQueue> queues_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::vector<std::thread> workers_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_WORKER_POOL_H_

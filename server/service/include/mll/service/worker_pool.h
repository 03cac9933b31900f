// The threads that run the environment steps of StepBatch (--threads of
// them): the thread that handles the call, which is awake anyway, and a fixed
// pool of --threads - 1 workers, so that a batch uses every core and wakes one
// thread fewer than it runs on.
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
  // Batches run on `threads` (>= 1) threads: the caller's and `threads` - 1
  // workers started here.
  explicit WorkerPool(int threads);
  // Runs every task already posted, then joins the workers.
  ~WorkerPool();
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  int threads() const { return static_cast<int>(workers_.size()) + 1; }

  // Calls body(i) for i in [0, count) spread over the calling thread and the
  // workers, then calls done() on the thread that finished last (possibly the
  // caller, before this returns). Returns once the caller has no index left
  // to run; the workers may still be running theirs. count == 0 calls done()
  // at once. Runner r (the caller for r = 0, else worker r - 1) starts on the
  // r-th contiguous share of [0, count), so with the same count an index goes
  // to the same thread batch after batch (its environment stays warm in that
  // core's cache); a runner that finishes its share early takes the remaining
  // indices of the others' shares.
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

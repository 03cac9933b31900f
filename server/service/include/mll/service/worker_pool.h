// The threads that run the environment steps of StepBatch (--threads of
// them): the thread that handles the call, which is awake anyway, and a fixed
// pool of --threads - 1 workers, so that a lone batch uses every core and wakes
// one thread fewer than it runs on.
#ifndef MLL_SERVICE_WORKER_POOL_H_
#define MLL_SERVICE_WORKER_POOL_H_

#include <atomic>
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
  // workers started here. `cores`: how many of them can run at once (0: the
  // cores in the process's affinity mask now).
  explicit WorkerPool(int threads, int cores = 0);
  // Runs every task already posted, then joins the workers.
  ~WorkerPool();
  WorkerPool(const WorkerPool&) = delete;
  WorkerPool& operator=(const WorkerPool&) = delete;

  int threads() const { return static_cast<int>(workers_.size()) + 1; }

  // Calls body(i) for i in [0, count) spread over the calling thread and the
  // workers that are idle now (none queued or running a task), then calls
  // done() on the thread that ran the last index to finish (possibly the
  // caller, before this returns). Returns once the caller has no index left
  // to run; the workers may still be running theirs. A woken worker that has
  // not started when the others have taken every index runs none (the batch
  // does not wait for it). count == 0 calls done() at once. Runner r
  // (the caller for r = 0, else the r-th idle worker) starts on the r-th
  // contiguous share of [0, count), so on an otherwise idle pool an index
  // goes to the same thread batch after batch (its environment stays warm in
  // that core's cache); a runner that finishes its share early takes the
  // remaining indices of the others' shares. While other batches keep the
  // workers busy, a batch is not split over them: it would only wake them;
  // with B batches in flight, each takes at most ceil(P / B) runners, P
  // being the lesser of threads() and the cores the process may run on; and
  // a runner gets at least `min_per_runner` indices (fewer runners, not
  // smaller shares), so a small batch is not split into pieces whose work
  // does not pay for waking a thread.
  void ParallelFor(int count, std::function<void(int)> body,
                   std::function<void()> done, int min_per_runner = 1);

 private:
  // One worker's queue, the condition it sleeps on, and whether it is
  // running a task (guarded by mu_).
  struct WorkerQueue {
    absl::CondVar wake;
    std::deque<std::function<void()>> tasks;
    bool running = false;
  };

  void Run(int worker);

  absl::Mutex mu_;
  // Worker w takes tasks from queues_[w] only (guarded by mu_).
  std::vector<WorkerQueue> queues_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  // The cores the process may run on when the pool was made.
  const int cores_;
  // Batches whose done() has not run yet.
  std::atomic<int> in_flight_{0};
  std::vector<std::thread> workers_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_WORKER_POOL_H_

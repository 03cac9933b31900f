// WorkerPool::ParallelFor: every index runs exactly once, done() runs once
// after all of them, the calling thread runs the first share, shares are
// contiguous per runner, a busy worker is not woken, a batch is not split
// below its least share, a batch does not wait for a worker that has not
// begun, and concurrent batches do not mix.
#include "mll/service/worker_pool.h"

#include <atomic>
#include <chrono>
#include <functional>
#include <set>
#include <thread>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "absl/synchronization/notification.h"
#include "gtest/gtest.h"

namespace mll::service {
namespace {

// Runs one ParallelFor and waits for its done().
void RunAndWait(WorkerPool& pool, int count,
                const std::function<void(int)>& body, int min_per_runner = 1) {
  absl::Notification finished;
  std::atomic<int> done_calls{0};
  pool.ParallelFor(
      count, body,
      [&] {
        ++done_calls;
        finished.Notify();
      },
      min_per_runner);
  finished.WaitForNotification();
  EXPECT_EQ(done_calls.load(), 1);
}

TEST(WorkerPoolTest, EveryIndexRunsExactlyOnceBeforeDone) {
  for (int threads : {1, 2, 3, 5}) {
    WorkerPool pool(threads, /*cores=*/threads);
    for (int count : {0, 1, 2, 3, 7, 64, 1000}) {
      std::vector<std::atomic<int>> runs(count);
      RunAndWait(pool, count, [&](int i) { ++runs[i]; });
      for (int i = 0; i < count; ++i) {
        EXPECT_EQ(runs[i].load(), 1)
            << "index " << i << " of " << count << " on " << threads;
      }
    }
  }
}

TEST(WorkerPoolTest, TheCallingThreadRunsTheFirstShare) {
  WorkerPool pool(2, /*cores=*/2);
  const std::thread::id caller = std::this_thread::get_id();
  std::vector<std::thread::id> ran_on(64);
  // The worker's share [32, 64) waits until the caller has run an index, so
  // a worker that is scheduled first cannot finish its share and take index
  // 0 before the caller begins; the caller's first index is then index 0.
  std::atomic<bool> caller_began{false};
  RunAndWait(pool, 64, [&](int i) {
    ran_on[i] = std::this_thread::get_id();
    if (ran_on[i] == caller) caller_began = true;
    const auto give_up =
        std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (i >= 32 && !caller_began &&
           std::chrono::steady_clock::now() < give_up) {
      std::this_thread::yield();
    }
  });
  EXPECT_EQ(ran_on[0], caller);
}

TEST(WorkerPoolTest, OneThreadRunsTheBatchOnTheCallerBeforeReturning) {
  WorkerPool pool(1, /*cores=*/1);
  const std::thread::id caller = std::this_thread::get_id();
  std::vector<std::thread::id> ran_on(5);
  bool done = false;
  pool.ParallelFor(
      5, [&](int i) { ran_on[i] = std::this_thread::get_id(); },
      [&] { done = true; });
  EXPECT_TRUE(done);
  for (const std::thread::id& id : ran_on) EXPECT_EQ(id, caller);
}

TEST(WorkerPoolTest, AWorkerStartsOnItsOwnContiguousShare) {
  WorkerPool pool(2, /*cores=*/2);
  // Every index of share 0 = [0, 32) waits until share 1 = [32, 64) has
  // begun. With contiguous shares the second worker begins at index 32 at
  // once; were both workers to start from the front, they would both wait
  // inside share 0 and time out.
  std::atomic<bool> share_one_begun{false};
  std::atomic<int> timed_out{0};
  RunAndWait(pool, 64, [&](int i) {
    if (i >= 32) {
      share_one_begun = true;
      return;
    }
    const auto give_up =
        std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (!share_one_begun && std::chrono::steady_clock::now() < give_up) {
      std::this_thread::yield();
    }
    if (!share_one_begun) ++timed_out;
  });
  EXPECT_EQ(timed_out.load(), 0);
}

TEST(WorkerPoolTest, ASlowShareIsFinishedByTheOtherWorker) {
  WorkerPool pool(2, /*cores=*/2);
  std::vector<std::atomic<int>> runs(64);
  std::atomic<int> others_done{0};
  std::atomic<bool> index_zero_saw_all_others{false};
  RunAndWait(pool, 64, [&](int i) {
    if (i == 0) {
      // Share 0's first item holds its worker until the 63 other items ran,
      // which needs the second worker to take share 0's items 1..31 too.
      const auto give_up =
          std::chrono::steady_clock::now() + std::chrono::seconds(10);
      while (others_done < 63 && std::chrono::steady_clock::now() < give_up) {
        std::this_thread::yield();
      }
      index_zero_saw_all_others = others_done == 63;
    } else {
      ++others_done;
    }
    ++runs[i];
  });
  EXPECT_TRUE(index_zero_saw_all_others);
  for (int i = 0; i < 64; ++i) EXPECT_EQ(runs[i].load(), 1) << i;
}

// A worker busy with another batch is not handed a share (it could start it
// only after that batch, and would only be woken for nothing): the batch runs
// on its caller and the idle workers.
TEST(WorkerPoolTest, ABusyWorkerIsNotWoken) {
  WorkerPool pool(2, /*cores=*/2);
  std::atomic<bool> worker_busy{false};
  absl::Notification release;
  std::thread first([&] {
    const std::thread::id caller = std::this_thread::get_id();
    RunAndWait(pool, 2, [&](int i) {
      const auto give_up =
          std::chrono::steady_clock::now() + std::chrono::seconds(10);
      if (std::this_thread::get_id() != caller) {
        worker_busy = true;
        release.WaitForNotificationWithTimeout(absl::Seconds(10));
      } else if (i == 0) {
        // Leaves index 1 to the worker.
        while (!worker_busy && std::chrono::steady_clock::now() < give_up) {
          std::this_thread::yield();
        }
      }
    });
  });
  const auto give_up =
      std::chrono::steady_clock::now() + std::chrono::seconds(10);
  while (!worker_busy && std::chrono::steady_clock::now() < give_up) {
    std::this_thread::yield();
  }
  ASSERT_TRUE(worker_busy);
  const std::thread::id caller = std::this_thread::get_id();
  std::vector<std::thread::id> ran_on(64);
  RunAndWait(pool, 64, [&](int i) { ran_on[i] = std::this_thread::get_id(); });
  for (int i = 0; i < 64; ++i) EXPECT_EQ(ran_on[i], caller) << i;
  release.Notify();
  first.join();
}

// More threads than cores: a batch is split over as many runners as there
// are cores (here 1: the caller alone), not over every thread.
TEST(WorkerPoolTest, ABatchTakesNoMoreRunnersThanCores) {
  WorkerPool pool(8, /*cores=*/1);
  const std::thread::id caller = std::this_thread::get_id();
  std::vector<std::thread::id> ran_on(64);
  RunAndWait(pool, 64, [&](int i) { ran_on[i] = std::this_thread::get_id(); });
  for (int i = 0; i < 64; ++i) EXPECT_EQ(ran_on[i], caller) << i;
}

// A runner gets at least min_per_runner indices: a batch of 8 with at least
// 8 per runner is the caller's alone, one with at least 4 per runner is split
// in two at most.
TEST(WorkerPoolTest, ABatchIsNotSplitBelowTheLeastPerRunner) {
  WorkerPool pool(4, /*cores=*/4);
  const std::thread::id caller = std::this_thread::get_id();
  std::vector<std::thread::id> ran_on(8);
  absl::Notification finished;
  pool.ParallelFor(
      8, [&](int i) { ran_on[i] = std::this_thread::get_id(); },
      [&] { finished.Notify(); }, /*min_per_runner=*/8);
  // The caller alone: done() ran before ParallelFor returned.
  EXPECT_TRUE(finished.HasBeenNotified());
  for (int i = 0; i < 8; ++i) EXPECT_EQ(ran_on[i], caller) << i;

  absl::Mutex mu;
  std::set<std::thread::id> runners;
  RunAndWait(
      pool, 8,
      [&](int) {
        absl::MutexLock lock(&mu);
        runners.insert(std::this_thread::get_id());
      },
      /*min_per_runner=*/4);
  EXPECT_LE(runners.size(), 2u);
}

// The batch is done when its last index is: when the caller has run every
// index (the worker it woke had not begun), done() has run before
// ParallelFor returns, not later on that worker. Each batch's index 1 is the
// worker's share and index 0 takes no time, so the caller usually takes
// index 1 too before the woken worker gets to it.
TEST(WorkerPoolTest, TheBatchDoesNotWaitForAWorkerThatHasNotBegun) {
  WorkerPool pool(2, /*cores=*/2);
  const std::thread::id caller = std::this_thread::get_id();
  int caller_ran_all = 0;
  for (int batch = 0; batch < 2000 && caller_ran_all < 20; ++batch) {
    std::atomic<int> on_caller{0};
    absl::Notification finished;
    pool.ParallelFor(
        2,
        [&](int) {
          if (std::this_thread::get_id() == caller) ++on_caller;
        },
        [&] { finished.Notify(); });
    if (on_caller == 2) {
      ++caller_ran_all;
      EXPECT_TRUE(finished.HasBeenNotified()) << "batch " << batch;
    }
    finished.WaitForNotification();
  }
  EXPECT_GT(caller_ran_all, 0);
}

TEST(WorkerPoolTest, ConcurrentBatchesEachRunTheirOwnIndices) {
  WorkerPool pool(2, /*cores=*/2);
  constexpr int kCallers = 4;
  constexpr int kCount = 100;
  std::vector<std::vector<std::atomic<int>>> runs(kCallers);
  for (auto& r : runs) r = std::vector<std::atomic<int>>(kCount);
  std::vector<std::thread> callers;
  for (int c = 0; c < kCallers; ++c) {
    callers.emplace_back([&, c] {
      for (int round = 0; round < 50; ++round) {
        RunAndWait(pool, kCount, [&](int i) { ++runs[c][i]; });
      }
    });
  }
  for (std::thread& caller : callers) caller.join();
  for (int c = 0; c < kCallers; ++c) {
    for (int i = 0; i < kCount; ++i) EXPECT_EQ(runs[c][i].load(), 50);
  }
}

}  // namespace
}  // namespace mll::service

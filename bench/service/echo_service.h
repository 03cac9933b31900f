// The bench-only echo service (echo.proto): the transport floor that the
// service's costs are compared with. Stream answers each request with its
// response_size bytes; with work_us set, each answer first spins for that
// long, so that the answers come at the rate and on the busy threads a server
// stepping environments would have; the CPU the spins took is counted
// (work_cpu_ns), so that what the transport took can be told from it.
#ifndef MLL_BENCH_SERVICE_ECHO_SERVICE_H_
#define MLL_BENCH_SERVICE_ECHO_SERVICE_H_

#include <time.h>

#include <atomic>
#include <cstdint>

#include "echo.grpc.pb.h"
#include "grpcpp/grpcpp.h"

namespace mll::bench {

// Nanoseconds on `clock` (CLOCK_MONOTONIC is read in user space, through
// the vDSO; a thread's CPU clock takes a system call).
inline int64_t ClockNs(clockid_t clock) {
  timespec now{};
  clock_gettime(clock, &now);
  return int64_t{now.tv_sec} * 1'000'000'000 + now.tv_nsec;
}

// Spins in user space for `us` microseconds of wall time: the CPU a request's
// work would take (less when the thread is preempted meanwhile).
inline void SpinFor(int64_t us) {
  if (us <= 0) return;
  const int64_t until = ClockNs(CLOCK_MONOTONIC) + us * 1000;
  while (ClockNs(CLOCK_MONOTONIC) < until) {
  }
}

class EchoService final : public Echo::CallbackService {
 public:
  explicit EchoService(int64_t work_us = 0) : work_us_(work_us) {}

  // Stream messages answered so far.
  int64_t answered() const { return answered_.load(); }
  // The CPU their spins took.
  int64_t work_cpu_ns() const { return work_cpu_ns_.load(); }

  grpc::ServerUnaryReactor* Unary(grpc::CallbackServerContext* context,
                                  const EchoRequest* request,
                                  EchoResponse* response) override {
    response->mutable_payload()->assign(request->response_size(), 'x');
    grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
    reactor->Finish(grpc::Status::OK);
    return reactor;
  }

  grpc::ServerBidiReactor<EchoRequest, EchoResponse>* Stream(
      grpc::CallbackServerContext* /*context*/) override {
    class Reactor final
        : public grpc::ServerBidiReactor<EchoRequest, EchoResponse> {
     public:
      explicit Reactor(EchoService* service) : service_(service) {
        StartRead(&request_);
      }
      void OnReadDone(bool ok) override {
        if (!ok) {
          Finish(grpc::Status::OK);
          return;
        }
        if (service_->work_us_ > 0) {
          const int64_t cpu_before = ClockNs(CLOCK_THREAD_CPUTIME_ID);
          SpinFor(service_->work_us_);
          service_->work_cpu_ns_.fetch_add(
              ClockNs(CLOCK_THREAD_CPUTIME_ID) - cpu_before,
              std::memory_order_relaxed);
        }
        // Made once per size, as a server's answer is written once: the
        // floor is the transport's, not the filling of a payload.
        if (static_cast<int64_t>(response_.payload().size()) !=
            request_.response_size()) {
          response_.mutable_payload()->assign(request_.response_size(), 'x');
        }
        service_->answered_.fetch_add(1, std::memory_order_relaxed);
        StartWrite(&response_);
      }
      void OnWriteDone(bool ok) override {
        if (ok) {
          StartRead(&request_);
        } else {
          Finish(grpc::Status::OK);
        }
      }
      void OnDone() override { delete this; }

     private:
      EchoService* const service_;
      EchoRequest request_;
      EchoResponse response_;
    };
    return new Reactor(this);
  }

 private:
  const int64_t work_us_;
  std::atomic<int64_t> answered_{0};
  std::atomic<int64_t> work_cpu_ns_{0};
};

}  // namespace mll::bench

#endif  // MLL_BENCH_SERVICE_ECHO_SERVICE_H_

// The bench-only echo service (echo.proto): the transport floor that the
// service's costs are compared with. Stream answers each request with its
// response_size bytes; with work_cpu_us set, each answer first spends that
// much of the answering thread's CPU, so that the answers come at the rate
// and on the busy threads a server stepping environments would have.
#ifndef MLL_BENCH_SERVICE_ECHO_SERVICE_H_
#define MLL_BENCH_SERVICE_ECHO_SERVICE_H_

#include <time.h>

#include <atomic>
#include <cstdint>

#include "echo.grpc.pb.h"
#include "grpcpp/grpcpp.h"

namespace mll::bench {

// Spins until the calling thread has used `us` more microseconds of CPU.
inline void SpendThreadCpu(int64_t us) {
  if (us <= 0) return;
  const auto now_ns = [] {
    timespec now{};
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &now);
    return int64_t{now.tv_sec} * 1'000'000'000 + now.tv_nsec;
  };
  const int64_t until = now_ns() + us * 1000;
  while (now_ns() < until) {
  }
}

class EchoService final : public Echo::CallbackService {
 public:
  explicit EchoService(int64_t work_cpu_us = 0) : work_cpu_us_(work_cpu_us) {}

  // Stream messages answered so far.
  int64_t answered() const { return answered_.load(); }

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
        SpendThreadCpu(service_->work_cpu_us_);
        response_.mutable_payload()->assign(request_.response_size(), 'x');
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
  const int64_t work_cpu_us_;
  std::atomic<int64_t> answered_{0};
};

}  // namespace mll::bench

#endif  // MLL_BENCH_SERVICE_ECHO_SERVICE_H_

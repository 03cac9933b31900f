// Service benchmarks, each beside its floor measured in the same run:
//   - one env's step latency (p50, p99), unary StepEnv and on a Session
//     stream, vs an echo RPC / echo stream carrying the same payload sizes
//     (bench/service/echo.proto, same process, same loopback transport);
//   - StepBatch of 64 envs x 3 landers on --threads=2, in the `steps` form
//     and in the packed form, vs the in-process core stepping the same 64
//     envs on 2 threads (agent-steps/s, and the ratios to it);
//   - 10,000 live envs: resident memory per env, idle CPU, create and delete
//     rates.
// Run: build/bench/service/service_bench (see docs/benchmarks.md, "Service").
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/synchronization/mutex.h"
#include "benchmark/benchmark.h"
#include "echo.grpc.pb.h"
#include "echo_service.h"
#include "grpcpp/grpcpp.h"
#include "mll/core/env.h"
#include "mll/service/convert.h"
#include "mll/service/server.h"

namespace mll::service {
namespace {

constexpr int kLanders = 3;
constexpr int kBatchEnvs = 64;
constexpr int kLiveEnvs = 10000;

// Discrete actions that keep landers flying for a while; the same table on
// every path so that both sides of a ratio do the same physics.
int32_t ActionFor(int64_t step, int agent) {
  constexpr int32_t kCycle[] = {2, 2, 0, 1, 2, 3, 2, 0};
  return kCycle[(step + 3 * agent) % 8];
}

// An mll server and an echo server, both on loopback TCP in this process.
struct Servers {
  explicit Servers(int threads, int max_envs = 10000) {
    ServerOptions options;
    options.address = "127.0.0.1:0";
    options.service.threads = threads;
    options.service.max_envs = max_envs;
    absl::StatusOr<std::unique_ptr<Server>> started = Server::Start(options);
    if (!started.ok()) std::abort();
    mll = *std::move(started);
    grpc::ServerBuilder builder;
    builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                             &echo_port);
    builder.RegisterService(&echo_service);
    echo = builder.BuildAndStart();
    stub = v1::MultiLunarLander::NewStub(
        grpc::CreateChannel("127.0.0.1:" + std::to_string(mll->port()),
                            grpc::InsecureChannelCredentials()));
    echo_stub = bench::Echo::NewStub(
        grpc::CreateChannel("127.0.0.1:" + std::to_string(echo_port),
                            grpc::InsecureChannelCredentials()));
  }
  ~Servers() { echo->Shutdown(); }

  std::unique_ptr<Server> mll;
  bench::EchoService echo_service;
  std::unique_ptr<grpc::Server> echo;
  int echo_port = 0;
  std::unique_ptr<v1::MultiLunarLander::Stub> stub;
  std::unique_ptr<bench::Echo::Stub> echo_stub;
};

std::string NewEnv(v1::MultiLunarLander::Stub& stub, bool reset) {
  v1::CreateEnvRequest create;
  create.mutable_config()->set_n_landers(kLanders);
  create.mutable_config()->set_auto_reset(true);
  grpc::ClientContext context;
  v1::Env env;
  if (!stub.CreateEnv(&context, create, &env).ok()) std::abort();
  if (reset) {
    grpc::ClientContext reset_context;
    v1::ResetEnvRequest request;
    request.set_name(env.name());
    request.set_seed(1);
    v1::ResetEnvResponse response;
    if (!stub.ResetEnv(&reset_context, request, &response).ok()) std::abort();
  }
  return env.name();
}

v1::StepEnvRequest StepRequest(const std::string& name, int64_t step) {
  v1::StepEnvRequest request;
  request.set_name(name);
  std::vector<int32_t> actions(kLanders);
  for (int i = 0; i < kLanders; ++i) actions[i] = ActionFor(step, i);
  const int shape[] = {kLanders};
  FillArray<int32_t>(actions, shape, request.mutable_actions());
  return request;
}

// Per-call latencies -> p50 / p99 counters in microseconds.
class Latencies {
 public:
  void Add(std::chrono::steady_clock::duration d) {
    us_.push_back(std::chrono::duration<double, std::micro>(d).count());
  }
  void Report(benchmark::State& state) {
    std::sort(us_.begin(), us_.end());
    if (us_.empty()) return;
    state.counters["p50_us"] = us_[us_.size() / 2];
    state.counters["p99_us"] = us_[us_.size() * 99 / 100];
  }

 private:
  std::vector<double> us_;
};

// Sizes of a real StepEnv call, for the echo floors.
struct PayloadSizes {
  int request = 0;
  int response = 0;
};
PayloadSizes StepPayloadSizes(Servers& servers, const std::string& name) {
  v1::StepEnvRequest request = StepRequest(name, 0);
  grpc::ClientContext context;
  v1::StepEnvResponse response;
  if (!servers.stub->StepEnv(&context, request, &response).ok()) std::abort();
  return {static_cast<int>(request.ByteSizeLong()),
          static_cast<int>(response.ByteSizeLong())};
}

// Times one call per benchmark iteration: `prepare` runs untimed before each
// call; a call returning false ends the run with `what` as the error.
template <typename Prepare, typename Call>
void TimeCalls(benchmark::State& state, const char* what, Prepare prepare,
               Call call) {
  Latencies latencies;
  for (auto _ : state) {
    prepare();
    const auto start = std::chrono::steady_clock::now();
    if (!call()) {
      state.SkipWithError(what);
      break;
    }
    latencies.Add(std::chrono::steady_clock::now() - start);
  }
  latencies.Report(state);
}

// An echo request carrying a real step's request size and asking for its
// response size.
bench::EchoRequest EchoRequestSizedLikeAStep(Servers& servers) {
  const PayloadSizes sizes =
      StepPayloadSizes(servers, NewEnv(*servers.stub, true));
  bench::EchoRequest request;
  request.mutable_payload()->assign(sizes.request, 'r');
  request.set_response_size(sizes.response);
  return request;
}

void BM_StepEnvUnary(benchmark::State& state) {
  Servers servers(2);
  const std::string name = NewEnv(*servers.stub, true);
  int64_t step = 0;
  v1::StepEnvRequest request;
  TimeCalls(
      state, "StepEnv failed", [&] { request = StepRequest(name, step++); },
      [&] {
        grpc::ClientContext context;
        v1::StepEnvResponse response;
        return servers.stub->StepEnv(&context, request, &response).ok();
      });
  const PayloadSizes sizes = StepPayloadSizes(servers, name);
  state.counters["request_B"] = sizes.request;
  state.counters["response_B"] = sizes.response;
}

void BM_EchoUnaryFloor(benchmark::State& state) {
  Servers servers(2);
  const bench::EchoRequest request = EchoRequestSizedLikeAStep(servers);
  TimeCalls(
      state, "echo failed", [] {},
      [&] {
        grpc::ClientContext context;
        bench::EchoResponse response;
        return servers.echo_stub->Unary(&context, request, &response).ok();
      });
}

void BM_StepEnvSession(benchmark::State& state) {
  Servers servers(2);
  const std::string name = NewEnv(*servers.stub, true);
  grpc::ClientContext context;
  auto stream = servers.stub->Session(&context);
  int64_t step = 0;
  v1::SessionRequest request;
  v1::SessionResponse response;
  TimeCalls(
      state, "session step failed",
      [&] {
        request.set_sequence(step);
        *request.mutable_step_env() = StepRequest(name, step++);
      },
      [&] {
        return stream->Write(request) && stream->Read(&response) &&
               !response.has_error();
      });
  stream->WritesDone();
  stream->Finish().IgnoreError();
}

void BM_EchoStreamFloor(benchmark::State& state) {
  Servers servers(2);
  const bench::EchoRequest request = EchoRequestSizedLikeAStep(servers);
  grpc::ClientContext context;
  auto stream = servers.echo_stub->Stream(&context);
  bench::EchoResponse response;
  TimeCalls(
      state, "echo stream failed", [] {},
      [&] { return stream->Write(request) && stream->Read(&response); });
  stream->WritesDone();
  stream->Finish().IgnoreError();
}

double ProcessCpuSeconds() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
         1e-6 * (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec);
}

// The floor: the same 64 envs stepped by the core directly, 32 per thread,
// each thread running all its rounds without waiting for the other (an upper
// bound for 2 threads), with a reset where the service would auto-reset.
constexpr int kBatchRounds = 500;

struct Throughput {
  double agent_steps_per_s = 0;
  double cpu_us_per_agent_step = 0;
};

Throughput RunCoreFloor() {
  core::EnvConfig config;
  config.n_landers = kLanders;
  std::vector<std::unique_ptr<core::Env>> envs;
  core::StepResult scratch;
  for (int e = 0; e < kBatchEnvs; ++e) {
    envs.push_back(*core::Env::Create(config));
    envs.back()->Reset(1, &scratch);
  }
  std::atomic<int64_t> agent_steps{0};
  auto run = [&](int first, int last) {
    core::StepResult result;
    std::vector<int32_t> actions(kLanders);
    int64_t count = 0;
    for (int64_t step = 0; step < kBatchRounds; ++step) {
      for (int i = 0; i < kLanders; ++i) actions[i] = ActionFor(step, i);
      for (int e = first; e < last; ++e) {
        core::Env& env = *envs[e];
        if (env.episode_over()) {
          env.Reset(std::nullopt, &result);
          continue;
        }
        count += env.num_active();
        if (!env.Step(core::ActionsView{actions, {}}, &result).ok())
          std::abort();
      }
    }
    agent_steps += count;
  };
  const double cpu_before = ProcessCpuSeconds();
  const auto start = std::chrono::steady_clock::now();
  std::thread other(run, 0, kBatchEnvs / 2);
  run(kBatchEnvs / 2, kBatchEnvs);
  other.join();
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  return {agent_steps.load() / seconds,
          1e6 * (ProcessCpuSeconds() - cpu_before) / agent_steps.load()};
}

void BM_CoreFloor64x3TwoThreads(benchmark::State& state) {
  Throughput floor;
  for (auto _ : state) floor = RunCoreFloor();
  state.counters["agent_steps_per_s"] = floor.agent_steps_per_s;
  state.counters["process_cpu_us_per_agent_step"] = floor.cpu_us_per_agent_step;
}

// Times kBatchRounds StepBatch calls over 64 envs on a --threads=2 server,
// building each request (request_for(names, step)) and reading each
// response (agent_steps_of(response)) inside the timed loop, as a trainer
// would; reports agent-steps/s and both ratios to the core floor, measured
// right before (so that both sides see the same machine load).
template <typename RequestFor, typename AgentStepsOf>
void TimeBatches(benchmark::State& state, RequestFor request_for,
                 AgentStepsOf agent_steps_of) {
  const Throughput floor = RunCoreFloor();
  Servers servers(2);
  std::vector<std::string> names;
  for (int e = 0; e < kBatchEnvs; ++e) {
    names.push_back(NewEnv(*servers.stub, true));
  }
  int64_t step = 0;
  int64_t agent_steps = 0;
  const double cpu_before = ProcessCpuSeconds();
  const auto start = std::chrono::steady_clock::now();
  for (auto _ : state) {
    const v1::StepBatchRequest request = request_for(names, step++);
    grpc::ClientContext context;
    // As a trainer would: the response's many sub-messages on one arena.
    google::protobuf::Arena arena;
    auto* response =
        google::protobuf::Arena::CreateMessage<v1::StepBatchResponse>(&arena);
    if (!servers.stub->StepBatch(&context, request, response).ok()) {
      state.SkipWithError("StepBatch failed");
      break;
    }
    agent_steps += agent_steps_of(*response);
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  // Every thread of the process (client, gRPC, workers): insensitive to how
  // much of a shared machine the run got.
  const double cpu_us = 1e6 * (ProcessCpuSeconds() - cpu_before) / agent_steps;
  const double rate = agent_steps / seconds;
  state.counters["agent_steps_per_s"] = rate;
  state.counters["process_cpu_us_per_agent_step"] = cpu_us;
  state.counters["floor_agent_steps_per_s"] = floor.agent_steps_per_s;
  state.counters["ratio_to_floor"] = rate / floor.agent_steps_per_s;
  state.counters["cpu_ratio_to_floor"] = floor.cpu_us_per_agent_step / cpu_us;
}

// The `steps` form: one StepEnvRequest per env.
void BM_StepBatch64x3(benchmark::State& state) {
  TimeBatches(
      state,
      [](const std::vector<std::string>& names, int64_t step) {
        v1::StepBatchRequest request;
        for (const std::string& name : names) {
          *request.add_steps() = StepRequest(name, step);
        }
        return request;
      },
      [](const v1::StepBatchResponse& response) {
        int64_t agent_steps = 0;
        for (const v1::StepBatchResult& result : response.results()) {
          if (result.data().auto_reset()) continue;  // No physics that step.
          for (char stepped : result.data().stepped().data()) {
            agent_steps += stepped;
          }
        }
        return agent_steps;
      });
}

// The packed form: one names list and one [64, 3] actions array in, one
// array per column out.
void BM_StepBatchPacked64x3(benchmark::State& state) {
  TimeBatches(
      state,
      [](const std::vector<std::string>& names, int64_t step) {
        v1::StepBatchRequest request;
        v1::PackedSteps* packed = request.mutable_packed();
        packed->mutable_names()->Assign(names.begin(), names.end());
        std::vector<int32_t> actions(names.size() * kLanders);
        for (size_t e = 0; e < names.size(); ++e) {
          for (int i = 0; i < kLanders; ++i) {
            actions[e * kLanders + i] = ActionFor(step, i);
          }
        }
        const int shape[] = {static_cast<int>(names.size()), kLanders};
        FillArray<int32_t>(actions, shape, packed->mutable_actions());
        return request;
      },
      [](const v1::StepBatchResponse& response) {
        const v1::PackedStepData& packed = response.packed();
        if (packed.errors_size() > 0) std::abort();
        const std::string& stepped = packed.stepped().data();
        const std::string& auto_reset = packed.auto_reset().data();
        int64_t agent_steps = 0;
        for (size_t e = 0; e < auto_reset.size(); ++e) {
          if (auto_reset[e]) continue;  // No physics that step.
          for (int i = 0; i < kLanders; ++i) {
            agent_steps += stepped[e * kLanders + i];
          }
        }
        return agent_steps;
      });
}

int64_t ResidentBytes() {
  std::ifstream statm("/proc/self/statm");
  int64_t pages = 0, resident = 0;
  statm >> pages >> resident;
  return resident * sysconf(_SC_PAGESIZE);
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
      .count();
}

// One unary call per env name, in order; any failure ends the run.
template <typename Request, typename Response, typename Method>
void CallForEach(const std::vector<std::string>& names, Method method,
                 v1::MultiLunarLander::Stub& stub) {
  for (const std::string& name : names) {
    grpc::ClientContext context;
    Request request;
    request.set_name(name);
    Response response;
    if (!(stub.*method)(&context, request, &response).ok()) std::abort();
  }
}

void BM_TenThousandLiveEnvs(benchmark::State& state) {
  for (auto _ : state) {
    Servers servers(2, kLiveEnvs);
    const int64_t rss_before = ResidentBytes();
    auto start = std::chrono::steady_clock::now();
    std::vector<std::string> names;
    for (int e = 0; e < kLiveEnvs; ++e) {
      names.push_back(NewEnv(*servers.stub, /*reset=*/false));
    }
    const double create_s = SecondsSince(start);
    start = std::chrono::steady_clock::now();
    CallForEach<v1::ResetEnvRequest, v1::ResetEnvResponse>(
        names, &v1::MultiLunarLander::Stub::ResetEnv, *servers.stub);
    const double reset_s = SecondsSince(start);
    const int64_t rss_live = ResidentBytes();
    // Idle: nothing is called for 3 s; the process should sleep.
    const double cpu_before = ProcessCpuSeconds();
    start = std::chrono::steady_clock::now();
    std::this_thread::sleep_for(std::chrono::seconds(3));
    const double idle_cpu =
        (ProcessCpuSeconds() - cpu_before) / SecondsSince(start);
    start = std::chrono::steady_clock::now();
    CallForEach<v1::DeleteEnvRequest, v1::DeleteEnvResponse>(
        names, &v1::MultiLunarLander::Stub::DeleteEnv, *servers.stub);
    const double delete_s = SecondsSince(start);
    state.counters["rss_KiB_per_env"] =
        (rss_live - rss_before) / 1024.0 / kLiveEnvs;
    state.counters["idle_cpu_percent"] = 100.0 * idle_cpu;
    state.counters["creates_per_s"] = kLiveEnvs / create_s;
    state.counters["resets_per_s"] = kLiveEnvs / reset_s;
    state.counters["deletes_per_s"] = kLiveEnvs / delete_s;
  }
}

BENCHMARK(BM_EchoUnaryFloor)->Iterations(5000)->UseRealTime();
BENCHMARK(BM_StepEnvUnary)->Iterations(5000)->UseRealTime();
BENCHMARK(BM_EchoStreamFloor)->Iterations(5000)->UseRealTime();
BENCHMARK(BM_StepEnvSession)->Iterations(5000)->UseRealTime();
BENCHMARK(BM_CoreFloor64x3TwoThreads)->Iterations(1)->UseRealTime();
BENCHMARK(BM_StepBatch64x3)->Iterations(kBatchRounds)->UseRealTime();
BENCHMARK(BM_StepBatchPacked64x3)->Iterations(kBatchRounds)->UseRealTime();
BENCHMARK(BM_TenThousandLiveEnvs)->Iterations(1)->UseRealTime();

}  // namespace
}  // namespace mll::service

// As mll_server does: no Mutex deadlock detection (see mll_server_main.cc).
int main(int argc, char** argv) {
  absl::SetMutexDeadlockDetectionMode(absl::OnDeadlockCycle::kIgnore);
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}

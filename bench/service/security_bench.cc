// What security and metrics cost, each beside its floor in the same run:
//   - recording one call / one step's result in Metrics vs one relaxed atomic
//     add and one steady_clock read (the parts a record is made of);
//   - checking a bearer token (SHA-256 + constant-time compare over every
//     token) with 1 and 16 tokens;
//   - rendering the /metrics text (one scrape);
//   - one unary StepEnv (3 landers) with tokens vs without, in-process
//     channel; and over loopback TCP with TLS vs plaintext.
// Run: build-sec/bench/service/security_bench (see docs/benchmarks.md,
// "Security and metrics").
#include <atomic>
#include <chrono>
#include <cstdlib>
#include <memory>
#include <string>
#include <vector>

#include "benchmark/benchmark.h"
#include "grpcpp/grpcpp.h"
#include "mll/service/auth.h"
#include "mll/service/convert.h"
#include "mll/service/metrics.h"
#include "mll/service/server.h"

namespace mll::service {
namespace {

constexpr int kLanders = 3;
constexpr char kToken[] = "bench-token-0123456789abcdef";

void BM_FloorAtomicAdd(benchmark::State& state) {
  std::atomic<uint64_t> counter{0};
  for (auto _ : state) counter.fetch_add(1, std::memory_order_relaxed);
  benchmark::DoNotOptimize(counter.load());
}
BENCHMARK(BM_FloorAtomicAdd);

void BM_FloorSteadyClock(benchmark::State& state) {
  for (auto _ : state) {
    benchmark::DoNotOptimize(std::chrono::steady_clock::now());
  }
}
BENCHMARK(BM_FloorSteadyClock);

void BM_MetricsRecordCall(benchmark::State& state) {
  Metrics metrics;
  int64_t latency_ns = 0;
  for (auto _ : state) {
    metrics.RecordCall(Method::kStepEnv, absl::StatusCode::kOk, latency_ns);
    latency_ns = (latency_ns + 37'000) % 3'000'000;
  }
}
BENCHMARK(BM_MetricsRecordCall);

void BM_MetricsRecordStepData(benchmark::State& state) {
  Metrics metrics;
  v1::StepData data;
  data.mutable_stepped()->set_data(std::string(kLanders, '\x01'));
  for (auto _ : state) metrics.RecordStepData(Method::kStepEnv, data);
}
BENCHMARK(BM_MetricsRecordStepData);

void BM_MetricsRender(benchmark::State& state) {
  Metrics metrics;
  for (int m = 0; m < kMethodCount; ++m) {
    metrics.RecordCall(static_cast<Method>(m), absl::StatusCode::kNotFound,
                       100'000);
  }
  for (auto _ : state) benchmark::DoNotOptimize(metrics.Render(10000));
}
BENCHMARK(BM_MetricsRender);

// Arg: number of tokens; the presented one is the last.
void BM_Authenticate(benchmark::State& state) {
  std::vector<std::string> tokens;
  for (int i = 1; i < state.range(0); ++i) {
    tokens.push_back(std::string(kToken) + std::to_string(i));
  }
  tokens.push_back(kToken);
  const Authenticator authenticator(tokens);
  const std::string header = std::string("Bearer ") + kToken;
  for (auto _ : state) {
    benchmark::DoNotOptimize(authenticator.Authenticate(header));
  }
}
BENCHMARK(BM_Authenticate)->Arg(1)->Arg(16);

// Steps one reset 3-lander env with unary StepEnv over `channel`, resetting
// when its episode ends; `token` sent when not empty.
void StepLoop(benchmark::State& state,
              const std::shared_ptr<grpc::Channel>& channel,
              const std::string& token) {
  auto stub = v1::MultiLunarLander::NewStub(channel);
  auto prepare = [&](grpc::ClientContext* context) {
    if (!token.empty()) {
      context->AddMetadata("authorization", "Bearer " + token);
    }
  };
  v1::Env env;
  {
    grpc::ClientContext context;
    prepare(&context);
    v1::CreateEnvRequest request;
    request.mutable_config()->set_n_landers(kLanders);
    if (!stub->CreateEnv(&context, request, &env).ok()) {
      state.SkipWithError("CreateEnv failed");
      return;
    }
  }
  v1::ResetEnvRequest reset;
  reset.set_name(env.name());
  reset.set_seed(5);
  v1::StepEnvRequest step;
  step.set_name(env.name());
  const std::vector<int32_t> actions(kLanders, 2);
  const int shape[] = {kLanders};
  FillArray<int32_t>(actions, shape, step.mutable_actions());
  bool need_reset = true;
  for (auto _ : state) {
    if (need_reset) {
      grpc::ClientContext context;
      prepare(&context);
      v1::ResetEnvResponse response;
      stub->ResetEnv(&context, reset, &response);
    }
    grpc::ClientContext context;
    prepare(&context);
    v1::StepEnvResponse response;
    const grpc::Status status = stub->StepEnv(&context, step, &response);
    if (!status.ok()) {
      state.SkipWithError(status.error_message().c_str());
      return;
    }
    need_reset = response.data().episode_over();
  }
}

// Arg 0: no tokens; 1: two tokens, the call presents one.
void BM_StepEnvInProcess(benchmark::State& state) {
  ServerOptions options;
  options.address = "";
  if (state.range(0) == 1) options.service.auth_tokens = {"other", kToken};
  absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
  if (!server.ok()) {
    state.SkipWithError(std::string(server.status().message()).c_str());
    return;
  }
  StepLoop(state, (*server)->InProcessChannel(),
           state.range(0) == 1 ? kToken : "");
}
BENCHMARK(BM_StepEnvInProcess)->Arg(0)->Arg(1)->UseRealTime();

// Arg 0: plaintext; 1: TLS (certificate made with the openssl CLI).
void BM_StepEnvTcp(benchmark::State& state) {
  ServerOptions options;
  options.address = "127.0.0.1:0";
  std::shared_ptr<grpc::ChannelCredentials> credentials =
      grpc::InsecureChannelCredentials();
  if (state.range(0) == 1) {
    const std::string dir = "/tmp/mll_security_bench_";
    options.tls_cert_file = dir + "cert.pem";
    options.tls_key_file = dir + "key.pem";
    const std::string command =
        "openssl req -x509 -newkey ec -pkeyopt ec_paramgen_curve:prime256v1 "
        "-nodes -days 1 -subj /CN=localhost "
        "-addext subjectAltName=IP:127.0.0.1 -keyout " +
        options.tls_key_file + " -out " + options.tls_cert_file +
        " 2>/dev/null";
    if (std::system(command.c_str()) != 0) {
      state.SkipWithError("openssl failed");
      return;
    }
    grpc::SslCredentialsOptions ssl;
    std::FILE* cert = std::fopen(options.tls_cert_file.c_str(), "r");
    char buffer[4096];
    const size_t size = std::fread(buffer, 1, sizeof(buffer), cert);
    std::fclose(cert);
    ssl.pem_root_certs.assign(buffer, size);
    credentials = grpc::SslCredentials(ssl);
  }
  absl::StatusOr<std::unique_ptr<Server>> server = Server::Start(options);
  if (!server.ok()) {
    state.SkipWithError(std::string(server.status().message()).c_str());
    return;
  }
  StepLoop(state,
           grpc::CreateChannel("127.0.0.1:" + std::to_string((*server)->port()),
                               credentials),
           "");
}
BENCHMARK(BM_StepEnvTcp)->Arg(0)->Arg(1)->UseRealTime();

}  // namespace
}  // namespace mll::service

BENCHMARK_MAIN();

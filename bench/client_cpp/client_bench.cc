// The client library's overhead against the raw generated stubs, in one run
// against one real mll_server on loopback (started here, --threads=2):
//   single parallel step (unary and session stream) of a 1-lander env, and
//   StepBatch over 64 envs of 3 landers;
// and the scale-out path: the same StepBatch through a client over two
// servers (a second mll_server started here), one call per server in flight
// at once, beside the one-server client in the same run.
// The raw variants build their request once and reuse it: the floor a
// hand-written gRPC program reaches. Envs use auto_reset, so every call steps.
//
//   build-cppclient/bench/client_cpp/client_cpp_bench
//       --benchmark_repetitions=3 --benchmark_report_aggregates_only=true
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "benchmark/benchmark.h"
#include "grpcpp/client_context.h"
#include "grpcpp/create_channel.h"
#include "grpcpp/security/credentials.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"
#include "server_process.h"

namespace mll::client {
namespace {

constexpr int kBatchEnvs = 64;
constexpr int kBatchLanders = 3;

// The server every benchmark talks to, and the second server of the
// scale-out variant; started and stopped by main().
ServerProcess* server = nullptr;
ServerProcess* second_server = nullptr;
ServerProcess& Server() { return *server; }

Client MakeClient() {
  absl::StatusOr<Client> client = Client::Create(Server().address());
  if (!client.ok()) std::abort();
  return *std::move(client);
}

RemoteEnv MakeEnv(const Client& client, int n_landers) {
  RemoteEnvConfig config;
  config.n_landers = n_landers;
  config.auto_reset = true;
  absl::StatusOr<RemoteEnv> env = client.CreateEnv(config);
  if (!env.ok() || !env->Reset(0).ok()) std::abort();
  return *std::move(env);
}

void Fail(benchmark::State& state, const std::string& what) {
  state.SkipWithError(what.c_str());
}

// A raw StepEnvRequest with `n` discrete actions "main engine off".
v1::StepEnvRequest RawStep(const std::string& name, int n) {
  v1::StepEnvRequest request;
  request.set_name(name);
  v1::Array& actions = *request.mutable_actions();
  actions.set_dtype(v1::DTYPE_INT32);
  actions.add_shape(n);
  actions.set_data(std::string(n * sizeof(int32_t), '\0'));
  return request;
}

std::unique_ptr<v1::MultiLunarLander::Stub> RawStub() {
  return v1::MultiLunarLander::NewStub(grpc::CreateChannel(
      Server().address(), grpc::InsecureChannelCredentials()));
}

void BM_RawStub_Step(benchmark::State& state) {
  Client client = MakeClient();
  RemoteEnv env = MakeEnv(client, 1);
  auto stub = RawStub();
  const v1::StepEnvRequest request = RawStep(env.name(), 1);
  v1::StepEnvResponse response;
  for (auto _ : state) {
    grpc::ClientContext context;
    grpc::Status status = stub->StepEnv(&context, request, &response);
    if (!status.ok()) return Fail(state, status.error_message());
  }
  state.SetItemsProcessed(state.iterations());
}
BENCHMARK(BM_RawStub_Step)->UseRealTime();

// Steps a 1-lander env through the client for every iteration.
void ClientStepLoop(benchmark::State& state, RemoteEnv& env) {
  const std::vector<int32_t> actions = {0};
  for (auto _ : state) {
    absl::StatusOr<StepData> data = env.Step(Actions::Discrete(actions));
    if (!data.ok()) return Fail(state, data.status().ToString());
    benchmark::DoNotOptimize(data->observations.data());
  }
  state.SetItemsProcessed(state.iterations());
}

void BM_Client_Step(benchmark::State& state) {
  Client client = MakeClient();
  RemoteEnv env = MakeEnv(client, 1);
  ClientStepLoop(state, env);
}
BENCHMARK(BM_Client_Step)->UseRealTime();

void BM_RawStub_SessionStep(benchmark::State& state) {
  Client client = MakeClient();
  RemoteEnv env = MakeEnv(client, 1);
  auto stub = RawStub();
  grpc::ClientContext context;
  auto stream = stub->Session(&context);
  v1::SessionRequest request;
  *request.mutable_step_env() = RawStep(env.name(), 1);
  v1::SessionResponse response;
  uint64_t sequence = 0;
  for (auto _ : state) {
    request.set_sequence(++sequence);
    if (!stream->Write(request) || !stream->Read(&response) ||
        response.has_error()) {
      return Fail(state, "session step failed");
    }
  }
  stream->WritesDone();
  (void)stream->Finish();
  state.SetItemsProcessed(state.iterations());
}
BENCHMARK(BM_RawStub_SessionStep)->UseRealTime();

void BM_Client_SessionStep(benchmark::State& state) {
  Client unary = MakeClient();
  absl::StatusOr<Client> session = unary.OpenSession();
  if (!session.ok()) return Fail(state, session.status().ToString());
  RemoteEnv env = MakeEnv(*session, 1);
  ClientStepLoop(state, env);
}
BENCHMARK(BM_Client_SessionStep)->UseRealTime();

std::vector<RemoteEnv> MakeBatchEnvs(const Client& client) {
  std::vector<RemoteEnv> envs;
  for (int i = 0; i < kBatchEnvs; ++i) {
    envs.push_back(MakeEnv(client, kBatchLanders));
  }
  return envs;
}

// Items are agent-steps.
void BM_RawStub_StepBatch(benchmark::State& state) {
  Client client = MakeClient();
  std::vector<RemoteEnv> envs = MakeBatchEnvs(client);
  auto stub = RawStub();
  v1::StepBatchRequest request;
  for (const RemoteEnv& env : envs) {
    *request.add_steps() = RawStep(env.name(), kBatchLanders);
  }
  v1::StepBatchResponse response;
  for (auto _ : state) {
    grpc::ClientContext context;
    grpc::Status status = stub->StepBatch(&context, request, &response);
    if (!status.ok()) return Fail(state, status.error_message());
  }
  state.SetItemsProcessed(state.iterations() * kBatchEnvs * kBatchLanders);
}
BENCHMARK(BM_RawStub_StepBatch)->UseRealTime();

// StepBatch of kBatchEnvs envs created through `client` (round-robin over
// its servers), every iteration.
void ClientBatchLoop(benchmark::State& state, const Client& client) {
  std::vector<RemoteEnv> envs = MakeBatchEnvs(client);
  const std::vector<int32_t> actions(kBatchLanders, 0);
  std::vector<BatchStep> steps;
  for (const RemoteEnv& env : envs) {
    steps.push_back({&env, Actions::Discrete(actions)});
  }
  for (auto _ : state) {
    auto results = client.StepBatch(steps);
    if (!results.ok()) return Fail(state, results.status().ToString());
    benchmark::DoNotOptimize(results->data());
  }
  state.SetItemsProcessed(state.iterations() * kBatchEnvs * kBatchLanders);
}

void BM_Client_StepBatch(benchmark::State& state) {
  ClientBatchLoop(state, MakeClient());
}
BENCHMARK(BM_Client_StepBatch)->UseRealTime();
// Process CPU as well: with two servers, gRPC's callback threads receive and
// parse one server's response, which the calling thread's CPU would miss.
BENCHMARK(BM_Client_StepBatch)
    ->Name("BM_Client_StepBatch_OneServer/process_cpu")
    ->MeasureProcessCPUTime()
    ->UseRealTime();

void BM_Client_StepBatchTwoServers(benchmark::State& state) {
  absl::StatusOr<Client> client =
      Client::Create({Server().address(), second_server->address()});
  if (!client.ok()) return Fail(state, client.status().ToString());
  ClientBatchLoop(state, *client);
}
BENCHMARK(BM_Client_StepBatchTwoServers)
    ->Name("BM_Client_StepBatch_TwoServers/process_cpu")
    ->MeasureProcessCPUTime()
    ->UseRealTime();

}  // namespace
}  // namespace mll::client

int main(int argc, char** argv) {
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  absl::StatusOr<std::unique_ptr<mll::client::ServerProcess>> server =
      mll::client::ServerProcess::Start(MLL_SERVER_PATH, {"--threads=2"});
  if (!server.ok()) {
    std::cerr << "cannot start the server: " << server.status() << std::endl;
    return 1;
  }
  absl::StatusOr<std::unique_ptr<mll::client::ServerProcess>> second =
      mll::client::ServerProcess::Start(MLL_SERVER_PATH, {"--threads=2"});
  if (!second.ok()) {
    std::cerr << "cannot start the second server: " << second.status()
              << std::endl;
    return 1;
  }
  mll::client::server = server->get();
  mll::client::second_server = second->get();
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;  // The servers stop when `server` and `second` go out of scope.
}

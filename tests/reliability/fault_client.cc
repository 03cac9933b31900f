// A client for the killed-client scenario (fault_test.cc): creates envs on
// the server at argv[1], two through unary calls and two on a Session
// stream, steps them mid-episode, prints "unary <name>" / "session <name>"
// lines and "ready", then keeps the stream open until it is killed (or 120 s
// pass, so that a lost child cannot linger).
#include <cstdio>
#include <memory>
#include <string>
#include <thread>

#include "grpcpp/grpcpp.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"

namespace {

using mll::v1::MultiLunarLander;

constexpr int kEnvsPerKind = 2;

mll::v1::Array ThreeMainEngines() {
  mll::v1::Array actions;
  actions.set_dtype(mll::v1::DTYPE_INT32);
  actions.add_shape(3);
  const int32_t values[3] = {2, 2, 2};
  actions.set_data(reinterpret_cast<const char*>(values), sizeof(values));
  return actions;
}

int Die(const char* what, const grpc::Status& status) {
  std::fprintf(stderr, "fault_client: %s: %s\n", what,
               status.error_message().c_str());
  return 1;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::fprintf(stderr, "usage: fault_client <address>\n");
    return 2;
  }
  auto stub = MultiLunarLander::NewStub(
      grpc::CreateChannel(argv[1], grpc::InsecureChannelCredentials()));
  for (int i = 0; i < kEnvsPerKind; ++i) {
    grpc::ClientContext create_context;
    mll::v1::CreateEnvRequest create;
    mll::v1::Env env;
    grpc::Status status = stub->CreateEnv(&create_context, create, &env);
    if (!status.ok()) return Die("CreateEnv", status);
    grpc::ClientContext reset_context;
    mll::v1::ResetEnvRequest reset;
    reset.set_name(env.name());
    mll::v1::ResetEnvResponse reset_response;
    status = stub->ResetEnv(&reset_context, reset, &reset_response);
    if (!status.ok()) return Die("ResetEnv", status);
    grpc::ClientContext step_context;
    mll::v1::StepEnvRequest step;
    step.set_name(env.name());
    *step.mutable_actions() = ThreeMainEngines();
    mll::v1::StepEnvResponse step_response;
    status = stub->StepEnv(&step_context, step, &step_response);
    if (!status.ok()) return Die("StepEnv", status);
    std::printf("unary %s\n", env.name().c_str());
  }

  grpc::ClientContext session_context;
  auto stream = stub->Session(&session_context);
  uint64_t sequence = 0;
  for (int i = 0; i < kEnvsPerKind; ++i) {
    mll::v1::SessionRequest request;
    mll::v1::SessionResponse response;
    request.set_sequence(++sequence);
    request.mutable_create_env();
    if (!stream->Write(request) || !stream->Read(&response) ||
        response.has_error()) {
      std::fprintf(stderr, "fault_client: session create failed\n");
      return 1;
    }
    const std::string name = response.env().name();
    request.Clear();
    request.set_sequence(++sequence);
    request.mutable_reset_env()->set_name(name);
    if (!stream->Write(request) || !stream->Read(&response)) return 1;
    request.Clear();
    request.set_sequence(++sequence);
    request.mutable_step_env()->set_name(name);
    *request.mutable_step_env()->mutable_actions() = ThreeMainEngines();
    if (!stream->Write(request) || !stream->Read(&response) ||
        response.has_error()) {
      std::fprintf(stderr, "fault_client: session step failed\n");
      return 1;
    }
    std::printf("session %s\n", name.c_str());
  }
  std::printf("ready\n");
  std::fflush(stdout);
  std::this_thread::sleep_for(std::chrono::seconds(120));
  return 0;
}

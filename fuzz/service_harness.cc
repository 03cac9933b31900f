// RunServiceInput: arbitrary request bytes through mll::service::Operations,
// the code every unary handler and Session operation of the service calls.
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/synchronization/notification.h"
#include "absl/time/time.h"
#include "google/protobuf/descriptor.h"
#include "google/protobuf/message.h"
#include "harness.h"
#include "mll/service/metrics.h"
#include "mll/service/operations.h"
#include "mll/service/registry.h"
#include "mll/service/worker_pool.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::fuzz {
namespace {

// Small, so that inputs reach RESOURCE_EXHAUSTED and stay cheap.
constexpr int kMaxEnvs = 6;
// Bounds the work of one input (each step of a 32-lander env costs ~0.5 ms).
constexpr int kMaxOps = 96;
constexpr int kWorkers = 2;

[[noreturn]] void Fail(const std::string& what) {
  HarnessFailure("service harness", what);
}

// Every failure must be a clean error with one of the codes the contract
// allows for this call, and a message that says what was wrong.
void CheckCode(const absl::Status& status,
               std::initializer_list<absl::StatusCode> allowed,
               const char* call) {
  if (status.ok()) return;
  for (absl::StatusCode code : allowed) {
    if (status.code() == code) {
      if (status.message().empty()) {
        Fail(absl::StrCat(call,
                          ": error without a message: ", status.ToString()));
      }
      return;
    }
  }
  Fail(absl::StrCat(call, ": unexpected status ", status.ToString()));
}

void CheckFloats(const v1::Array& array, size_t count, const char* what) {
  if (array.dtype() != v1::DTYPE_FLOAT32 ||
      array.data().size() != count * sizeof(float)) {
    Fail(absl::StrCat(what, ": dtype ", array.dtype(), ", ",
                      array.data().size(), " bytes, want ", count, " float32"));
  }
  std::vector<float> values(count);
  std::memcpy(values.data(), array.data().data(), array.data().size());
  for (size_t i = 0; i < count; ++i) {
    if (!std::isfinite(values[i])) {
      Fail(absl::StrCat(what, "[", i, "] is ", values[i]));
    }
  }
}

// A successful step's or reset's columns have n_landers rows and finite
// values, whatever the actions were.
void CheckStepData(const v1::StepData& data, int n_landers) {
  CheckFloats(data.observations(), n_landers * 12, "observations");
  CheckFloats(data.rewards(), n_landers, "rewards");
  CheckFloats(data.episode_returns(), n_landers, "episode_returns");
  if (data.terminations().data().size() != static_cast<size_t>(n_landers)) {
    Fail("terminations: wrong size");
  }
}

struct Service {
  Service()
      : registry(kMaxEnvs, absl::Hours(1)),
        operations(&registry, &pool),
        pool(kWorkers) {}
  // In the service's order: the workers stop first.
  service::Registry registry;
  service::Operations operations;
  service::WorkerPool pool;
};

Service& TheService() {
  // Built once per process: the fuzzer runs millions of inputs against it.
  static Service* const service = new Service();
  return *service;
}

// "@<digit>" names the env created n-th by this input.
void Resolve(const std::vector<std::string>& created, std::string* name) {
  if (created.empty() || name->size() != 2 || (*name)[0] != '@' ||
      (*name)[1] < '0' || (*name)[1] > '9') {
    return;
  }
  *name = created[((*name)[1] - '0') % created.size()];
}

// n_landers of the env called `name`, or 0 when there is none.
int LandersOf(Service& service, const std::string& name) {
  v1::GetEnvRequest request;
  request.set_name(name);
  v1::Env env;
  if (!service.operations.GetEnv(request, &env).ok()) return 0;
  return env.config().n_landers();
}

constexpr std::initializer_list<absl::StatusCode> kStepCodes = {
    absl::StatusCode::kInvalidArgument, absl::StatusCode::kNotFound,
    absl::StatusCode::kFailedPrecondition};
constexpr std::initializer_list<absl::StatusCode> kLookupCodes = {
    absl::StatusCode::kInvalidArgument, absl::StatusCode::kNotFound};

// A packed StepBatch's columns have a row per env, finite values whatever
// the actions were, and its errors name distinct rows in increasing order
// with a code a single StepEnv could give.
void CheckPacked(const v1::PackedSteps& request,
                 const v1::PackedStepData& packed) {
  const v1::Array& actions = request.actions();
  // Parse accepted the actions, so their shape is [num_envs, n_landers, ...].
  const size_t rows = static_cast<size_t>(request.names_size()) *
                      (actions.shape_size() >= 2 ? actions.shape(1) : 0);
  CheckFloats(packed.observations(), rows * 12, "packed.observations");
  CheckFloats(packed.rewards(), rows, "packed.rewards");
  CheckFloats(packed.episode_returns(), rows, "packed.episode_returns");
  int previous = -1;
  for (const v1::IndexedItemError& error : packed.errors()) {
    if (error.index() <= previous || error.index() >= request.names_size()) {
      Fail(absl::StrCat("StepBatch packed: error index ", error.index(),
                        " after ", previous, " of ", request.names_size()));
    }
    previous = error.index();
    CheckCode(absl::Status(static_cast<absl::StatusCode>(error.error().code()),
                           error.error().message()),
              kStepCodes, "StepBatch packed item");
  }
}

void RunOp(Service& service, service::Method method, const std::string& bytes,
           bool in_session, std::vector<std::string>* created);

// A Session request runs its operation as the RPC it stands for: the one
// whose request message the operation is (found by name, so the harness keeps
// one list of the RPCs, mll::service::Method). A request without an operation
// never reaches Operations (the stream answers it itself).
void RunSessionOp(Service& service, const std::string& bytes,
                  std::vector<std::string>* created) {
  v1::SessionRequest request;
  if (!request.ParseFromString(bytes)) return;
  const google::protobuf::Reflection& reflection = *request.GetReflection();
  const google::protobuf::FieldDescriptor* const field =
      reflection.GetOneofFieldDescriptor(
          request, request.GetDescriptor()->FindOneofByName("op"));
  if (field == nullptr) return;
  for (int i = 0; i < service::kMethodCount; ++i) {
    const auto method = static_cast<service::Method>(i);
    if (absl::StrCat(service::MethodName(method), "Request") ==
        field->message_type()->name()) {
      RunOp(service, method,
            reflection.GetMessage(request, field).SerializeAsString(),
            /*in_session=*/true, created);
      return;
    }
  }
  Fail(absl::StrCat("Session: no method takes op ", field->name()));
}

void RunOp(Service& service, service::Method method, const std::string& bytes,
           bool in_session, std::vector<std::string>* created) {
  service::Operations& ops = service.operations;
  switch (method) {
    case service::Method::kCreateEnv: {
      v1::CreateEnvRequest request;
      if (!request.ParseFromString(bytes)) return;
      v1::Env env;
      absl::Status status = ops.CreateEnv(
          request, /*session_bound=*/in_session && !request.detached(), &env);
      CheckCode(status,
                {absl::StatusCode::kInvalidArgument,
                 absl::StatusCode::kResourceExhausted},
                "CreateEnv");
      if (status.ok()) created->push_back(env.name());
      return;
    }
    case service::Method::kGetEnv: {
      v1::GetEnvRequest request;
      if (!request.ParseFromString(bytes)) return;
      Resolve(*created, request.mutable_name());
      v1::Env env;
      CheckCode(ops.GetEnv(request, &env), kLookupCodes, "GetEnv");
      return;
    }
    case service::Method::kListEnvs: {
      v1::ListEnvsRequest request;
      if (!request.ParseFromString(bytes)) return;
      v1::ListEnvsResponse response;
      absl::Status status = ops.ListEnvs(request, &response);
      CheckCode(status, {absl::StatusCode::kInvalidArgument}, "ListEnvs");
      if (status.ok() && response.envs_size() > kMaxEnvs) {
        Fail(absl::StrCat("ListEnvs: ", response.envs_size(), " envs"));
      }
      return;
    }
    case service::Method::kDeleteEnv: {
      v1::DeleteEnvRequest request;
      if (!request.ParseFromString(bytes)) return;
      Resolve(*created, request.mutable_name());
      CheckCode(ops.DeleteEnv(request), kLookupCodes, "DeleteEnv");
      return;
    }
    case service::Method::kResetEnv: {
      v1::ResetEnvRequest request;
      if (!request.ParseFromString(bytes)) return;
      Resolve(*created, request.mutable_name());
      v1::ResetEnvResponse response;
      absl::Status status = ops.ResetEnv(request, &response);
      CheckCode(status, kLookupCodes, "ResetEnv");
      if (status.ok()) {
        CheckStepData(response.data(), LandersOf(service, request.name()));
      }
      return;
    }
    case service::Method::kStepEnv: {
      v1::StepEnvRequest request;
      if (!request.ParseFromString(bytes)) return;
      Resolve(*created, request.mutable_name());
      v1::StepData data;
      absl::Status status =
          ops.StepEnv(request, in_session ? "step_env." : "", &data);
      CheckCode(status, kStepCodes, "StepEnv");
      if (status.ok()) CheckStepData(data, LandersOf(service, request.name()));
      return;
    }
    case service::Method::kStepAgent: {
      v1::StepAgentRequest request;
      if (!request.ParseFromString(bytes)) return;
      Resolve(*created, request.mutable_name());
      v1::StepAgentResponse response;
      absl::Status status = ops.StepAgent(request, &response);
      CheckCode(status, kStepCodes, "StepAgent");
      if (status.ok()) {
        const int n = LandersOf(service, request.name());
        CheckFloats(response.aec().observations(), n * 12, "aec.observations");
        CheckFloats(response.aec().cumulative_rewards(), n,
                    "aec.cumulative_rewards");
      }
      return;
    }
    case service::Method::kStepBatch: {
      v1::StepBatchRequest request;
      if (!request.ParseFromString(bytes)) return;
      for (v1::StepEnvRequest& step : *request.mutable_steps()) {
        Resolve(*created, step.mutable_name());
      }
      for (std::string& name : *request.mutable_packed()->mutable_names()) {
        Resolve(*created, &name);
      }
      v1::StepBatchResponse response;
      absl::Notification finished;
      absl::Status batch_status;
      ops.StepBatch(request, &response, [&](absl::Status status) {
        batch_status = status;
        finished.Notify();
      });
      finished.WaitForNotification();
      CheckCode(batch_status, {absl::StatusCode::kInvalidArgument},
                "StepBatch");
      if (!batch_status.ok()) return;
      if (request.has_packed()) {
        CheckPacked(request.packed(), response.packed());
        return;
      }
      if (response.results_size() != request.steps_size()) {
        Fail("StepBatch: one result per step expected");
      }
      for (int i = 0; i < response.results_size(); ++i) {
        const v1::StepBatchResult& result = response.results(i);
        if (result.has_error()) {
          CheckCode(
              absl::Status(static_cast<absl::StatusCode>(result.error().code()),
                           result.error().message()),
              kStepCodes, "StepBatch item");
        } else {
          CheckStepData(result.data(),
                        LandersOf(service, request.steps(i).name()));
        }
      }
      return;
    }
    case service::Method::kRenderEnv: {
      v1::RenderEnvRequest request;
      if (!request.ParseFromString(bytes)) return;
      Resolve(*created, request.mutable_name());
      v1::Frame frame;
      absl::Status status = ops.RenderEnv(request, &frame);
      CheckCode(status, kStepCodes, "RenderEnv");
      if (!status.ok()) return;
      const bool png = frame.format() == v1::FRAME_FORMAT_PNG;
      if (png ? frame.data().compare(0, 4, "\x89PNG") != 0
              : frame.data().size() !=
                    static_cast<size_t>(frame.width()) * frame.height() * 3) {
        Fail("RenderEnv: malformed frame");
      }
      return;
    }
    case service::Method::kKeepAlive: {
      v1::KeepAliveRequest request;
      if (!request.ParseFromString(bytes)) return;
      for (std::string& name : *request.mutable_names()) {
        Resolve(*created, &name);
      }
      v1::KeepAliveResponse response;
      absl::Status status = ops.KeepAlive(request, &response);
      CheckCode(status, {absl::StatusCode::kInvalidArgument}, "KeepAlive");
      if (status.ok() && response.not_found_size() > request.names_size()) {
        Fail("KeepAlive: more names not found than asked for");
      }
      return;
    }
    case service::Method::kGetServerInfo:
      // Answered by the service from its options; nothing of Operations.
      return;
    case service::Method::kSession:
      // RunSessionOp never comes back here: a SessionRequest cannot nest one.
      RunSessionOp(service, bytes, created);
      return;
  }
}

}  // namespace

void HarnessFailure(const std::string& harness, const std::string& what) {
  std::fprintf(stderr, "%s: %s\n", harness.c_str(), what.c_str());
  std::fflush(stderr);
  std::abort();
}

void AppendServiceOp(service::Method method, const std::string& proto_bytes,
                     std::vector<uint8_t>* input) {
  input->push_back(static_cast<uint8_t>(method));
  input->push_back(proto_bytes.size() & 0xff);
  input->push_back((proto_bytes.size() >> 8) & 0xff);
  input->insert(input->end(), proto_bytes.begin(), proto_bytes.end());
}

void RunServiceInput(const uint8_t* data, size_t size) {
  Service& service = TheService();
  std::vector<std::string> created;
  size_t offset = 0;
  for (int op = 0; op < kMaxOps && offset + 3 <= size; ++op) {
    const auto method =
        static_cast<service::Method>(data[offset] % service::kMethodCount);
    size_t length = data[offset + 1] | (size_t{data[offset + 2]} << 8);
    offset += 3;
    if (length > size - offset) length = size - offset;
    RunOp(service, method,
          std::string(reinterpret_cast<const char*>(data) + offset, length),
          /*in_session=*/false, &created);
    offset += length;
  }
  for (const std::string& name : created) {
    service.registry.Delete(name, "name").IgnoreError();
  }
  if (service.registry.size() != 0) {
    Fail(absl::StrCat(service.registry.size(),
                      " envs left after deleting every env created"));
  }
}

}  // namespace mll::fuzz

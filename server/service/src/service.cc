#include "mll/service/service.h"

#include <string>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "mll/service/convert.h"

namespace mll {
namespace {

grpc::ServerUnaryReactor* FinishUnary(grpc::CallbackServerContext* context,
                                      const absl::Status& status) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  reactor->Finish(ToGrpcStatus(status));
  return reactor;
}

// One Session stream: reads a request, runs it, writes its response, reads
// the next; so responses come in request order and at most one operation of
// the stream is in flight. Envs it created (not detached) are deleted when
// the stream ends, however it ends.
class SessionReactor final
    : public grpc::ServerBidiReactor<v1::SessionRequest, v1::SessionResponse> {
 public:
  SessionReactor(Operations* operations, Registry* registry)
      : operations_(operations), registry_(registry) {
    StartRead(&request_);
  }

  void OnReadDone(bool ok) override {
    if (!ok) {  // The client half-closed, or the call was cancelled.
      Finish(grpc::Status::OK);
      return;
    }
    response_.Clear();
    response_.set_sequence(request_.sequence());
    if (request_.op_case() == v1::SessionRequest::kStepBatch) {
      // Runs on the worker pool; the write starts when the batch is done.
      operations_->StepBatch(
          request_.step_batch(), response_.mutable_step_batch(),
          [this](absl::Status status) { Respond(status); });
      return;
    }
    Respond(Run());
  }

  void OnWriteDone(bool ok) override {
    if (!ok) {  // The stream broke; nobody reads any more answers.
      Finish(grpc::Status::OK);
      return;
    }
    StartRead(&request_);
  }

  void OnDone() override {
    for (const std::string& name : bound_envs_) {
      // Already deleted or reclaimed is fine: the goal is that it is gone.
      registry_->Delete(name, "name").IgnoreError();
    }
    delete this;
  }

 private:
  absl::Status Run() {
    switch (request_.op_case()) {
      case v1::SessionRequest::kCreateEnv: {
        const bool bound = !request_.create_env().detached();
        absl::Status status = operations_->CreateEnv(
            request_.create_env(), bound, response_.mutable_env());
        if (status.ok() && bound) bound_envs_.push_back(response_.env().name());
        return status;
      }
      case v1::SessionRequest::kGetEnv:
        return operations_->GetEnv(request_.get_env(), response_.mutable_env());
      case v1::SessionRequest::kResetEnv:
        return operations_->ResetEnv(request_.reset_env(),
                                     response_.mutable_reset_env());
      case v1::SessionRequest::kStepEnv:
        return operations_->StepEnv(
            request_.step_env(), "step_env.",
            response_.mutable_step_env()->mutable_data());
      case v1::SessionRequest::kStepAgent:
        return operations_->StepAgent(request_.step_agent(),
                                      response_.mutable_step_agent());
      case v1::SessionRequest::kRenderEnv:
        return operations_->RenderEnv(request_.render_env(),
                                      response_.mutable_frame());
      case v1::SessionRequest::kDeleteEnv:
        response_.mutable_delete_env();
        return operations_->DeleteEnv(request_.delete_env());
      default:
        return absl::InvalidArgumentError(absl::StrCat(
            "op: not set (sequence ", request_.sequence(),
            "); allowed: create_env, reset_env, step_env, step_agent, "
            "step_batch, render_env, delete_env, get_env"));
    }
  }

  void Respond(const absl::Status& status) {
    if (!status.ok()) {
      response_.clear_result();
      FillItemError(status, response_.mutable_error());
    }
    StartWrite(&response_);
  }

  Operations* const operations_;
  Registry* const registry_;
  v1::SessionRequest request_;
  v1::SessionResponse response_;
  std::vector<std::string> bound_envs_;
};

}  // namespace

MultiLunarLanderService::MultiLunarLanderService(const ServiceOptions& options)
    : registry_(options.max_envs, options.idle_timeout),
      operations_(&registry_, &pool_),
      pool_(options.threads) {}

MultiLunarLanderService::~MultiLunarLanderService() = default;

grpc::ServerUnaryReactor* MultiLunarLanderService::CreateEnv(
    grpc::CallbackServerContext* context, const v1::CreateEnvRequest* request,
    v1::Env* response) {
  return FinishUnary(context, operations_.CreateEnv(
                                  *request, /*session_bound=*/false, response));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::GetEnv(
    grpc::CallbackServerContext* context, const v1::GetEnvRequest* request,
    v1::Env* response) {
  return FinishUnary(context, operations_.GetEnv(*request, response));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::ListEnvs(
    grpc::CallbackServerContext* context, const v1::ListEnvsRequest* request,
    v1::ListEnvsResponse* response) {
  return FinishUnary(context, operations_.ListEnvs(*request, response));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::DeleteEnv(
    grpc::CallbackServerContext* context, const v1::DeleteEnvRequest* request,
    v1::DeleteEnvResponse* /*response*/) {
  return FinishUnary(context, operations_.DeleteEnv(*request));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::ResetEnv(
    grpc::CallbackServerContext* context, const v1::ResetEnvRequest* request,
    v1::ResetEnvResponse* response) {
  return FinishUnary(context, operations_.ResetEnv(*request, response));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::StepEnv(
    grpc::CallbackServerContext* context, const v1::StepEnvRequest* request,
    v1::StepEnvResponse* response) {
  return FinishUnary(context, operations_.StepEnv(*request, /*field=*/"",
                                                  response->mutable_data()));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::StepAgent(
    grpc::CallbackServerContext* context, const v1::StepAgentRequest* request,
    v1::StepAgentResponse* response) {
  return FinishUnary(context, operations_.StepAgent(*request, response));
}

grpc::ServerUnaryReactor* MultiLunarLanderService::StepBatch(
    grpc::CallbackServerContext* context, const v1::StepBatchRequest* request,
    v1::StepBatchResponse* response) {
  grpc::ServerUnaryReactor* reactor = context->DefaultReactor();
  operations_.StepBatch(*request, response, [reactor](absl::Status status) {
    reactor->Finish(ToGrpcStatus(status));
  });
  return reactor;
}

grpc::ServerUnaryReactor* MultiLunarLanderService::RenderEnv(
    grpc::CallbackServerContext* context, const v1::RenderEnvRequest* request,
    v1::Frame* response) {
  return FinishUnary(context, operations_.RenderEnv(*request, response));
}

grpc::ServerBidiReactor<v1::SessionRequest, v1::SessionResponse>*
MultiLunarLanderService::Session(grpc::CallbackServerContext* /*context*/) {
  return new SessionReactor(&operations_, &registry_);
}

}  // namespace mll

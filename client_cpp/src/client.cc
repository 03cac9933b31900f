#include "mll/client.h"

#include <string>
#include <utility>

#include "absl/strings/str_cat.h"
#include "transport.h"
#include "wire.h"

namespace mll {

using client_internal::Transport;

absl::string_view LanderOutcomeName(LanderOutcome outcome) {
  switch (outcome) {
    case LanderOutcome::kNone:
      return "none";
    case LanderOutcome::kLanded:
      return "landed";
    case LanderOutcome::kCrashed:
      return "crashed";
    case LanderOutcome::kOutOfBounds:
      return "out_of_bounds";
    case LanderOutcome::kTruncated:
      return "truncated";
    case LanderOutcome::kAborted:
      return "aborted";
  }
  return "unknown";
}

AecTurn AecState::Last(int agent) const {
  AecTurn turn;
  turn.agent = agent;
  turn.observation = observation(agent);
  turn.cumulative_reward = cumulative_rewards[agent];
  turn.termination = terminations[agent] != 0;
  turn.truncation = truncations[agent] != 0;
  turn.outcome = outcomes[agent];
  turn.episode_return = episode_returns[agent];
  turn.episode_length = episode_lengths[agent];
  return turn;
}

// ---------------------------------------------------------------- RemoteEnv

RemoteEnv::RemoteEnv(std::shared_ptr<Transport> transport, EnvInfo info,
                     bool owned)
    : transport_(std::move(transport)), info_(std::move(info)), owned_(owned) {}

RemoteEnv::RemoteEnv(RemoteEnv&& other) noexcept
    : transport_(std::move(other.transport_)),
      info_(std::move(other.info_)),
      owned_(std::exchange(other.owned_, false)),
      aec_(std::move(other.aec_)) {}

RemoteEnv& RemoteEnv::operator=(RemoteEnv&& other) noexcept {
  if (this != &other) {
    if (owned_) (void)Delete();
    transport_ = std::move(other.transport_);
    info_ = std::move(other.info_);
    owned_ = std::exchange(other.owned_, false);
    aec_ = std::move(other.aec_);
  }
  return *this;
}

RemoteEnv::~RemoteEnv() {
  // A destructor cannot report; the server's idle timeout reclaims an env
  // whose deletion failed (e.g. the server was unreachable).
  if (owned_) (void)Delete();
}

absl::StatusOr<StepData> RemoteEnv::Reset(std::optional<uint64_t> seed) {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError("Reset on an empty RemoteEnv handle");
  }
  v1::SessionRequest request;
  v1::ResetEnvRequest& reset = *request.mutable_reset_env();
  reset.set_name(info_.name);
  if (seed.has_value()) reset.set_seed(*seed);
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  absl::StatusOr<AecState> aec =
      client_internal::DecodeAecState(response.reset_env().aec());
  if (!aec.ok()) return aec.status();
  absl::StatusOr<StepData> data =
      client_internal::DecodeStepData(response.reset_env().data());
  if (!data.ok()) return data.status();
  if (response.reset_env().has_seed()) data->seed = response.reset_env().seed();
  aec_ = *std::move(aec);
  return data;
}

absl::StatusOr<StepData> RemoteEnv::Step(const Actions& actions) {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError("Step on an empty RemoteEnv handle");
  }
  v1::SessionRequest request;
  v1::StepEnvRequest& step = *request.mutable_step_env();
  step.set_name(info_.name);
  absl::Status status =
      client_internal::EncodeActions(actions, step.mutable_actions());
  if (!status.ok()) return status;
  v1::SessionResponse response;
  status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  return client_internal::DecodeStepData(response.step_env().data());
}

absl::Status RemoteEnv::StepAgent(int32_t discrete_action) {
  AgentMove move;
  move.kind = AgentMove::Kind::kDiscrete;
  move.discrete = discrete_action;
  return StepAgentImpl(move);
}

absl::Status RemoteEnv::StepAgent(
    std::array<float, kRemoteContinuousActionSize> action) {
  AgentMove move;
  move.kind = AgentMove::Kind::kContinuous;
  move.continuous = action;
  return StepAgentImpl(move);
}

absl::Status RemoteEnv::StepAgentDead() { return StepAgentImpl(AgentMove()); }

absl::Status RemoteEnv::StepAgentImpl(const AgentMove& move) {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError(
        "StepAgent on an empty RemoteEnv handle");
  }
  v1::SessionRequest request;
  v1::StepAgentRequest& step = *request.mutable_step_agent();
  step.set_name(info_.name);
  if (aec_.agent_selection >= 0) step.set_agent(aec_.agent_selection);
  switch (move.kind) {
    case AgentMove::Kind::kDead:
      break;
    case AgentMove::Kind::kDiscrete:
      step.mutable_action()->set_discrete(move.discrete);
      break;
    case AgentMove::Kind::kContinuous:
      client_internal::EncodeAgentAction(
          move.continuous, step.mutable_action()->mutable_continuous());
      break;
  }
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  absl::StatusOr<AecState> aec =
      client_internal::DecodeAecState(response.step_agent().aec());
  if (!aec.ok()) return aec.status();
  aec_ = *std::move(aec);
  return absl::OkStatus();
}

absl::StatusOr<AecTurn> RemoteEnv::Last() const {
  if (aec_.agent_selection < 0) {
    return absl::FailedPreconditionError(absl::StrCat(
        "Last on ", info_.name,
        ": no agent is selected (Reset through this handle first, or every "
        "agent has taken its dead step)"));
  }
  return aec_.Last();
}

absl::StatusOr<RenderedFrame> RemoteEnv::Render(FrameFormat format) {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError("Render on an empty RemoteEnv handle");
  }
  v1::SessionRequest request;
  v1::RenderEnvRequest& render = *request.mutable_render_env();
  render.set_name(info_.name);
  render.set_format(format == FrameFormat::kPng ? v1::FRAME_FORMAT_PNG
                                                : v1::FRAME_FORMAT_RGB);
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  return client_internal::DecodeFrame(response.frame());
}

absl::StatusOr<EnvInfo> RemoteEnv::Refresh() {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError(
        "Refresh on an empty RemoteEnv handle");
  }
  absl::StatusOr<EnvInfo> info = Client(transport_).GetEnv(info_.name);
  if (info.ok()) info_ = *info;
  return info;
}

absl::Status RemoteEnv::Delete() {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError("Delete on an empty RemoteEnv handle");
  }
  absl::Status status = Client(std::move(transport_)).DeleteEnv(info_.name);
  transport_ = nullptr;
  owned_ = false;
  return status;
}

std::string RemoteEnv::Release() {
  owned_ = false;
  return info_.name;
}

// ------------------------------------------------------------------- Client

Client::Client(std::shared_ptr<Transport> transport)
    : transport_(std::move(transport)) {}
Client::Client(Client&&) noexcept = default;
Client& Client::operator=(Client&&) noexcept = default;
Client::~Client() = default;

absl::StatusOr<Client> Client::Create(absl::string_view address,
                                      const ClientOptions& options) {
  absl::StatusOr<std::shared_ptr<Transport>> transport =
      client_internal::MakeUnaryTransport(address, options);
  if (!transport.ok()) return transport.status();
  return Client(*std::move(transport));
}

absl::StatusOr<Client> Client::OpenSession() const {
  absl::StatusOr<std::shared_ptr<Transport>> session =
      transport_->OpenSession();
  if (!session.ok()) return session.status();
  return Client(*std::move(session));
}

bool Client::is_session() const { return transport_->is_session(); }

absl::Status Client::CheckHealth(absl::string_view service) const {
  return transport_->CheckHealth(service);
}

absl::StatusOr<RemoteEnv> Client::CreateEnv(const RemoteEnvConfig& config,
                                            bool detached) const {
  v1::SessionRequest request;
  v1::CreateEnvRequest& create = *request.mutable_create_env();
  client_internal::EncodeConfig(config, create.mutable_config());
  create.set_detached(detached);
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  return RemoteEnv(transport_, client_internal::DecodeEnv(response.env()),
                   /*owned=*/true);
}

absl::StatusOr<RemoteEnv> Client::Attach(absl::string_view name) const {
  absl::StatusOr<EnvInfo> info = GetEnv(name);
  if (!info.ok()) return info.status();
  return RemoteEnv(transport_, *std::move(info), /*owned=*/false);
}

absl::StatusOr<EnvInfo> Client::GetEnv(absl::string_view name) const {
  v1::SessionRequest request;
  request.mutable_get_env()->set_name(std::string(name));
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  return client_internal::DecodeEnv(response.env());
}

absl::StatusOr<std::vector<EnvInfo>> Client::ListEnvs() const {
  std::vector<EnvInfo> envs;
  v1::ListEnvsRequest request;
  request.set_page_size(1000);
  do {
    v1::ListEnvsResponse response;
    absl::Status status = transport_->ListEnvs(request, &response);
    if (!status.ok()) return status;
    for (const v1::Env& env : response.envs()) {
      envs.push_back(client_internal::DecodeEnv(env));
    }
    request.set_page_token(response.next_page_token());
  } while (!request.page_token().empty());
  return envs;
}

absl::Status Client::DeleteEnv(absl::string_view name) const {
  v1::SessionRequest request;
  request.mutable_delete_env()->set_name(std::string(name));
  v1::SessionResponse response;
  return transport_->Call(request, &response);
}

absl::StatusOr<std::vector<absl::StatusOr<StepData>>> Client::StepBatch(
    absl::Span<const BatchStep> steps) const {
  v1::SessionRequest request;
  v1::StepBatchRequest& batch = *request.mutable_step_batch();
  for (size_t i = 0; i < steps.size(); ++i) {
    if (steps[i].env == nullptr || steps[i].env->name().empty()) {
      return absl::InvalidArgumentError(
          absl::StrCat("steps[", i, "].env is not a live RemoteEnv handle"));
    }
    v1::StepEnvRequest& step = *batch.add_steps();
    step.set_name(steps[i].env->name());
    absl::Status status = client_internal::EncodeActions(
        steps[i].actions, step.mutable_actions());
    if (!status.ok()) {
      return absl::InvalidArgumentError(
          absl::StrCat("steps[", i, "] (", steps[i].env->name(),
                       "): ", status.message()));
    }
  }
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  const auto& results = response.step_batch().results();
  if (results.size() != static_cast<int>(steps.size())) {
    return absl::InternalError(
        absl::StrCat("StepBatch sent ", steps.size(), " steps and received ",
                     results.size(), " results"));
  }
  std::vector<absl::StatusOr<StepData>> out;
  out.reserve(steps.size());
  for (const v1::StepBatchResult& result : results) {
    if (result.has_error()) {
      out.push_back(client_internal::FromItemError(result.error()));
    } else {
      out.push_back(client_internal::DecodeStepData(result.data()));
    }
  }
  return out;
}

}  // namespace mll

#include "mll/client.h"

#include <future>
#include <string>
#include <utility>

#include "absl/container/flat_hash_set.h"
#include "absl/strings/str_cat.h"
#include "discovery.h"
#include "placement.h"
#include "transport.h"
#include "wire.h"

namespace mll::client {

using internal::Transport;

namespace {

// GetEnv on one server.
absl::StatusOr<EnvInfo> GetEnvOn(Transport& transport, absl::string_view name,
                                 int server) {
  v1::SessionRequest request;
  request.mutable_get_env()->set_name(std::string(name));
  v1::SessionResponse response;
  absl::Status status = transport.Call(request, &response);
  if (!status.ok()) return status;
  EnvInfo info = internal::DecodeEnv(response.env());
  info.server = server;
  return info;
}

absl::Status DeleteEnvOn(Transport& transport, absl::string_view name) {
  v1::SessionRequest request;
  request.mutable_delete_env()->set_name(std::string(name));
  v1::SessionResponse response;
  return transport.Call(request, &response);
}

// `status` with the server's address in front, so that a failure among
// several servers says which one.
absl::Status AtServer(const Transport& transport, const absl::Status& status) {
  return absl::Status(
      status.code(),
      absl::StrCat("server ", transport.address(), ": ", status.message()));
}

}  // namespace

// The client's outcome codes are the wire's: mll.v1.Outcome.
static_assert(static_cast<int>(LanderOutcome::kNone) ==
              v1::OUTCOME_UNSPECIFIED);
static_assert(static_cast<int>(LanderOutcome::kLanded) == v1::OUTCOME_LANDED);
static_assert(static_cast<int>(LanderOutcome::kCrashed) == v1::OUTCOME_CRASHED);
static_assert(static_cast<int>(LanderOutcome::kOutOfBounds) ==
              v1::OUTCOME_OUT_OF_BOUNDS);
static_assert(static_cast<int>(LanderOutcome::kTruncated) ==
              v1::OUTCOME_TRUNCATED);
static_assert(static_cast<int>(LanderOutcome::kAborted) == v1::OUTCOME_ABORTED);

absl::string_view LanderOutcomeName(LanderOutcome outcome) {
  return internal::OutcomeName(static_cast<int>(outcome));
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
    : transport_(std::move(transport)), info_(std::move(info)), owned_(owned) {
  transport_->Hold(info_.name, info_.idle_timeout_s);
}

RemoteEnv::RemoteEnv(RemoteEnv&& other) noexcept
    : transport_(std::move(other.transport_)),
      info_(std::move(other.info_)),
      owned_(std::exchange(other.owned_, false)),
      aec_(std::move(other.aec_)) {}

RemoteEnv& RemoteEnv::operator=(RemoteEnv&& other) noexcept {
  if (this != &other) {
    if (owned_) (void)Delete();
    if (transport_ != nullptr) transport_->Unhold(info_.name);
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
  if (transport_ != nullptr) transport_->Unhold(info_.name);
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
      internal::DecodeAecState(response.reset_env().aec());
  if (!aec.ok()) return aec.status();
  absl::StatusOr<StepData> data =
      internal::DecodeStepData(response.reset_env().data());
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
      internal::EncodeActions(actions, step.mutable_actions());
  if (!status.ok()) return status;
  v1::SessionResponse response;
  status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  return internal::DecodeStepData(response.step_env().data());
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
      internal::EncodeAgentAction(move.continuous,
                                  step.mutable_action()->mutable_continuous());
      break;
  }
  v1::SessionResponse response;
  absl::Status status = transport_->Call(request, &response);
  if (!status.ok()) return status;
  absl::StatusOr<AecState> aec =
      internal::DecodeAecState(response.step_agent().aec());
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
  return internal::DecodeFrame(response.frame());
}

absl::StatusOr<EnvInfo> RemoteEnv::Refresh() {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError(
        "Refresh on an empty RemoteEnv handle");
  }
  absl::StatusOr<EnvInfo> info =
      GetEnvOn(*transport_, info_.name, info_.server);
  if (info.ok()) info_ = *info;
  return info;
}

absl::Status RemoteEnv::Delete() {
  if (transport_ == nullptr) {
    return absl::FailedPreconditionError("Delete on an empty RemoteEnv handle");
  }
  absl::Status status = DeleteEnvOn(*transport_, info_.name);
  transport_->Unhold(info_.name);
  transport_ = nullptr;
  owned_ = false;
  return status;
}

std::string RemoteEnv::Release() {
  owned_ = false;
  return info_.name;
}

// ------------------------------------------------------------------- Client

Client::Client(std::vector<std::shared_ptr<Transport>> transports)
    : transports_(std::move(transports)) {}
Client::Client(Client&&) noexcept = default;
Client& Client::operator=(Client&&) noexcept = default;
Client::~Client() = default;

absl::StatusOr<Client> Client::Create(absl::string_view address,
                                      const ClientOptions& options) {
  return Create(std::vector<std::string>{std::string(address)}, options);
}

absl::StatusOr<Client> Client::Create(const std::vector<std::string>& addresses,
                                      const ClientOptions& options) {
  if (addresses.empty()) {
    return absl::InvalidArgumentError(
        "addresses is empty; expected at least one host:port");
  }
  if (options.rediscover_interval.count() < 0) {
    return absl::InvalidArgumentError(absl::StrCat(
        "rediscover_interval is ", options.rediscover_interval.count(),
        " ms; allowed: 0 (never) or more"));
  }
  // A message about addresses[i] says which entry when there are several.
  const auto about = [&](size_t i, const absl::Status& status) {
    if (addresses.size() == 1) return status;
    return absl::Status(status.code(),
                        absl::StrCat("addresses[", i, "]: ", status.message()));
  };
  absl::flat_hash_set<std::string> seen;
  std::vector<internal::AddressEntry> entries;
  for (size_t i = 0; i < addresses.size(); ++i) {
    // Two entries for one server would make names ambiguous and double its
    // share of the placement.
    if (!seen.insert(addresses[i]).second) {
      return absl::InvalidArgumentError(
          absl::StrCat("addresses[", i, "] is \"", addresses[i],
                       "\", which appears earlier; each server once"));
    }
    absl::StatusOr<internal::AddressEntry> entry =
        internal::ParseAddressEntry(addresses[i]);
    if (!entry.ok()) return about(i, entry.status());
    entries.push_back(*std::move(entry));
  }
  std::vector<absl::Status> failures;
  absl::StatusOr<std::vector<internal::Endpoint>> endpoints =
      internal::ResolveEntries(entries, &failures);
  for (size_t i = 0; i < failures.size(); ++i) {
    if (!failures[i].ok()) return about(i, failures[i]);
  }
  std::vector<std::shared_ptr<Transport>> transports;
  for (const internal::Endpoint& endpoint : *endpoints) {
    absl::StatusOr<std::shared_ptr<Transport>> transport =
        internal::MakeUnaryTransport(
            endpoint.address,
            internal::EndpointOptions(entries[endpoint.entry], options));
    if (!transport.ok()) return about(endpoint.entry, transport.status());
    transports.push_back(*std::move(transport));
  }
  Client client(std::move(transports));
  client.entries_ = addresses;
  client.options_ = options;
  return client;
}

absl::StatusOr<Client> Client::OpenSession() const {
  std::vector<std::shared_ptr<Transport>> sessions;
  for (const std::shared_ptr<Transport>& transport : transports_) {
    absl::StatusOr<std::shared_ptr<Transport>> session =
        transport->OpenSession();
    if (!session.ok()) return session.status();
    sessions.push_back(*std::move(session));
  }
  Client client(std::move(sessions));
  client.entries_ = entries_;
  client.options_ = options_;
  return client;
}

bool Client::is_session() const { return transports_.front()->is_session(); }

const std::string& Client::address(int server) const {
  return transports_.at(static_cast<size_t>(server))->address();
}

absl::Status Client::CheckHealth(absl::string_view service) const {
  for (const std::shared_ptr<Transport>& transport : transports_) {
    absl::Status status = transport->CheckHealth(service);
    if (!status.ok()) {
      return transports_.size() == 1 ? status : AtServer(*transport, status);
    }
  }
  return absl::OkStatus();
}

absl::StatusOr<RemoteEnv> Client::CreateEnv(const RemoteEnvConfig& config,
                                            bool detached) const {
  if (transports_.size() == 1) return CreateEnvAt(0, config, detached);
  // The least-loaded server by what each reports now (PlanPlacement, the
  // rule of VectorEnv's placement). One that does not answer (e.g. a name's
  // IPv6 address where the server listens on IPv4 only, or a pod not up
  // yet) or refuses (RESOURCE_EXHAUSTED: full, or this token's quota there)
  // is passed over for the next; its error, naming it, when none is left.
  std::vector<internal::ServerCapacity> capacity(transports_.size());
  absl::StatusOr<RemoteEnv> env = absl::UnavailableError("no server");
  for (size_t server = 0; server < transports_.size(); ++server) {
    absl::StatusOr<v1::ServerInfo> info =
        transports_[server]->ServerInfo(/*fresh=*/true);
    if (info.ok()) {
      capacity[server] =
          internal::CapacityOf(internal::DecodeServerInfo(*info));
    } else {
      capacity[server].usable = false;
      env = AtServer(*transports_[server], info.status());
    }
  }
  for (size_t tried = 0; tried < transports_.size(); ++tried) {
    const std::vector<int> plan = internal::PlanPlacement(capacity, 1);
    const auto chosen = std::find(plan.begin(), plan.end(), 1);
    if (chosen == plan.end()) break;
    const size_t server = static_cast<size_t>(chosen - plan.begin());
    env = CreateEnvAt(server, config, detached);
    if (env.ok()) return env;
    env = AtServer(*transports_[server], env.status());
    if (!absl::IsUnavailable(env.status()) &&
        !absl::IsResourceExhausted(env.status())) {
      return env;
    }
    capacity[server].usable = false;
  }
  return env;
}

absl::StatusOr<RemoteEnv> Client::CreateEnvOn(int server,
                                              const RemoteEnvConfig& config,
                                              bool detached) const {
  if (server < 0 || server >= server_count()) {
    return absl::InvalidArgumentError(
        absl::StrCat("server is ", server, "; allowed: 0..", server_count() - 1,
                     " (one per address)"));
  }
  return CreateEnvAt(static_cast<size_t>(server), config, detached);
}

absl::StatusOr<RemoteEnv> Client::CreateEnvAt(size_t server,
                                              const RemoteEnvConfig& config,
                                              bool detached) const {
  // Asked once per connection: a server this client cannot use is refused
  // before anything is created on it.
  const int index = static_cast<int>(server);
  absl::StatusOr<ServerInfo> server_info = GetServerInfo(index);
  if (!server_info.ok()) return server_info.status();
  absl::Status compatible = CheckCompatible(*server_info, address(index));
  if (!compatible.ok()) return compatible;
  v1::SessionRequest request;
  v1::CreateEnvRequest& create = *request.mutable_create_env();
  internal::EncodeConfig(config, create.mutable_config());
  create.set_detached(detached);
  v1::SessionResponse response;
  absl::Status status = transports_[server]->Call(request, &response);
  if (!status.ok()) return status;
  EnvInfo info = internal::DecodeEnv(response.env());
  info.server = static_cast<int>(server);
  return RemoteEnv(transports_[server], std::move(info), /*owned=*/true);
}

absl::StatusOr<RemoteEnv> Client::Attach(absl::string_view name) const {
  absl::StatusOr<EnvInfo> info = GetEnv(name);
  if (!info.ok()) return info.status();
  const size_t server = static_cast<size_t>(info->server);
  return RemoteEnv(transports_[server], *std::move(info), /*owned=*/false);
}

absl::StatusOr<EnvInfo> Client::GetEnv(absl::string_view name) const {
  absl::StatusOr<EnvInfo> info;
  for (size_t server = 0; server < transports_.size(); ++server) {
    info = GetEnvOn(*transports_[server], name, static_cast<int>(server));
    if (info.status().code() != absl::StatusCode::kNotFound) break;
  }
  return info;
}

absl::StatusOr<std::vector<EnvInfo>> Client::ListEnvs() const {
  std::vector<EnvInfo> envs;
  for (size_t server = 0; server < transports_.size(); ++server) {
    v1::ListEnvsRequest request;
    request.set_page_size(1000);
    do {
      v1::ListEnvsResponse response;
      absl::Status status = transports_[server]->ListEnvs(request, &response);
      if (!status.ok()) {
        return transports_.size() == 1 ? status
                                       : AtServer(*transports_[server], status);
      }
      for (const v1::Env& env : response.envs()) {
        envs.push_back(internal::DecodeEnv(env));
        envs.back().server = static_cast<int>(server);
      }
      request.set_page_token(response.next_page_token());
    } while (!request.page_token().empty());
  }
  return envs;
}

absl::Status Client::DeleteEnv(absl::string_view name) const {
  absl::Status status;
  for (const std::shared_ptr<Transport>& transport : transports_) {
    status = DeleteEnvOn(*transport, name);
    if (status.code() != absl::StatusCode::kNotFound) break;
  }
  return status;
}

absl::StatusOr<size_t> Client::ServerOf(const RemoteEnv* env,
                                        absl::string_view what) const {
  if (env == nullptr || env->transport_ == nullptr || env->name().empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat(what, " is not a live RemoteEnv handle"));
  }
  // With one server, any handle's name goes there (as it always has).
  if (transports_.size() == 1) return 0;
  for (size_t server = 0; server < transports_.size(); ++server) {
    if (transports_[server]->address() == env->transport_->address()) {
      return server;
    }
  }
  return absl::InvalidArgumentError(absl::StrCat(
      what, " (", env->name(), ") lives on ", env->transport_->address(),
      ", which is not one of this client's servers"));
}

absl::StatusOr<std::vector<absl::StatusOr<StepData>>> Client::StepBatch(
    absl::Span<const BatchStep> steps) const {
  // One request per server, and where each of the caller's items went.
  struct ServerCall {
    v1::SessionRequest request;
    v1::SessionResponse response;
    std::vector<size_t> items;
    absl::Status status;
  };
  std::vector<ServerCall> calls(transports_.size());
  for (size_t i = 0; i < steps.size(); ++i) {
    absl::StatusOr<size_t> server =
        ServerOf(steps[i].env, absl::StrCat("steps[", i, "].env"));
    if (!server.ok()) return server.status();
    ServerCall& call = calls[*server];
    v1::StepEnvRequest& step = *call.request.mutable_step_batch()->add_steps();
    step.set_name(steps[i].env->name());
    absl::Status status =
        internal::EncodeActions(steps[i].actions, step.mutable_actions());
    if (!status.ok()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "steps[", i, "] (", steps[i].env->name(), "): ", status.message()));
    }
    call.items.push_back(i);
  }

  // Every server's call in flight at once; the last one runs in this thread.
  std::vector<size_t> busy;
  for (size_t server = 0; server < calls.size(); ++server) {
    if (!calls[server].items.empty()) busy.push_back(server);
  }
  // An empty batch still makes one (empty) call, as a single server always
  // has: the server's answer checks that it is there.
  if (busy.empty()) {
    busy.push_back(0);
    calls[0].request.mutable_step_batch();
  }
  std::vector<std::future<absl::Status>> pending;
  for (size_t k = 0; k + 1 < busy.size(); ++k) {
    ServerCall& call = calls[busy[k]];
    pending.push_back(
        transports_[busy[k]]->CallAsync(call.request, &call.response));
  }
  ServerCall& last = calls[busy.back()];
  last.status = transports_[busy.back()]->Call(last.request, &last.response);
  for (size_t k = 0; k < pending.size(); ++k) {
    calls[busy[k]].status = pending[k].get();
  }

  std::vector<absl::StatusOr<StepData>> out(steps.size());
  absl::Status first_failure;
  bool any_answered = false;
  for (size_t server : busy) {
    ServerCall& call = calls[server];
    if (!call.status.ok()) {
      if (transports_.size() > 1) {
        call.status = AtServer(*transports_[server], call.status);
      }
      if (first_failure.ok()) first_failure = call.status;
      for (size_t item : call.items) out[item] = call.status;
      continue;
    }
    any_answered = true;
    const auto& results = call.response.step_batch().results();
    if (results.size() != static_cast<int>(call.items.size())) {
      return absl::InternalError(
          absl::StrCat("StepBatch sent ", call.items.size(), " steps to ",
                       transports_[server]->address(), " and received ",
                       results.size(), " results"));
    }
    for (size_t k = 0; k < call.items.size(); ++k) {
      const v1::StepBatchResult& result = results[static_cast<int>(k)];
      out[call.items[k]] = result.has_error()
                               ? absl::StatusOr<StepData>(
                                     internal::FromItemError(result.error()))
                               : internal::DecodeStepData(result.data());
    }
  }
  if (!any_answered) return first_failure;
  return out;
}

}  // namespace mll::client

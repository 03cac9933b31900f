#include "mll/vector_env.h"

#include <cstring>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "absl/strings/str_cat.h"
#include "transport.h"
#include "wire.h"

namespace mll::client {

using internal::StreamTransport;

namespace {

constexpr int kMaxVectorEnvs = 65536;

// Every request of `requests` sent on `transport` before any answer is
// awaited (pipelined), then the answers in order; the first failure, with the
// others still received.
absl::Status CallPipelined(StreamTransport& transport,
                           std::vector<v1::SessionRequest>& requests,
                           std::vector<v1::SessionResponse>* responses) {
  responses->assign(requests.size(), v1::SessionResponse());
  std::vector<absl::StatusOr<uint64_t>> sequences;
  sequences.reserve(requests.size());
  for (v1::SessionRequest& request : requests) {
    sequences.push_back(transport.Send(request));
  }
  absl::Status first = absl::OkStatus();
  for (size_t k = 0; k < requests.size(); ++k) {
    absl::Status status = sequences[k].status();
    if (status.ok())
      status = transport.Receive(*sequences[k], &(*responses)[k]);
    if (first.ok()) first = status;
  }
  return first;
}

// One server's share: env rows `rows` (env i on server i mod S), and its
// packed StepBatch request, built once, of which each step replaces only the
// action bytes.
struct Shard {
  StreamTransport* transport = nullptr;
  std::vector<int> rows;
  v1::SessionRequest request;
  v1::SessionResponse response;
};

}  // namespace

struct VectorEnv::State {
  explicit State(Client session_client) : session(std::move(session_client)) {}
  // Unholds the leases; the envs created on the session's streams go with
  // the streams (when `session` goes, after this).
  ~State() {
    for (size_t i = 0; i < names.size(); ++i) {
      shards[i % shards.size()].transport->Unhold(names[i]);
    }
  }

  Client session;
  std::vector<Shard> shards;
  std::vector<std::string> names;
  int n_landers = 0;
  bool continuous = false;

  std::vector<float> observations;
  std::vector<float> rewards;
  std::vector<uint8_t> terminations;
  std::vector<uint8_t> truncations;
  std::vector<uint8_t> active;
  std::vector<uint8_t> outcomes;
  std::vector<float> episode_returns;
  std::vector<int32_t> episode_lengths;
  std::vector<uint8_t> auto_reset;
  std::vector<uint8_t> episode_over;

  int num_envs() const { return static_cast<int>(names.size()); }

  // Sizes the result arrays for num_envs() envs of n_landers.
  void SizeResults() {
    const size_t rows = names.size() * static_cast<size_t>(n_landers);
    observations.assign(rows * kRemoteObservationSize, 0.0f);
    rewards.assign(rows, 0.0f);
    terminations.assign(rows, 0);
    truncations.assign(rows, 0);
    active.assign(rows, 0);
    outcomes.assign(rows, 0);
    episode_returns.assign(rows, 0.0f);
    episode_lengths.assign(rows, 0);
    auto_reset.assign(names.size(), 0);
    episode_over.assign(names.size(), 0);
  }

  // Marks the rows that carry a transition: stepped (already in `active`)
  // and not an auto-reset.
  void MaskAutoResetRows() {
    for (int env = 0; env < num_envs(); ++env) {
      if (!auto_reset[env]) continue;
      std::memset(active.data() + static_cast<size_t>(env) * n_landers, 0,
                  n_landers);
    }
  }
};

VectorEnv::VectorEnv(std::unique_ptr<State> state) : state_(std::move(state)) {}
VectorEnv::VectorEnv(VectorEnv&&) noexcept = default;
VectorEnv& VectorEnv::operator=(VectorEnv&&) noexcept = default;
VectorEnv::~VectorEnv() = default;

absl::StatusOr<VectorEnv> VectorEnv::Create(const Client& client, int num_envs,
                                            RemoteEnvConfig config) {
  if (num_envs < 1 || num_envs > kMaxVectorEnvs) {
    return absl::InvalidArgumentError(absl::StrCat(
        "num_envs is ", num_envs, "; allowed: 1..", kMaxVectorEnvs));
  }
  absl::StatusOr<Client> session = client.OpenSession();
  if (!session.ok()) return session.status();
  config.auto_reset = true;
  const size_t servers =
      std::min<size_t>(session->transports_.size(), num_envs);
  std::vector<EnvInfo> infos(num_envs);
  absl::Status failure = absl::OkStatus();
  for (size_t server = 0; server < servers; ++server) {
    auto& transport =
        static_cast<StreamTransport&>(*session->transports_[server]);
    std::vector<v1::SessionRequest> requests;
    for (int env = static_cast<int>(server); env < num_envs;
         env += static_cast<int>(servers)) {
      internal::EncodeConfig(
          config,
          requests.emplace_back().mutable_create_env()->mutable_config());
    }
    std::vector<v1::SessionResponse> responses;
    absl::Status status = CallPipelined(transport, requests, &responses);
    if (failure.ok()) failure = status;
    for (size_t k = 0; k < responses.size(); ++k) {
      infos[server + k * servers] = internal::DecodeEnv(responses[k].env());
      infos[server + k * servers].server = static_cast<int>(server);
    }
  }
  // A failure leaves what was made to the session's end.
  if (!failure.ok()) return failure;
  return Assemble(*std::move(session), std::move(infos));
}

absl::StatusOr<VectorEnv> VectorEnv::Attach(
    const Client& client, const std::vector<std::string>& names) {
  if (names.empty() || names.size() > kMaxVectorEnvs) {
    return absl::InvalidArgumentError(absl::StrCat(
        "names has ", names.size(), " entries; allowed: 1..", kMaxVectorEnvs));
  }
  absl::StatusOr<Client> session = client.OpenSession();
  if (!session.ok()) return session.status();
  std::vector<EnvInfo> infos;
  for (const std::string& name : names) {
    absl::StatusOr<EnvInfo> info = session->GetEnv(name);
    if (!info.ok()) return info.status();
    if (!infos.empty() && (info->n_landers() != infos[0].n_landers() ||
                           info->continuous() != infos[0].continuous())) {
      return absl::InvalidArgumentError(
          absl::StrCat("names[", infos.size(), "] (", name, ") has n_landers ",
                       info->n_landers(), " and ",
                       info->continuous() ? "continuous" : "discrete",
                       " actions; allowed: those of names[0] (", infos[0].name,
                       "): ", infos[0].n_landers(), ", ",
                       infos[0].continuous() ? "continuous" : "discrete"));
    }
    infos.push_back(*std::move(info));
  }
  // Each env stays on the server that has it; the packed batches are per
  // server, so env i must be on server i mod S as for Create.
  const int servers =
      std::min(session->server_count(), static_cast<int>(names.size()));
  for (size_t i = 0; i < infos.size(); ++i) {
    if (infos[i].server != static_cast<int>(i) % servers) {
      return absl::InvalidArgumentError(
          absl::StrCat("names[", i, "] (", names[i], ") is on server ",
                       session->address(infos[i].server),
                       "; allowed: env i on server i mod ", servers, " (",
                       session->address(static_cast<int>(i) % servers), ")"));
    }
  }
  return Assemble(*std::move(session), std::move(infos));
}

// Created envs are bound to the session (they go with its streams);
// attached ones are not.
absl::StatusOr<VectorEnv> VectorEnv::Assemble(Client session,
                                              std::vector<EnvInfo> infos) {
  auto state = std::make_unique<State>(std::move(session));
  state->n_landers = infos[0].n_landers();
  state->continuous = infos[0].continuous();
  const int servers =
      std::min(state->session.server_count(), static_cast<int>(infos.size()));
  state->shards.resize(servers);
  for (int server = 0; server < servers; ++server) {
    Shard& shard = state->shards[server];
    shard.transport =
        static_cast<StreamTransport*>(state->session.transports_[server].get());
    v1::PackedSteps* packed =
        shard.request.mutable_step_batch()->mutable_packed();
    v1::Array* actions = packed->mutable_actions();
    actions->set_dtype(state->continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32);
    for (size_t env = server; env < infos.size(); env += servers) {
      shard.rows.push_back(static_cast<int>(env));
      packed->add_names(infos[env].name);
    }
    actions->add_shape(static_cast<int>(shard.rows.size()));
    actions->add_shape(state->n_landers);
    if (state->continuous) actions->add_shape(kRemoteContinuousActionSize);
  }
  for (size_t env = 0; env < infos.size(); ++env) {
    state->names.push_back(infos[env].name);
    state->shards[env % servers].transport->Hold(infos[env].name,
                                                 infos[env].idle_timeout_s);
  }
  state->SizeResults();
  return VectorEnv(std::move(state));
}

int VectorEnv::num_envs() const { return state_->num_envs(); }
int VectorEnv::n_landers() const { return state_->n_landers; }
bool VectorEnv::continuous() const { return state_->continuous; }
const std::vector<std::string>& VectorEnv::names() const {
  return state_->names;
}

std::string VectorEnv::address(int env) const {
  return state_->shards[env % state_->shards.size()].transport->address();
}

std::string VectorEnv::transport() {
  for (Shard& shard : state_->shards) {
    if (shard.transport->transport_name() != "shared_memory") return "native";
  }
  return "shared_memory";
}

absl::Status VectorEnv::Reset(std::optional<uint64_t> seed) {
  if (!seed.has_value()) return Reset(absl::Span<const uint64_t>());
  std::vector<uint64_t> seeds(num_envs());
  for (int env = 0; env < num_envs(); ++env) seeds[env] = *seed + env;
  return Reset(absl::MakeConstSpan(seeds));
}

absl::Status VectorEnv::Reset(absl::Span<const uint64_t> seeds) {
  State& state = *state_;
  // Empty from Reset(nullopt): no reseed.
  if (!seeds.empty() && seeds.size() != state.names.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("seeds has ", seeds.size(),
                     " entries; expected num_envs = ", state.names.size()));
  }
  const int n = state.n_landers;
  absl::Status first = absl::OkStatus();
  // Every shard's resets are in flight before any answer is awaited.
  std::vector<std::vector<v1::SessionRequest>> requests(state.shards.size());
  std::vector<std::vector<absl::StatusOr<uint64_t>>> sequences(
      state.shards.size());
  for (size_t s = 0; s < state.shards.size(); ++s) {
    Shard& shard = state.shards[s];
    for (int env : shard.rows) {
      v1::ResetEnvRequest* reset =
          requests[s].emplace_back().mutable_reset_env();
      reset->set_name(state.names[env]);
      if (!seeds.empty()) reset->set_seed(seeds[env]);
    }
    for (v1::SessionRequest& request : requests[s]) {
      sequences[s].push_back(shard.transport->Send(request));
    }
  }
  for (size_t s = 0; s < state.shards.size(); ++s) {
    Shard& shard = state.shards[s];
    for (size_t k = 0; k < shard.rows.size(); ++k) {
      const int env = shard.rows[k];
      v1::SessionResponse response;
      absl::Status status = sequences[s][k].status();
      if (status.ok()) {
        status = shard.transport->Receive(*sequences[s][k], &response);
      }
      absl::StatusOr<StepData> data =
          status.ok() ? internal::DecodeStepData(response.reset_env().data())
                      : absl::StatusOr<StepData>(status);
      if (!data.ok()) {
        if (first.ok()) {
          first = absl::Status(data.status().code(),
                               absl::StrCat("env ", env, " (", state.names[env],
                                            "): ", data.status().message()));
        }
        continue;
      }
      const size_t row = static_cast<size_t>(env) * n;
      std::memcpy(&state.observations[row * kRemoteObservationSize],
                  data->observations.data(),
                  data->observations.size() * sizeof(float));
      for (int a = 0; a < n; ++a) {
        state.rewards[row + a] = data->rewards[a];
        state.terminations[row + a] = data->terminations[a];
        state.truncations[row + a] = data->truncations[a];
        state.active[row + a] = data->stepped[a];
        state.outcomes[row + a] = static_cast<uint8_t>(data->outcomes[a]);
        state.episode_returns[row + a] = data->episode_returns[a];
        state.episode_lengths[row + a] = data->episode_lengths[a];
      }
      state.auto_reset[env] = data->auto_reset;
      state.episode_over[env] = data->episode_over;
    }
  }
  state.MaskAutoResetRows();
  return first;
}

absl::Status VectorEnv::Step(absl::Span<const int32_t> discrete_actions) {
  return StepWith(
      absl::string_view(reinterpret_cast<const char*>(discrete_actions.data()),
                        discrete_actions.size() * sizeof(int32_t)),
      discrete_actions.size(), /*continuous_actions=*/false);
}

absl::Status VectorEnv::Step(absl::Span<const float> continuous_actions) {
  return StepWith(absl::string_view(
                      reinterpret_cast<const char*>(continuous_actions.data()),
                      continuous_actions.size() * sizeof(float)),
                  continuous_actions.size(), /*continuous_actions=*/true);
}

namespace {

// Copies a packed column's rows (`width` elements each) into `out` at the
// shard's env rows; INTERNAL when the column has the wrong dtype or shape.
template <typename T>
absl::Status Scatter(const v1::Array& column, absl::string_view field,
                     v1::DType dtype, const std::vector<int>& rows,
                     std::vector<int> shape, size_t width, T* out) {
  absl::Status status = internal::CheckColumn(column, field, dtype, sizeof(T),
                                              absl::MakeConstSpan(shape));
  if (!status.ok()) return status;
  const char* data = column.data().data();
  const size_t row_bytes = width * sizeof(T);
  if (rows.size() == 1 || (rows.size() > 1 && rows[1] == rows[0] + 1)) {
    // One server: the rows are contiguous.
    std::memcpy(out + rows[0] * width, data, rows.size() * row_bytes);
    return absl::OkStatus();
  }
  for (size_t k = 0; k < rows.size(); ++k) {
    std::memcpy(out + rows[k] * width, data + k * row_bytes, row_bytes);
  }
  return absl::OkStatus();
}

}  // namespace

absl::Status VectorEnv::StepWith(absl::string_view action_bytes, size_t count,
                                 bool continuous_actions) {
  State& state = *state_;
  const int n = state.n_landers;
  const size_t per_env =
      n * (continuous_actions ? kRemoteContinuousActionSize : 1);
  if (continuous_actions != state.continuous) {
    return absl::InvalidArgumentError(absl::StrCat(
        "actions are ", continuous_actions ? "continuous" : "discrete",
        "; the envs take ", state.continuous ? "continuous" : "discrete",
        " actions"));
  }
  if (count != per_env * state.names.size()) {
    return absl::InvalidArgumentError(absl::StrCat(
        "actions has ", count, " values; expected num_envs * n_landers",
        continuous_actions ? " * 2" : "", " = ", per_env * state.names.size()));
  }
  const size_t env_bytes = action_bytes.size() / state.names.size();
  for (Shard& shard : state.shards) {
    std::string* data = shard.request.mutable_step_batch()
                            ->mutable_packed()
                            ->mutable_actions()
                            ->mutable_data();
    data->resize(shard.rows.size() * env_bytes);
    for (size_t k = 0; k < shard.rows.size(); ++k) {
      std::memcpy(data->data() + k * env_bytes,
                  action_bytes.data() + shard.rows[k] * env_bytes, env_bytes);
    }
  }
  // One packed StepBatch per server, all in flight at once.
  std::vector<absl::StatusOr<uint64_t>> sequences;
  for (Shard& shard : state.shards) {
    sequences.push_back(shard.transport->Send(shard.request));
  }
  absl::Status failure = absl::OkStatus();
  int failed_env = state.num_envs();
  for (size_t s = 0; s < state.shards.size(); ++s) {
    Shard& shard = state.shards[s];
    absl::Status status = sequences[s].status();
    if (status.ok()) {
      status = shard.transport->Receive(*sequences[s], &shard.response);
    }
    if (status.ok() && !shard.response.step_batch().has_packed()) {
      status = absl::UnimplementedError(absl::StrCat(
          shard.transport->address(),
          " answered a packed StepBatch without packed results; its "
          "mll_server predates StepBatchRequest.packed: upgrade it"));
    }
    if (!status.ok()) {
      // A server's failure: the first server in order reports it.
      if (failed_env > shard.rows[0]) {
        failure = status;
        failed_env = shard.rows[0];
      }
      continue;
    }
    const v1::PackedStepData& packed = shard.response.step_batch().packed();
    const int rows = static_cast<int>(shard.rows.size());
    absl::Status decoded =
        Scatter(packed.observations(), "observations", v1::DTYPE_FLOAT32,
                shard.rows, {rows, n, kRemoteObservationSize},
                n * kRemoteObservationSize, state.observations.data());
    const auto agent_column = [&](const v1::Array& column,
                                  absl::string_view field, v1::DType dtype,
                                  auto* out) {
      if (decoded.ok()) {
        decoded = Scatter(column, field, dtype, shard.rows, {rows, n},
                          static_cast<size_t>(n), out);
      }
    };
    agent_column(packed.rewards(), "rewards", v1::DTYPE_FLOAT32,
                 state.rewards.data());
    agent_column(packed.terminations(), "terminations", v1::DTYPE_UINT8,
                 state.terminations.data());
    agent_column(packed.truncations(), "truncations", v1::DTYPE_UINT8,
                 state.truncations.data());
    agent_column(packed.stepped(), "stepped", v1::DTYPE_UINT8,
                 state.active.data());
    agent_column(packed.outcomes(), "outcomes", v1::DTYPE_UINT8,
                 state.outcomes.data());
    agent_column(packed.episode_returns(), "episode_returns", v1::DTYPE_FLOAT32,
                 state.episode_returns.data());
    agent_column(packed.episode_lengths(), "episode_lengths", v1::DTYPE_INT32,
                 state.episode_lengths.data());
    if (decoded.ok()) {
      decoded = Scatter(packed.auto_reset(), "auto_reset", v1::DTYPE_UINT8,
                        shard.rows, {rows}, 1, state.auto_reset.data());
    }
    if (decoded.ok()) {
      decoded = Scatter(packed.episode_over(), "episode_over", v1::DTYPE_UINT8,
                        shard.rows, {rows}, 1, state.episode_over.data());
    }
    if (!decoded.ok() && failed_env > shard.rows[0]) {
      failure = decoded;
      failed_env = shard.rows[0];
    }
    for (const v1::IndexedItemError& item : packed.errors()) {
      if (item.index() < 0 || item.index() >= rows) {
        return absl::InternalError(absl::StrCat(
            shard.transport->address(), " reported an error for row ",
            item.index(), " of a packed StepBatch of ", rows, " envs"));
      }
      const int env = shard.rows[item.index()];
      if (env < failed_env) {
        failed_env = env;
        const absl::Status error = internal::FromItemError(item.error());
        failure = absl::Status(error.code(),
                               absl::StrCat("env ", env, " (", state.names[env],
                                            "): ", error.message()));
      }
    }
  }
  state.MaskAutoResetRows();
  return failure;
}

absl::Span<const float> VectorEnv::observations() const {
  return state_->observations;
}
absl::Span<const float> VectorEnv::rewards() const { return state_->rewards; }
absl::Span<const uint8_t> VectorEnv::terminations() const {
  return state_->terminations;
}
absl::Span<const uint8_t> VectorEnv::truncations() const {
  return state_->truncations;
}
absl::Span<const uint8_t> VectorEnv::active() const { return state_->active; }
absl::Span<const uint8_t> VectorEnv::outcomes() const {
  return state_->outcomes;
}
absl::Span<const float> VectorEnv::episode_returns() const {
  return state_->episode_returns;
}
absl::Span<const int32_t> VectorEnv::episode_lengths() const {
  return state_->episode_lengths;
}
absl::Span<const uint8_t> VectorEnv::auto_reset() const {
  return state_->auto_reset;
}
absl::Span<const uint8_t> VectorEnv::episode_over() const {
  return state_->episode_over;
}

StepData VectorEnv::EnvResult(int env) const {
  const State& state = *state_;
  const int n = state.n_landers;
  const size_t row = static_cast<size_t>(env) * n;
  const auto slice = [&](const auto& column) {
    return std::vector<typename std::decay_t<decltype(column)>::value_type>(
        column.begin() + row, column.begin() + row + n);
  };
  StepData data;
  data.n_landers = n;
  data.observations.assign(
      state.observations.begin() + row * kRemoteObservationSize,
      state.observations.begin() + (row + n) * kRemoteObservationSize);
  data.rewards = slice(state.rewards);
  data.terminations = slice(state.terminations);
  data.truncations = slice(state.truncations);
  data.stepped = slice(state.active);
  for (uint8_t outcome : slice(state.outcomes)) {
    data.outcomes.push_back(static_cast<LanderOutcome>(outcome));
  }
  data.episode_returns = slice(state.episode_returns);
  data.episode_lengths = slice(state.episode_lengths);
  data.episode_over = state.episode_over[env] != 0;
  data.auto_reset = state.auto_reset[env] != 0;
  return data;
}

}  // namespace mll::client

#include "mll/vector_env.h"

#include <algorithm>
#include <cstring>
#include <deque>
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

// Result columns of some envs (rows), env-major.
struct Columns {
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

  // `rows` rows of n landers, zero.
  void Resize(size_t rows, int n) {
    const size_t agents = rows * static_cast<size_t>(n);
    observations.assign(agents * kRemoteObservationSize, 0.0f);
    rewards.assign(agents, 0.0f);
    terminations.assign(agents, 0);
    truncations.assign(agents, 0);
    active.assign(agents, 0);
    outcomes.assign(agents, 0);
    episode_returns.assign(agents, 0.0f);
    episode_lengths.assign(agents, 0);
    auto_reset.assign(rows, 0);
    episode_over.assign(rows, 0);
  }

  // Marks the rows that carry a transition: stepped (already in `active`)
  // and not an auto-reset.
  void MaskAutoResetRows(int n) {
    for (size_t row = 0; row < auto_reset.size(); ++row) {
      if (auto_reset[row]) std::memset(active.data() + row * n, 0, n);
    }
  }

  // Row `from` of `source` into row `to`.
  void CopyRow(const Columns& source, size_t from, size_t to, int n) {
    const auto copy = [&](const auto& in, auto& out, size_t width) {
      std::copy(in.begin() + from * width, in.begin() + (from + 1) * width,
                out.begin() + to * width);
    };
    copy(source.observations, observations, n * kRemoteObservationSize);
    copy(source.rewards, rewards, n);
    copy(source.terminations, terminations, n);
    copy(source.truncations, truncations, n);
    copy(source.active, active, n);
    copy(source.outcomes, outcomes, n);
    copy(source.episode_returns, episode_returns, n);
    copy(source.episode_lengths, episode_lengths, n);
    copy(source.auto_reset, auto_reset, 1);
    copy(source.episode_over, episode_over, 1);
  }
};

// Results received by the async API and not yet returned by Recv: the env
// of each row, in the order they came.
struct ReadyChunk {
  std::vector<int> envs;
  Columns columns;
  size_t taken = 0;  // Rows already returned.
};

// An async request in flight: its server, sequence and envs.
struct PendingRequest {
  size_t shard = 0;
  uint64_t sequence = 0;
  std::vector<int> envs;
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

  // The latest results (num_envs rows after Reset and Step, batch_size rows
  // after Recv, whose envs are in `env_ids`).
  Columns results;
  std::vector<int> env_ids;

  // The async API: batch_size, which envs have a step (or AsyncReset) whose
  // results Recv has not returned, the requests in flight in send order, and
  // the results received and not yet returned.
  int batch_size = 0;
  std::vector<bool> in_flight;
  int in_flight_count = 0;
  std::deque<PendingRequest> pending;
  std::deque<ReadyChunk> ready;
  size_t ready_rows = 0;

  int num_envs() const { return static_cast<int>(names.size()); }
};

VectorEnv::VectorEnv(std::unique_ptr<State> state) : state_(std::move(state)) {}
VectorEnv::VectorEnv(VectorEnv&&) noexcept = default;
VectorEnv& VectorEnv::operator=(VectorEnv&&) noexcept = default;
VectorEnv::~VectorEnv() = default;

absl::StatusOr<VectorEnv> VectorEnv::Create(const Client& client, int num_envs,
                                            RemoteEnvConfig config,
                                            int batch_size) {
  if (num_envs < 1 || num_envs > kMaxVectorEnvs) {
    return absl::InvalidArgumentError(absl::StrCat(
        "num_envs is ", num_envs, "; allowed: 1..", kMaxVectorEnvs));
  }
  if (batch_size == 0) batch_size = num_envs;
  if (batch_size < 1 || batch_size > num_envs) {
    return absl::InvalidArgumentError(
        absl::StrCat("batch_size is ", batch_size,
                     "; allowed: 0 (num_envs) or 1..num_envs = 1..", num_envs));
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
  return Assemble(*std::move(session), std::move(infos), batch_size);
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
  return Assemble(*std::move(session), std::move(infos),
                  static_cast<int>(names.size()));
}

// Created envs are bound to the session (they go with its streams);
// attached ones are not.
absl::StatusOr<VectorEnv> VectorEnv::Assemble(Client session,
                                              std::vector<EnvInfo> infos,
                                              int batch_size) {
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
  state->results.Resize(infos.size(), state->n_landers);
  state->batch_size = batch_size;
  state->in_flight.assign(infos.size(), false);
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

absl::Status VectorEnv::CheckNothingInFlight() const {
  if (state_->in_flight_count == 0) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      state_->in_flight_count,
      " envs have a Send (or AsyncReset) whose results Recv has not "
      "returned; Recv them first"));
}

absl::Status VectorEnv::Reset(absl::Span<const uint64_t> seeds) {
  State& state = *state_;
  if (absl::Status status = CheckNothingInFlight(); !status.ok()) return status;
  // Empty from Reset(nullopt): no reseed.
  if (!seeds.empty() && seeds.size() != state.names.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("seeds has ", seeds.size(),
                     " entries; expected num_envs = ", state.names.size()));
  }
  const int n = state.n_landers;
  Columns& out = state.results;
  out.Resize(state.names.size(), n);
  absl::Status first = absl::OkStatus();
  // Every shard's resets are in flight before any answer is awaited.
  std::vector<std::vector<absl::StatusOr<uint64_t>>> sequences(
      state.shards.size());
  for (size_t s = 0; s < state.shards.size(); ++s) {
    Shard& shard = state.shards[s];
    for (int env : shard.rows) {
      v1::SessionRequest request;
      v1::ResetEnvRequest* reset = request.mutable_reset_env();
      reset->set_name(state.names[env]);
      if (!seeds.empty()) reset->set_seed(seeds[env]);
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
      std::memcpy(&out.observations[row * kRemoteObservationSize],
                  data->observations.data(),
                  data->observations.size() * sizeof(float));
      for (int a = 0; a < n; ++a) {
        out.rewards[row + a] = data->rewards[a];
        out.terminations[row + a] = data->terminations[a];
        out.truncations[row + a] = data->truncations[a];
        out.active[row + a] = data->stepped[a];
        out.outcomes[row + a] = static_cast<uint8_t>(data->outcomes[a]);
        out.episode_returns[row + a] = data->episode_returns[a];
        out.episode_lengths[row + a] = data->episode_lengths[a];
      }
      out.auto_reset[env] = data->auto_reset;
      out.episode_over[env] = data->episode_over;
    }
  }
  out.MaskAutoResetRows(n);
  state.env_ids.resize(state.names.size());
  for (int env = 0; env < num_envs(); ++env) state.env_ids[env] = env;
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

// Copies a packed column's rows (`width` elements each) into `out` at rows
// `rows` (row k of the column to row rows[k]); INTERNAL when the column has
// the wrong dtype or shape.
template <typename T>
absl::Status Scatter(const v1::Array& column, absl::string_view field,
                     v1::DType dtype, const std::vector<int>& rows,
                     std::vector<int> shape, size_t width, T* out) {
  absl::Status status = internal::CheckColumn(column, field, dtype, sizeof(T),
                                              absl::MakeConstSpan(shape));
  if (!status.ok()) return status;
  const char* data = column.data().data();
  const size_t row_bytes = width * sizeof(T);
  if (rows.size() == 1 ||
      (rows.size() > 1 &&
       rows.back() == rows[0] + static_cast<int>(rows.size()) - 1)) {
    // Consecutive rows (one server): one copy.
    std::memcpy(out + rows[0] * width, data, rows.size() * row_bytes);
    return absl::OkStatus();
  }
  for (size_t k = 0; k < rows.size(); ++k) {
    std::memcpy(out + rows[k] * width, data + k * row_bytes, row_bytes);
  }
  return absl::OkStatus();
}

// A packed StepBatch's results into `out` at rows `rows`; INTERNAL when a
// column has the wrong dtype or shape.
absl::Status DecodePacked(const v1::PackedStepData& packed,
                          const std::vector<int>& rows, int n, Columns* out) {
  const int count = static_cast<int>(rows.size());
  absl::Status status =
      Scatter(packed.observations(), "observations", v1::DTYPE_FLOAT32, rows,
              {count, n, kRemoteObservationSize}, n * kRemoteObservationSize,
              out->observations.data());
  const auto agent_column = [&](const v1::Array& column,
                                absl::string_view field, v1::DType dtype,
                                auto* into) {
    if (status.ok()) {
      status = Scatter(column, field, dtype, rows, {count, n},
                       static_cast<size_t>(n), into);
    }
  };
  agent_column(packed.rewards(), "rewards", v1::DTYPE_FLOAT32,
               out->rewards.data());
  agent_column(packed.terminations(), "terminations", v1::DTYPE_UINT8,
               out->terminations.data());
  agent_column(packed.truncations(), "truncations", v1::DTYPE_UINT8,
               out->truncations.data());
  agent_column(packed.stepped(), "stepped", v1::DTYPE_UINT8,
               out->active.data());
  agent_column(packed.outcomes(), "outcomes", v1::DTYPE_UINT8,
               out->outcomes.data());
  agent_column(packed.episode_returns(), "episode_returns", v1::DTYPE_FLOAT32,
               out->episode_returns.data());
  agent_column(packed.episode_lengths(), "episode_lengths", v1::DTYPE_INT32,
               out->episode_lengths.data());
  if (status.ok()) {
    status = Scatter(packed.auto_reset(), "auto_reset", v1::DTYPE_UINT8, rows,
                     {count}, 1, out->auto_reset.data());
  }
  if (status.ok()) {
    status = Scatter(packed.episode_over(), "episode_over", v1::DTYPE_UINT8,
                     rows, {count}, 1, out->episode_over.data());
  }
  return status;
}

// The packed results of `response` to a packed StepBatch of the envs `envs`
// (in request order), or the first env's failure in env order, that env in
// `*failed_env`: results missing (the request's first env), or an env's own
// error (prefixed "env {i} ({name}): ").
absl::StatusOr<const v1::PackedStepData*> PackedResults(
    const v1::SessionResponse& response, const std::vector<int>& envs,
    const std::vector<std::string>& names, const std::string& address,
    int* failed_env) {
  *failed_env = envs[0];
  if (!response.step_batch().has_packed()) {
    return absl::UnimplementedError(absl::StrCat(
        address,
        " answered a packed StepBatch without packed results; its mll_server "
        "predates StepBatchRequest.packed: upgrade it"));
  }
  const v1::PackedStepData& packed = response.step_batch().packed();
  const v1::IndexedItemError* first = nullptr;
  for (const v1::IndexedItemError& item : packed.errors()) {
    if (item.index() < 0 || item.index() >= static_cast<int>(envs.size())) {
      return absl::InternalError(
          absl::StrCat(address, " reported an error for row ", item.index(),
                       " of a packed StepBatch of ", envs.size(), " envs"));
    }
    if (first == nullptr || envs[item.index()] < envs[first->index()]) {
      first = &item;
    }
  }
  if (first != nullptr) {
    const int env = envs[first->index()];
    *failed_env = env;
    const absl::Status error = internal::FromItemError(first->error());
    return absl::Status(
        error.code(),
        absl::StrCat("env ", env, " (", names[env], "): ", error.message()));
  }
  return &packed;
}

}  // namespace

absl::Status VectorEnv::CheckActions(size_t count, bool continuous_actions,
                                     size_t envs) const {
  const State& state = *state_;
  if (continuous_actions != state.continuous) {
    return absl::InvalidArgumentError(absl::StrCat(
        "actions are ", continuous_actions ? "continuous" : "discrete",
        "; the envs take ", state.continuous ? "continuous" : "discrete",
        " actions"));
  }
  const size_t per_env =
      state.n_landers * (continuous_actions ? kRemoteContinuousActionSize : 1);
  if (count != per_env * envs) {
    return absl::InvalidArgumentError(
        absl::StrCat("actions has ", count, " values; expected ",
                     envs == state.names.size() ? "num_envs" : "len(env_ids)",
                     " * n_landers", continuous_actions ? " * 2" : "", " = ",
                     per_env * envs));
  }
  return absl::OkStatus();
}

absl::Status VectorEnv::StepWith(absl::string_view action_bytes, size_t count,
                                 bool continuous_actions) {
  State& state = *state_;
  if (absl::Status status = CheckNothingInFlight(); !status.ok()) return status;
  if (absl::Status status =
          CheckActions(count, continuous_actions, state.names.size());
      !status.ok()) {
    return status;
  }
  const int n = state.n_landers;
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
  Columns& out = state.results;
  out.Resize(state.names.size(), n);
  absl::Status failure = absl::OkStatus();
  int failed_env = state.num_envs();
  for (size_t s = 0; s < state.shards.size(); ++s) {
    Shard& shard = state.shards[s];
    absl::Status status = sequences[s].status();
    if (status.ok()) {
      status = shard.transport->Receive(*sequences[s], &shard.response);
    }
    // A server's failure counts as its first env's; an env's own error as
    // that env's. The first in env order is reported.
    int env = shard.rows[0];
    absl::StatusOr<const v1::PackedStepData*> packed =
        status.ok() ? PackedResults(shard.response, shard.rows, state.names,
                                    shard.transport->address(), &env)
                    : absl::StatusOr<const v1::PackedStepData*>(status);
    if (packed.ok()) {
      status = DecodePacked(**packed, shard.rows, n, &out);
    } else {
      status = packed.status();
    }
    if (!status.ok()) {
      if (env < failed_env) {
        failed_env = env;
        failure = status;
      }
    }
  }
  out.MaskAutoResetRows(n);
  state.env_ids.resize(state.names.size());
  for (int env = 0; env < num_envs(); ++env) state.env_ids[env] = env;
  return failure;
}

// ----------------------------------------------------- EnvPool's async API

int VectorEnv::batch_size() const { return state_->batch_size; }

absl::Status VectorEnv::AsyncReset(std::optional<uint64_t> seed) {
  State& state = *state_;
  absl::Status status = Reset(seed);
  if (!status.ok()) return status;
  ReadyChunk chunk;
  chunk.envs = state.env_ids;
  chunk.columns = state.results;
  std::fill(chunk.columns.active.begin(), chunk.columns.active.end(), 0);
  state.ready_rows += chunk.envs.size();
  state.ready.push_back(std::move(chunk));
  state.in_flight.assign(state.names.size(), true);
  state.in_flight_count = state.num_envs();
  return absl::OkStatus();
}

absl::Status VectorEnv::Send(absl::Span<const int32_t> discrete_actions,
                             absl::Span<const int> env_ids) {
  return SendWith(
      absl::string_view(reinterpret_cast<const char*>(discrete_actions.data()),
                        discrete_actions.size() * sizeof(int32_t)),
      discrete_actions.size(), /*continuous_actions=*/false, env_ids);
}

absl::Status VectorEnv::Send(absl::Span<const float> continuous_actions,
                             absl::Span<const int> env_ids) {
  return SendWith(absl::string_view(
                      reinterpret_cast<const char*>(continuous_actions.data()),
                      continuous_actions.size() * sizeof(float)),
                  continuous_actions.size(), /*continuous_actions=*/true,
                  env_ids);
}

absl::Status VectorEnv::SendWith(absl::string_view action_bytes, size_t count,
                                 bool continuous_actions,
                                 absl::Span<const int> env_ids) {
  State& state = *state_;
  if (env_ids.empty()) {
    return absl::InvalidArgumentError(
        "env_ids is empty; expected distinct env indices");
  }
  std::vector<bool> seen(state.names.size(), false);
  for (int env : env_ids) {
    if (env < 0 || env >= state.num_envs()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "env_ids holds ", env, "; allowed: 0..", state.num_envs() - 1));
    }
    if (seen[env]) {
      return absl::InvalidArgumentError(absl::StrCat(
          "env_ids holds ", env, " more than once; each env at most once"));
    }
    seen[env] = true;
    if (state.in_flight[env]) {
      return absl::FailedPreconditionError(absl::StrCat(
          "env ", env,
          " has a step in flight (sent, or reset by AsyncReset); Recv its "
          "result before sending it another"));
    }
  }
  if (absl::Status status =
          CheckActions(count, continuous_actions, env_ids.size());
      !status.ok()) {
    return status;
  }
  const size_t env_bytes = action_bytes.size() / env_ids.size();
  const size_t servers = state.shards.size();
  for (size_t s = 0; s < servers; ++s) {
    PendingRequest request{s, 0, {}};
    v1::SessionRequest message;
    v1::PackedSteps* packed = message.mutable_step_batch()->mutable_packed();
    std::string* data = packed->mutable_actions()->mutable_data();
    for (size_t k = 0; k < env_ids.size(); ++k) {
      const int env = env_ids[k];
      if (static_cast<size_t>(env) % servers != s) continue;
      request.envs.push_back(env);
      packed->add_names(state.names[env]);
      data->append(action_bytes.data() + k * env_bytes, env_bytes);
    }
    if (request.envs.empty()) continue;
    v1::Array* actions = packed->mutable_actions();
    actions->set_dtype(state.continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32);
    actions->add_shape(static_cast<int>(request.envs.size()));
    actions->add_shape(state.n_landers);
    if (state.continuous) actions->add_shape(kRemoteContinuousActionSize);
    absl::StatusOr<uint64_t> sequence =
        state.shards[s].transport->Send(message);
    if (!sequence.ok()) return sequence.status();
    request.sequence = *sequence;
    for (int env : request.envs) state.in_flight[env] = true;
    state.in_flight_count += static_cast<int>(request.envs.size());
    state.pending.push_back(std::move(request));
  }
  return absl::OkStatus();
}

absl::Status VectorEnv::ReceiveOne() {
  State& state = *state_;
  PendingRequest request = std::move(state.pending.front());
  state.pending.pop_front();
  Shard& shard = state.shards[request.shard];
  v1::SessionResponse response;
  absl::Status status = shard.transport->Receive(request.sequence, &response);
  int failed_env = 0;
  absl::StatusOr<const v1::PackedStepData*> packed =
      status.ok() ? PackedResults(response, request.envs, state.names,
                                  shard.transport->address(), &failed_env)
                  : absl::StatusOr<const v1::PackedStepData*>(status);
  ReadyChunk chunk;
  if (packed.ok()) {
    chunk.columns.Resize(request.envs.size(), state.n_landers);
    std::vector<int> rows(request.envs.size());
    for (size_t k = 0; k < rows.size(); ++k) rows[k] = static_cast<int>(k);
    status = DecodePacked(**packed, rows, state.n_landers, &chunk.columns);
  } else {
    status = packed.status();
  }
  if (!status.ok()) {
    // This request's envs are no longer in flight: their results are lost.
    for (int env : request.envs) state.in_flight[env] = false;
    state.in_flight_count -= static_cast<int>(request.envs.size());
    return status;
  }
  chunk.columns.MaskAutoResetRows(state.n_landers);
  chunk.envs = std::move(request.envs);
  state.ready_rows += chunk.envs.size();
  state.ready.push_back(std::move(chunk));
  return absl::OkStatus();
}

absl::Status VectorEnv::Recv() {
  State& state = *state_;
  if (state.in_flight_count < state.batch_size) {
    return absl::FailedPreconditionError(
        absl::StrCat("Recv needs batch_size = ", state.batch_size,
                     " envs with a step in flight; ", state.in_flight_count,
                     " have one (Send or AsyncReset first)"));
  }
  while (state.ready_rows < static_cast<size_t>(state.batch_size)) {
    if (absl::Status status = ReceiveOne(); !status.ok()) return status;
  }
  Columns& out = state.results;
  out.Resize(state.batch_size, state.n_landers);
  state.env_ids.resize(state.batch_size);
  for (int row = 0; row < state.batch_size; ++row) {
    ReadyChunk& chunk = state.ready.front();
    out.CopyRow(chunk.columns, chunk.taken, row, state.n_landers);
    const int env = chunk.envs[chunk.taken];
    state.env_ids[row] = env;
    state.in_flight[env] = false;
    if (++chunk.taken == chunk.envs.size()) state.ready.pop_front();
  }
  state.ready_rows -= state.batch_size;
  state.in_flight_count -= state.batch_size;
  return absl::OkStatus();
}

absl::Span<const int> VectorEnv::env_ids() const { return state_->env_ids; }

absl::Span<const float> VectorEnv::observations() const {
  return state_->results.observations;
}
absl::Span<const float> VectorEnv::rewards() const {
  return state_->results.rewards;
}
absl::Span<const uint8_t> VectorEnv::terminations() const {
  return state_->results.terminations;
}
absl::Span<const uint8_t> VectorEnv::truncations() const {
  return state_->results.truncations;
}
absl::Span<const uint8_t> VectorEnv::active() const {
  return state_->results.active;
}
absl::Span<const uint8_t> VectorEnv::outcomes() const {
  return state_->results.outcomes;
}
absl::Span<const float> VectorEnv::episode_returns() const {
  return state_->results.episode_returns;
}
absl::Span<const int32_t> VectorEnv::episode_lengths() const {
  return state_->results.episode_lengths;
}
absl::Span<const uint8_t> VectorEnv::auto_reset() const {
  return state_->results.auto_reset;
}
absl::Span<const uint8_t> VectorEnv::episode_over() const {
  return state_->results.episode_over;
}

StepData VectorEnv::Result(int row) const {
  const Columns& results = state_->results;
  const int n = state_->n_landers;
  const size_t first = static_cast<size_t>(row) * n;
  const auto slice = [&](const auto& column) {
    return std::vector<typename std::decay_t<decltype(column)>::value_type>(
        column.begin() + first, column.begin() + first + n);
  };
  StepData data;
  data.n_landers = n;
  data.observations.assign(
      results.observations.begin() + first * kRemoteObservationSize,
      results.observations.begin() + (first + n) * kRemoteObservationSize);
  data.rewards = slice(results.rewards);
  data.terminations = slice(results.terminations);
  data.truncations = slice(results.truncations);
  data.stepped = slice(results.active);
  for (uint8_t outcome : slice(results.outcomes)) {
    data.outcomes.push_back(static_cast<LanderOutcome>(outcome));
  }
  data.episode_returns = slice(results.episode_returns);
  data.episode_lengths = slice(results.episode_lengths);
  data.episode_over = results.episode_over[row] != 0;
  data.auto_reset = results.auto_reset[row] != 0;
  return data;
}

}  // namespace mll::client

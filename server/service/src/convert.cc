#include "mll/service/convert.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace mll::service {
namespace {

size_t ElementSize(v1::DType dtype) {
  switch (dtype) {
    case v1::DTYPE_FLOAT32:
    case v1::DTYPE_INT32:
      return 4;
    case v1::DTYPE_UINT8:
      return 1;
    default:
      return 0;
  }
}

std::string DTypeName(int dtype) {
  if (v1::DType_IsValid(dtype)) return v1::DType_Name(dtype);
  return absl::StrCat(dtype);
}

// Columns the core keeps per agent in other types than the wire's.
template <typename To, typename From>
std::vector<To> PerAgent(int n, From from) {
  std::vector<To> values(n);
  for (int i = 0; i < n; ++i) values[i] = static_cast<To>(from(i));
  return values;
}

// Sets `out`'s dtype and shape and sizes its data, zero; returns the data's
// bytes as a column of T for the caller to fill.
template <typename T, typename Wire = T>
ByteColumn<T> SizeArray(absl::Span<const int> shape, v1::Array* out) {
  static_assert(sizeof(T) == sizeof(Wire), "a column stores T as Wire");
  size_t count = 1;
  for (int dim : shape) count *= static_cast<size_t>(dim);
  out->set_dtype(DTypeOf<Wire>());
  out->mutable_shape()->Assign(shape.begin(), shape.end());
  std::string* data = out->mutable_data();
  data->assign(count * sizeof(T), '\0');
  return ByteColumn<T>(data);
}

// Replaces `out` with the little-endian elements of `bytes` (whose size the
// caller has checked to be a multiple of sizeof(T)).
template <typename T>
void LoadAll(const std::string& bytes, std::vector<T>* out) {
  out->resize(bytes.size() / sizeof(T));
  if (bytes.empty()) return;  // out->data() may be null.
  std::memcpy(out->data(), bytes.data(), bytes.size());
}

// Each agent's return and length so far in this episode, into row `row` of
// n float32 and n int32.
void WriteEpisodeColumns(const core::Env& env, size_t row,
                         const ByteColumn<float>& returns,
                         const ByteColumn<int32_t>& lengths) {
  const size_t n = static_cast<size_t>(env.n_landers());
  for (size_t i = 0; i < n; ++i) {
    returns.Store(row * n + i, static_cast<float>(env.episode_return(i)));
    lengths.Store(row * n + i, static_cast<int32_t>(env.episode_length(i)));
  }
}

// The same as two [n] arrays.
void FillEpisodeColumns(const core::Env& env, v1::Array* returns,
                        v1::Array* lengths) {
  const int rows[] = {env.n_landers()};
  WriteEpisodeColumns(env, 0, SizeArray<float>(rows, returns),
                      SizeArray<int32_t>(rows, lengths));
}

absl::Span<const int> ShapeOf(const v1::Array& array) {
  return absl::MakeConstSpan(array.shape().data(), array.shape().size());
}

// INVALID_ARGUMENT unless `array`'s data has the byte count of `shape` in
// `dtype` (whose shape was already checked).
absl::Status CheckByteSize(const v1::Array& array, v1::DType dtype,
                           absl::Span<const int> shape,
                           absl::string_view field) {
  size_t count = 1;
  for (int dim : shape) count *= static_cast<size_t>(dim);
  const size_t want = count * ElementSize(dtype);
  if (array.data().size() == want) return absl::OkStatus();
  return absl::InvalidArgumentError(absl::StrCat(
      field, ": data has ", array.data().size(), " bytes but shape ",
      ShapeString(shape), " of ", v1::DType_Name(dtype), " needs ", want));
}

// Every agent's latest observation as one [n, 12] row-major matrix.
template <typename ObservationOf>
std::vector<float> ObservationMatrix(int n, ObservationOf observation_of) {
  std::vector<float> matrix(static_cast<size_t>(n) * core::kObservationSize);
  for (int i = 0; i < n; ++i) {
    absl::Span<const float> row = observation_of(i);
    std::copy(row.begin(), row.end(),
              matrix.begin() + static_cast<size_t>(i) * core::kObservationSize);
  }
  return matrix;
}

}  // namespace

grpc::Status ToGrpcStatus(const absl::Status& status) {
  if (status.ok()) return grpc::Status::OK;
  const int code = static_cast<int>(status.code());
  // absl::StatusCode and grpc::StatusCode number the canonical codes alike.
  // The core never means UNKNOWN (absl's code for anything non-canonical):
  // it is a bug, which the wire reports as INTERNAL.
  if (status.code() == absl::StatusCode::kUnknown || code < 1 || code > 16) {
    return grpc::Status(grpc::StatusCode::INTERNAL,
                        absl::StrCat("internal error (status code ", code,
                                     "): ", status.message()));
  }
  return grpc::Status(static_cast<grpc::StatusCode>(code),
                      std::string(status.message()));
}

void FillItemError(const absl::Status& status, v1::ItemError* out) {
  const grpc::Status wire = ToGrpcStatus(status);
  out->set_code(static_cast<int>(wire.error_code()));
  out->set_message(wire.error_message());
}

std::string ShapeString(absl::Span<const int> shape) {
  return absl::StrCat("[", absl::StrJoin(shape, ", "), "]");
}

absl::Status CheckDTypeAndShape(int got_dtype, absl::Span<const int> got_shape,
                                v1::DType dtype, absl::Span<const int> shape,
                                absl::string_view field,
                                absl::string_view what) {
  if (got_dtype != dtype) {
    return absl::InvalidArgumentError(absl::StrCat(
        field, ": dtype ", DTypeName(got_dtype), " does not match ",
        v1::DType_Name(dtype), " (", what, ")"));
  }
  if (got_shape != shape) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": shape ", ShapeString(got_shape),
                     " does not match ", ShapeString(shape), " (", what, ")"));
  }
  return absl::OkStatus();
}

absl::Status CheckArray(const v1::Array& array, v1::DType dtype,
                        absl::Span<const int> shape, absl::string_view field,
                        absl::string_view what) {
  absl::Status status = CheckDTypeAndShape(array.dtype(), ShapeOf(array), dtype,
                                           shape, field, what);
  if (!status.ok()) return status;
  return CheckByteSize(array, dtype, shape, field);
}

absl::StatusOr<core::EnvConfig> EnvConfigFromProto(const v1::EnvConfig& proto) {
  core::EnvConfig config;  // The core's defaults fill every unset field.
#define MLL_COPY_IF_SET(type, name, default_value, range, help) \
  if (proto.has_##name()) config.name = proto.name();
  MLL_ENV_OPTIONS(MLL_COPY_IF_SET)
#undef MLL_COPY_IF_SET
  switch (proto.render_mode()) {
    case v1::RENDER_MODE_UNSPECIFIED:
    case v1::RENDER_MODE_NONE:
      config.render_mode = core::RenderMode::kNone;
      break;
    case v1::RENDER_MODE_RGB_ARRAY:
      config.render_mode = core::RenderMode::kRgbArray;
      break;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat("render_mode: ", proto.render_mode(),
                       " is not a RenderMode (allowed: RENDER_MODE_NONE = 1, "
                       "RENDER_MODE_RGB_ARRAY = 2)"));
  }
  absl::Status status = core::ValidateEnvConfig(config);
  if (!status.ok()) return status;
  return config;
}

v1::EnvConfig EnvConfigToProto(const core::EnvConfig& config, bool auto_reset) {
  v1::EnvConfig proto;
#define MLL_SET(type, name, default_value, range, help) \
  proto.set_##name(config.name);
  MLL_ENV_OPTIONS(MLL_SET)
#undef MLL_SET
  proto.set_render_mode(config.render_mode == core::RenderMode::kRgbArray
                            ? v1::RENDER_MODE_RGB_ARRAY
                            : v1::RENDER_MODE_NONE);
  proto.set_auto_reset(auto_reset);
  return proto;
}

v1::Space ObservationSpace() {
  v1::Space space;
  space.set_kind(v1::Space::KIND_BOX);
  space.set_dtype(v1::DTYPE_FLOAT32);
  space.add_shape(core::kObservationSize);
  for (int i = 0; i < core::kObservationSize; ++i) {
    space.add_low(-std::numeric_limits<double>::infinity());
    space.add_high(std::numeric_limits<double>::infinity());
  }
  return space;
}

v1::Space ActionSpace(const core::EnvConfig& config) {
  v1::Space space;
  if (config.continuous) {
    space.set_kind(v1::Space::KIND_BOX);
    space.set_dtype(v1::DTYPE_FLOAT32);
    space.add_shape(core::kContinuousActionSize);
    for (int i = 0; i < core::kContinuousActionSize; ++i) {
      space.add_low(-1.0);
      space.add_high(1.0);
    }
  } else {
    space.set_kind(v1::Space::KIND_DISCRETE);
    space.set_dtype(v1::DTYPE_INT32);
    space.set_n(core::kDiscreteActionCount);
  }
  return space;
}

absl::Status CheckActionLayout(int dtype, absl::Span<const int> shape,
                               const core::EnvConfig& config,
                               absl::string_view field) {
  const int n = config.n_landers;
  const int dims[] = {n, core::kContinuousActionSize};
  const absl::Span<const int> want(dims, config.continuous ? 2 : 1);
  const v1::DType want_dtype =
      config.continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32;
  // Explaining the expected layout costs an allocation: only on failure.
  if (dtype == want_dtype && shape == want) return absl::OkStatus();
  return CheckDTypeAndShape(
      dtype, shape, want_dtype, want, field,
      config.continuous
          ? absl::StrCat(
                "one float32 [main, lateral] pair per agent of n_landers = ", n)
          : absl::StrCat("one int32 per agent of n_landers = ", n));
}

absl::Status ParseActions(const v1::Array& array, const core::EnvConfig& config,
                          absl::string_view field, ActionBuffer* out) {
  absl::Status status =
      CheckActionLayout(array.dtype(), ShapeOf(array), config, field);
  if (!status.ok()) return status;
  const v1::DType dtype =
      config.continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32;
  status = CheckByteSize(array, dtype, ShapeOf(array), field);
  if (!status.ok()) return status;
  if (config.continuous) {
    out->discrete.clear();
    LoadAll(array.data(), &out->continuous);
  } else {
    out->continuous.clear();
    LoadAll(array.data(), &out->discrete);
  }
  return absl::OkStatus();
}

absl::StatusOr<PackedActions> PackedActions::Parse(
    const v1::PackedSteps& packed, int num_envs) {
  constexpr absl::string_view kField = "packed.actions";
  const v1::Array& array = packed.actions();
  const auto expected = [&packed, num_envs] {
    return absl::StrCat(
        "expected int32 [", num_envs,
        ", n_landers] for discrete actions or float32 [", num_envs,
        ", n_landers, 2] for continuous ones: num_envs = ",
        packed.names_size() == 0 && packed.handle() != 0
            ? absl::StrCat("the envs declared as packed.handle ",
                           packed.handle())
            : "len(packed.names)",
        " = ", num_envs, ", n_landers ", core::kMinLanders, "..",
        core::kMaxLanders);
  };
  PackedActions actions;
  switch (array.dtype()) {
    case v1::DTYPE_INT32:
      actions.continuous_ = false;
      break;
    case v1::DTYPE_FLOAT32:
      actions.continuous_ = true;
      break;
    default:
      return absl::InvalidArgumentError(
          absl::StrCat(kField, ": dtype ", DTypeName(array.dtype()),
                       " is not allowed (", expected(), ")"));
  }
  const absl::Span<const int> shape = ShapeOf(array);
  const size_t rank = actions.continuous_ ? 3 : 2;
  if (shape.size() != rank || shape[0] != num_envs ||
      (actions.continuous_ && shape[2] != core::kContinuousActionSize) ||
      shape[1] < core::kMinLanders || shape[1] > core::kMaxLanders) {
    return absl::InvalidArgumentError(absl::StrCat(
        kField, ": shape ", ShapeString(shape), " of ",
        DTypeName(array.dtype()), " does not fit (", expected(), ")"));
  }
  absl::Status status = CheckByteSize(array, array.dtype(), shape, kField);
  if (!status.ok()) return status;
  actions.n_landers_ = shape[1];
  std::vector<int32_t>& discrete = actions.values_.discrete;
  std::vector<float>& continuous = actions.values_.continuous;
  if (actions.continuous_) {
    LoadAll(array.data(), &continuous);
  } else {
    LoadAll(array.data(), &discrete);
  }
  return actions;
}

absl::Status PackedActions::CheckFits(int e,
                                      const core::EnvConfig& config) const {
  if (config.n_landers == n_landers_ && config.continuous == continuous_) {
    return absl::OkStatus();
  }
  const int dims[] = {n_landers_, core::kContinuousActionSize};
  return CheckActionLayout(continuous_ ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32,
                           absl::MakeConstSpan(dims, continuous_ ? 2 : 1),
                           config, absl::StrCat("packed.actions[", e, "]"));
}

core::ActionsView PackedActions::Row(int e) const {
  const size_t agents = static_cast<size_t>(n_landers_);
  if (continuous_) {
    const size_t size = agents * core::kContinuousActionSize;
    return core::ActionsView{
        {}, absl::MakeConstSpan(values_.continuous.data() + e * size, size)};
  }
  return core::ActionsView{
      absl::MakeConstSpan(values_.discrete.data() + e * agents, agents), {}};
}

absl::StatusOr<std::optional<core::AgentAction>> ParseAgentAction(
    const v1::StepAgentRequest& request, const core::EnvConfig& config) {
  if (!request.has_action()) return std::optional<core::AgentAction>();
  const v1::AgentAction& proto = request.action();
  core::AgentAction action;
  switch (proto.action_case()) {
    case v1::AgentAction::kDiscrete:
      if (config.continuous) {
        return absl::InvalidArgumentError(
            absl::StrCat("action.discrete: ", proto.discrete(),
                         " given but the env has continuous actions (set "
                         "action.continuous to float32 [2])"));
      }
      action.discrete = proto.discrete();
      break;
    case v1::AgentAction::kContinuous: {
      if (!config.continuous) {
        return absl::InvalidArgumentError(
            "action.continuous given but the env has Discrete(4) actions "
            "(set action.discrete to 0..3)");
      }
      const int shape[] = {core::kContinuousActionSize};
      absl::Status status =
          CheckArray(proto.continuous(), v1::DTYPE_FLOAT32, shape,
                     "action.continuous", "[main, lateral]");
      if (!status.ok()) return status;
      std::memcpy(action.continuous.data(), proto.continuous().data().data(),
                  sizeof(action.continuous));
      break;
    }
    default:
      return absl::InvalidArgumentError(
          "action: neither discrete nor continuous is set (leave action "
          "unset for a dead step)");
  }
  return std::optional<core::AgentAction>(action);
}

// The core's outcome codes travel as they are: they are the wire's Outcome
// values, which the clients name.
static_assert(sizeof(core::Outcome) == 1, "outcomes travel as uint8");
static_assert(static_cast<int>(core::Outcome::kNone) ==
              v1::OUTCOME_UNSPECIFIED);
static_assert(static_cast<int>(core::Outcome::kLanded) == v1::OUTCOME_LANDED);
static_assert(static_cast<int>(core::Outcome::kCrashed) == v1::OUTCOME_CRASHED);
static_assert(static_cast<int>(core::Outcome::kOutOfBounds) ==
              v1::OUTCOME_OUT_OF_BOUNDS);
static_assert(static_cast<int>(core::Outcome::kTruncated) ==
              v1::OUTCOME_TRUNCATED);
static_assert(static_cast<int>(core::Outcome::kAborted) == v1::OUTCOME_ABORTED);

void AgentColumns::Write(size_t row, const core::StepResult& result,
                         const core::Env& env) const {
  const size_t first = row * static_cast<size_t>(env.n_landers());
  observations.StoreAll(first * core::kObservationSize, result.observations);
  rewards.StoreAll(first, result.rewards);
  terminations.StoreAll(first, result.terminations);
  truncations.StoreAll(first, result.truncations);
  stepped.StoreAll(first, result.stepped);
  outcomes.StoreAll(first, result.outcomes);
  WriteEpisodeColumns(env, row, episode_returns, episode_lengths);
}

namespace {

// Sizes the eight per-agent columns that StepData and PackedStepData share
// (same field names), each with `lead` (none, or num_envs) before its
// per-agent dimensions.
template <typename Columns>
AgentColumns SizeAgentColumns(absl::Span<const int> lead, int n_landers,
                              Columns* out) {
  int rows_dims[2] = {0, n_landers};
  int matrix_dims[3] = {0, n_landers, core::kObservationSize};
  std::copy(lead.begin(), lead.end(), rows_dims);
  std::copy(lead.begin(), lead.end(), matrix_dims);
  const size_t skip = 1 - lead.size();  // 0 or 1.
  const absl::Span<const int> rows =
      absl::MakeConstSpan(rows_dims).subspan(skip);
  const absl::Span<const int> matrix =
      absl::MakeConstSpan(matrix_dims).subspan(skip);
  return AgentColumns{
      SizeArray<float>(matrix, out->mutable_observations()),
      SizeArray<float>(rows, out->mutable_rewards()),
      SizeArray<uint8_t>(rows, out->mutable_terminations()),
      SizeArray<uint8_t>(rows, out->mutable_truncations()),
      SizeArray<uint8_t>(rows, out->mutable_stepped()),
      SizeArray<core::Outcome, uint8_t>(rows, out->mutable_outcomes()),
      SizeArray<float>(rows, out->mutable_episode_returns()),
      SizeArray<int32_t>(rows, out->mutable_episode_lengths())};
}

}  // namespace

void FillStepData(const core::StepResult& result, const core::Env& env,
                  bool auto_reset, v1::StepData* out) {
  SizeAgentColumns({}, env.n_landers(), out).Write(0, result, env);
  out->set_episode_over(result.episode_over);
  out->set_auto_reset(auto_reset);
  out->set_cycles(env.cycles());
}

PackedColumns::PackedColumns(int num_envs, int n_landers,
                             v1::PackedStepData* out) {
  const int envs[] = {num_envs};
  agents_ = SizeAgentColumns(envs, n_landers, out);
  episode_over_ = SizeArray<uint8_t>(envs, out->mutable_episode_over());
  auto_reset_ = SizeArray<uint8_t>(envs, out->mutable_auto_reset());
  cycles_ = SizeArray<int32_t>(envs, out->mutable_cycles());
}

void PackedColumns::Write(int e, const core::StepResult& result,
                          const core::Env& env, bool auto_reset) const {
  const size_t row = static_cast<size_t>(e);
  agents_.Write(row, result, env);
  episode_over_.Store(row, result.episode_over);
  auto_reset_.Store(row, auto_reset);
  cycles_.Store(row, static_cast<int32_t>(env.cycles()));
}

void FillAecState(const core::AecEnv& aec, bool world_stepped,
                  v1::AecState* out) {
  const core::Env& env = aec.env();
  const int n = env.n_landers();
  std::vector<uint8_t> in_cycle(n, 0);
  for (int agent : aec.agents()) in_cycle[agent] = 1;
  out->mutable_agents()->Assign(aec.agents().begin(), aec.agents().end());
  out->set_agent_selection(aec.agent_selection());

  const std::vector<float> observations =
      ObservationMatrix(n, [&](int i) { return aec.observe(i); });
  const int rows[] = {n};
  const int matrix[] = {n, core::kObservationSize};
  // The adapter's per-agent state is only defined for agents in the cycle;
  // the others read as zero.
  FillArray<float>(observations, matrix, out->mutable_observations());
  FillArray<float>(
      PerAgent<float>(
          n, [&](int i) { return in_cycle[i] ? aec.reward(i) : 0.0f; }),
      rows, out->mutable_rewards());
  FillArray<float>(
      PerAgent<float>(
          n,
          [&](int i) { return in_cycle[i] ? aec.cumulative_reward(i) : 0.0f; }),
      rows, out->mutable_cumulative_rewards());
  FillArray<uint8_t>(
      PerAgent<uint8_t>(
          n, [&](int i) { return in_cycle[i] && aec.terminated(i); }),
      rows, out->mutable_terminations());
  FillArray<uint8_t>(
      PerAgent<uint8_t>(n,
                        [&](int i) { return in_cycle[i] && aec.truncated(i); }),
      rows, out->mutable_truncations());
  FillArray<uint8_t>(
      PerAgent<uint8_t>(
          n, [&](int i) { return static_cast<uint8_t>(env.outcome(i)); }),
      rows, out->mutable_outcomes());
  FillEpisodeColumns(env, out->mutable_episode_returns(),
                     out->mutable_episode_lengths());
  out->set_world_stepped(world_stepped);
}

}  // namespace mll::service

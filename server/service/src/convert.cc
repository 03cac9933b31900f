#include "mll/service/convert.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"

namespace mll {
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
// bytes for the caller to fill.
template <typename T>
char* SizeArray(absl::Span<const int> shape, v1::Array* out) {
  size_t count = 1;
  for (int dim : shape) count *= static_cast<size_t>(dim);
  out->set_dtype(DTypeOf<T>());
  out->mutable_shape()->Assign(shape.begin(), shape.end());
  std::string* data = out->mutable_data();
  data->assign(count * sizeof(T), '\0');
  return data->data();
}

// Stores `value` at element `index` of a little-endian byte column.
template <typename T>
void Store(T value, size_t index, char* column) {
  std::memcpy(column + index * sizeof(T), &value, sizeof(T));
}

// Copies a whole core column into a row of bytes.
template <typename T>
void StoreAll(const std::vector<T>& values, char* column) {
  // memcpy with a null pointer is undefined even for 0 bytes (empty batch).
  if (values.empty()) return;
  std::memcpy(column, values.data(), values.size() * sizeof(T));
}

// Replaces `out` with the little-endian elements of `bytes` (whose size the
// caller has checked to be a multiple of sizeof(T)).
template <typename T>
void LoadAll(const std::string& bytes, std::vector<T>* out) {
  out->resize(bytes.size() / sizeof(T));
  if (bytes.empty()) return;  // out->data() may be null.
  std::memcpy(out->data(), bytes.data(), bytes.size());
}

// Each agent's return and length so far in this episode, into two rows of n
// float32 and n int32.
void WriteEpisodeColumns(const Env& env, char* returns, char* lengths) {
  for (int i = 0; i < env.n_landers(); ++i) {
    Store(static_cast<float>(env.episode_return(i)), i, returns);
    Store(static_cast<int32_t>(env.episode_length(i)), i, lengths);
  }
}

// The same as two [n] arrays.
void FillEpisodeColumns(const Env& env, v1::Array* returns,
                        v1::Array* lengths) {
  const int rows[] = {env.n_landers()};
  WriteEpisodeColumns(env, SizeArray<float>(rows, returns),
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
  std::vector<float> matrix(static_cast<size_t>(n) * kObservationSize);
  for (int i = 0; i < n; ++i) {
    absl::Span<const float> row = observation_of(i);
    std::copy(row.begin(), row.end(),
              matrix.begin() + static_cast<size_t>(i) * kObservationSize);
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
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": dtype ", DTypeName(got_dtype),
                     " does not match ", v1::DType_Name(dtype), " (", what,
                     ")"));
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
  absl::Status status =
      CheckDTypeAndShape(array.dtype(), ShapeOf(array), dtype, shape, field,
                         what);
  if (!status.ok()) return status;
  return CheckByteSize(array, dtype, shape, field);
}

// The fields that proto and core configs share, listed once: both
// directions of the conversion expand this list.
#define MLL_SHARED_CONFIG_FIELDS(X)                                           \
  X(n_landers) X(continuous) X(max_cycles) X(gravity) X(enable_wind)          \
  X(wind_power) X(turbulence_power) X(remove_on_damage)                       \
  X(terminate_on_damage) X(shared_reward) X(damage_reward)                    \
  X(successful_reward) X(terminate_reward)

absl::StatusOr<EnvConfig> EnvConfigFromProto(const v1::EnvConfig& proto) {
  EnvConfig config;  // The core's defaults fill every unset field.
#define MLL_COPY_IF_SET(field) \
  if (proto.has_##field()) config.field = proto.field();
  MLL_SHARED_CONFIG_FIELDS(MLL_COPY_IF_SET)
#undef MLL_COPY_IF_SET
  switch (proto.render_mode()) {
    case v1::RENDER_MODE_UNSPECIFIED:
    case v1::RENDER_MODE_NONE:
      config.render_mode = RenderMode::kNone;
      break;
    case v1::RENDER_MODE_RGB_ARRAY:
      config.render_mode = RenderMode::kRgbArray;
      break;
    default:
      return absl::InvalidArgumentError(absl::StrCat(
          "render_mode: ", proto.render_mode(),
          " is not a RenderMode (allowed: RENDER_MODE_NONE = 1, "
          "RENDER_MODE_RGB_ARRAY = 2)"));
  }
  absl::Status status = ValidateEnvConfig(config);
  if (!status.ok()) return status;
  return config;
}

v1::EnvConfig EnvConfigToProto(const EnvConfig& config, bool auto_reset) {
  v1::EnvConfig proto;
#define MLL_SET(field) proto.set_##field(config.field);
  MLL_SHARED_CONFIG_FIELDS(MLL_SET)
#undef MLL_SET
  proto.set_render_mode(config.render_mode == RenderMode::kRgbArray
                            ? v1::RENDER_MODE_RGB_ARRAY
                            : v1::RENDER_MODE_NONE);
  proto.set_auto_reset(auto_reset);
  return proto;
}

#undef MLL_SHARED_CONFIG_FIELDS

v1::Space ObservationSpace() {
  v1::Space space;
  space.set_kind(v1::Space::KIND_BOX);
  space.set_dtype(v1::DTYPE_FLOAT32);
  space.add_shape(kObservationSize);
  for (int i = 0; i < kObservationSize; ++i) {
    space.add_low(-std::numeric_limits<double>::infinity());
    space.add_high(std::numeric_limits<double>::infinity());
  }
  return space;
}

v1::Space ActionSpace(const EnvConfig& config) {
  v1::Space space;
  if (config.continuous) {
    space.set_kind(v1::Space::KIND_BOX);
    space.set_dtype(v1::DTYPE_FLOAT32);
    space.add_shape(kContinuousActionSize);
    for (int i = 0; i < kContinuousActionSize; ++i) {
      space.add_low(-1.0);
      space.add_high(1.0);
    }
  } else {
    space.set_kind(v1::Space::KIND_DISCRETE);
    space.set_dtype(v1::DTYPE_INT32);
    space.set_n(kDiscreteActionCount);
  }
  return space;
}

absl::Status CheckActionLayout(int dtype, absl::Span<const int> shape,
                               const EnvConfig& config,
                               absl::string_view field) {
  const int n = config.n_landers;
  const int dims[] = {n, kContinuousActionSize};
  const absl::Span<const int> want(dims, config.continuous ? 2 : 1);
  const v1::DType want_dtype =
      config.continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32;
  // Explaining the expected layout costs an allocation: only on failure.
  if (dtype == want_dtype && shape == want) return absl::OkStatus();
  return CheckDTypeAndShape(
      dtype, shape, want_dtype, want, field,
      config.continuous
          ? absl::StrCat(
                "one float32 [main, lateral] pair per agent of n_landers = ",
                n)
          : absl::StrCat("one int32 per agent of n_landers = ", n));
}

absl::Status ParseActions(const v1::Array& array, const EnvConfig& config,
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
    const v1::PackedSteps& packed) {
  constexpr absl::string_view kField = "packed.actions";
  const v1::Array& array = packed.actions();
  const int num_envs = packed.names_size();
  const auto expected = [num_envs] {
    return absl::StrCat("expected int32 [", num_envs,
                        ", n_landers] for discrete actions or float32 [",
                        num_envs,
                        ", n_landers, 2] for continuous ones: num_envs = "
                        "len(packed.names) = ",
                        num_envs, ", n_landers ", kMinLanders, "..",
                        kMaxLanders);
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
      (actions.continuous_ && shape[2] != kContinuousActionSize) ||
      shape[1] < kMinLanders || shape[1] > kMaxLanders) {
    return absl::InvalidArgumentError(
        absl::StrCat(kField, ": shape ", ShapeString(shape), " of ",
                     DTypeName(array.dtype()), " does not fit (", expected(),
                     ")"));
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

absl::Status PackedActions::CheckFits(int e, const EnvConfig& config) const {
  if (config.n_landers == n_landers_ && config.continuous == continuous_) {
    return absl::OkStatus();
  }
  const int dims[] = {n_landers_, kContinuousActionSize};
  return CheckActionLayout(
      continuous_ ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32,
      absl::MakeConstSpan(dims, continuous_ ? 2 : 1), config,
      absl::StrCat("packed.actions[", e, "]"));
}

ActionsView PackedActions::Row(int e) const {
  const size_t agents = static_cast<size_t>(n_landers_);
  if (continuous_) {
    const size_t size = agents * kContinuousActionSize;
    return ActionsView{{}, absl::MakeConstSpan(
                               values_.continuous.data() + e * size, size)};
  }
  return ActionsView{
      absl::MakeConstSpan(values_.discrete.data() + e * agents, agents), {}};
}

absl::StatusOr<std::optional<AgentAction>> ParseAgentAction(
    const v1::StepAgentRequest& request, const EnvConfig& config) {
  if (!request.has_action()) return std::optional<AgentAction>();
  const v1::AgentAction& proto = request.action();
  AgentAction action;
  switch (proto.action_case()) {
    case v1::AgentAction::kDiscrete:
      if (config.continuous) {
        return absl::InvalidArgumentError(absl::StrCat(
            "action.discrete: ", proto.discrete(),
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
      const int shape[] = {kContinuousActionSize};
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
  return std::optional<AgentAction>(action);
}

// The core's outcome codes travel as they are: they are the wire's Outcome
// values, which the clients name.
static_assert(sizeof(Outcome) == 1, "outcomes travel as uint8");
static_assert(static_cast<int>(Outcome::kNone) == v1::OUTCOME_UNSPECIFIED);
static_assert(static_cast<int>(Outcome::kLanded) == v1::OUTCOME_LANDED);
static_assert(static_cast<int>(Outcome::kCrashed) == v1::OUTCOME_CRASHED);
static_assert(static_cast<int>(Outcome::kOutOfBounds) ==
              v1::OUTCOME_OUT_OF_BOUNDS);
static_assert(static_cast<int>(Outcome::kTruncated) == v1::OUTCOME_TRUNCATED);
static_assert(static_cast<int>(Outcome::kAborted) == v1::OUTCOME_ABORTED);

void WriteStepRow(const StepResult& result, const Env& env, bool auto_reset,
                  const StepRow& row) {
  StoreAll(result.observations, row.observations);
  StoreAll(result.rewards, row.rewards);
  StoreAll(result.terminations, row.terminations);
  StoreAll(result.truncations, row.truncations);
  StoreAll(result.stepped, row.stepped);
  StoreAll(result.outcomes, row.outcomes);
  WriteEpisodeColumns(env, row.episode_returns, row.episode_lengths);
  Store(static_cast<uint8_t>(result.episode_over), 0, row.episode_over);
  Store(static_cast<uint8_t>(auto_reset), 0, row.auto_reset);
  Store(static_cast<int32_t>(env.cycles()), 0, row.cycles);
}

namespace {

// Sizes the eight per-agent columns that StepData and PackedStepData share
// (same field names), each with `lead` (none, or num_envs) before its
// per-agent dimensions; the per-env columns of the returned row are unset.
template <typename Columns>
StepRow SizeAgentColumns(absl::Span<const int> lead, int n_landers,
                         Columns* out) {
  int rows_dims[2] = {0, n_landers};
  int matrix_dims[3] = {0, n_landers, kObservationSize};
  std::copy(lead.begin(), lead.end(), rows_dims);
  std::copy(lead.begin(), lead.end(), matrix_dims);
  const int skip = 1 - static_cast<int>(lead.size());  // 0 or 1.
  const absl::Span<const int> rows(rows_dims + skip, lead.size() + 1);
  const absl::Span<const int> matrix(matrix_dims + skip, lead.size() + 2);
  return StepRow{SizeArray<float>(matrix, out->mutable_observations()),
                 SizeArray<float>(rows, out->mutable_rewards()),
                 SizeArray<uint8_t>(rows, out->mutable_terminations()),
                 SizeArray<uint8_t>(rows, out->mutable_truncations()),
                 SizeArray<uint8_t>(rows, out->mutable_stepped()),
                 SizeArray<uint8_t>(rows, out->mutable_outcomes()),
                 SizeArray<float>(rows, out->mutable_episode_returns()),
                 SizeArray<int32_t>(rows, out->mutable_episode_lengths()),
                 nullptr,
                 nullptr,
                 nullptr};
}

}  // namespace

void FillStepData(const StepResult& result, const Env& env, bool auto_reset,
                  v1::StepData* out) {
  StepRow row = SizeAgentColumns({}, env.n_landers(), out);
  // StepData's per-env columns are scalar fields: written here, then set.
  uint8_t episode_over = 0;
  uint8_t was_reset = 0;
  int32_t cycles = 0;
  row.episode_over = reinterpret_cast<char*>(&episode_over);
  row.auto_reset = reinterpret_cast<char*>(&was_reset);
  row.cycles = reinterpret_cast<char*>(&cycles);
  WriteStepRow(result, env, auto_reset, row);
  out->set_episode_over(episode_over != 0);
  out->set_auto_reset(was_reset != 0);
  out->set_cycles(cycles);
}

PackedColumns::PackedColumns(int num_envs, int n_landers,
                             v1::PackedStepData* out)
    : n_landers_(n_landers) {
  const int envs[] = {num_envs};
  base_ = SizeAgentColumns(envs, n_landers, out);
  base_.episode_over = SizeArray<uint8_t>(envs, out->mutable_episode_over());
  base_.auto_reset = SizeArray<uint8_t>(envs, out->mutable_auto_reset());
  base_.cycles = SizeArray<int32_t>(envs, out->mutable_cycles());
}

StepRow PackedColumns::Row(int e) const {
  const size_t env = static_cast<size_t>(e);
  const size_t agents = env * static_cast<size_t>(n_landers_);
  return StepRow{base_.observations + agents * kObservationSize * sizeof(float),
                 base_.rewards + agents * sizeof(float),
                 base_.terminations + agents,
                 base_.truncations + agents,
                 base_.stepped + agents,
                 base_.outcomes + agents,
                 base_.episode_returns + agents * sizeof(float),
                 base_.episode_lengths + agents * sizeof(int32_t),
                 base_.episode_over + env,
                 base_.auto_reset + env,
                 base_.cycles + env * sizeof(int32_t)};
}

void FillAecState(const AecEnv& aec, bool world_stepped, v1::AecState* out) {
  const Env& env = aec.env();
  const int n = env.n_landers();
  std::vector<uint8_t> in_cycle(n, 0);
  for (int agent : aec.agents()) in_cycle[agent] = 1;
  out->mutable_agents()->Assign(aec.agents().begin(), aec.agents().end());
  out->set_agent_selection(aec.agent_selection());

  const std::vector<float> observations =
      ObservationMatrix(n, [&](int i) { return aec.observe(i); });
  const int rows[] = {n};
  const int matrix[] = {n, kObservationSize};
  // The adapter's per-agent state is only defined for agents in the cycle;
  // the others read as zero.
  FillArray<float>(observations, matrix, out->mutable_observations());
  FillArray<float>(PerAgent<float>(n,
                                   [&](int i) {
                                     return in_cycle[i] ? aec.reward(i) : 0.0f;
                                   }),
                   rows, out->mutable_rewards());
  FillArray<float>(PerAgent<float>(n,
                                   [&](int i) {
                                     return in_cycle[i]
                                                ? aec.cumulative_reward(i)
                                                : 0.0f;
                                   }),
                   rows, out->mutable_cumulative_rewards());
  FillArray<uint8_t>(
      PerAgent<uint8_t>(n,
                        [&](int i) { return in_cycle[i] && aec.terminated(i); }),
      rows, out->mutable_terminations());
  FillArray<uint8_t>(
      PerAgent<uint8_t>(n,
                        [&](int i) { return in_cycle[i] && aec.truncated(i); }),
      rows, out->mutable_truncations());
  FillArray<uint8_t>(PerAgent<uint8_t>(n,
                                       [&](int i) {
                                         return static_cast<uint8_t>(
                                             env.outcome(i));
                                       }),
                     rows, out->mutable_outcomes());
  FillEpisodeColumns(env, out->mutable_episode_returns(),
                     out->mutable_episode_lengths());
  out->set_world_stepped(world_stepped);
}

void ResultAfterReset(const Env& env, StepResult* out) {
  const int n = env.n_landers();
  out->observations =
      ObservationMatrix(n, [&](int i) { return env.observation(i); });
  out->rewards.assign(n, 0.0f);
  out->terminations.assign(n, 0);
  out->truncations.assign(n, 0);
  out->stepped.assign(n, 1);
  out->outcomes.resize(n);
  for (int i = 0; i < n; ++i) out->outcomes[i] = env.outcome(i);
  out->episode_over = env.episode_over();
}

}  // namespace mll

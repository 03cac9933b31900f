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

// Each agent's return and length so far in this episode.
void FillEpisodeColumns(const Env& env, v1::Array* returns,
                        v1::Array* lengths) {
  const int n = env.n_landers();
  const int rows[] = {n};
  FillArray<float>(
      PerAgent<float>(n, [&](int i) { return env.episode_return(i); }), rows,
      returns);
  FillArray<int32_t>(
      PerAgent<int32_t>(n, [&](int i) { return env.episode_length(i); }),
      rows, lengths);
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

absl::Status CheckArray(const v1::Array& array, v1::DType dtype,
                        absl::Span<const int> shape, absl::string_view field,
                        absl::string_view what) {
  if (array.dtype() != dtype) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": dtype ", DTypeName(array.dtype()),
                     " does not match ", v1::DType_Name(dtype), " (", what,
                     ")"));
  }
  const std::vector<int> got(array.shape().begin(), array.shape().end());
  if (got != std::vector<int>(shape.begin(), shape.end())) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": shape ", ShapeString(got), " does not match ",
                     ShapeString(shape), " (", what, ")"));
  }
  size_t count = 1;
  for (int dim : shape) count *= static_cast<size_t>(dim);
  const size_t want = count * ElementSize(dtype);
  if (array.data().size() != want) {
    return absl::InvalidArgumentError(absl::StrCat(
        field, ": data has ", array.data().size(), " bytes but shape ",
        ShapeString(shape), " of ", v1::DType_Name(dtype), " needs ", want));
  }
  return absl::OkStatus();
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

absl::Status ParseActions(const v1::Array& array, const EnvConfig& config,
                          absl::string_view field, ActionBuffer* out) {
  const int n = config.n_landers;
  if (config.continuous) {
    const int shape[] = {n, kContinuousActionSize};
    absl::Status status = CheckArray(
        array, v1::DTYPE_FLOAT32, shape, field,
        absl::StrCat("one float32 [main, lateral] pair per agent of "
                     "n_landers = ",
                     n));
    if (!status.ok()) return status;
    out->discrete.clear();
    out->continuous.resize(static_cast<size_t>(n) * kContinuousActionSize);
    std::memcpy(out->continuous.data(), array.data().data(),
                array.data().size());
  } else {
    const int shape[] = {n};
    absl::Status status = CheckArray(
        array, v1::DTYPE_INT32, shape, field,
        absl::StrCat("one int32 per agent of n_landers = ", n));
    if (!status.ok()) return status;
    out->continuous.clear();
    out->discrete.resize(n);
    std::memcpy(out->discrete.data(), array.data().data(),
                array.data().size());
  }
  return absl::OkStatus();
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

void FillStepData(const StepResult& result, const Env& env, bool auto_reset,
                  v1::StepData* out) {
  const int n = env.n_landers();
  const int rows[] = {n};
  const int matrix[] = {n, kObservationSize};
  static_assert(sizeof(Outcome) == 1, "outcomes travel as uint8");
  FillArray<float>(result.observations, matrix, out->mutable_observations());
  FillArray<float>(result.rewards, rows, out->mutable_rewards());
  FillArray<uint8_t>(result.terminations, rows, out->mutable_terminations());
  FillArray<uint8_t>(result.truncations, rows, out->mutable_truncations());
  FillArray<uint8_t>(result.stepped, rows, out->mutable_stepped());
  FillArray<uint8_t>(
      absl::MakeConstSpan(
          reinterpret_cast<const uint8_t*>(result.outcomes.data()),
          result.outcomes.size()),
      rows, out->mutable_outcomes());
  FillEpisodeColumns(env, out->mutable_episode_returns(),
                     out->mutable_episode_lengths());
  out->set_episode_over(result.episode_over);
  out->set_auto_reset(auto_reset);
  out->set_cycles(env.cycles());
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

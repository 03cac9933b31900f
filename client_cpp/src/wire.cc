#include "wire.h"

#include <algorithm>
#include <array>
#include <cstring>
#include <string>
#include <type_traits>
#include <vector>

#include "absl/base/config.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/strings/strip.h"
#include "google/protobuf/descriptor.h"
#include "google/protobuf/util/json_util.h"

namespace mll::client {
namespace internal {
namespace {

// Arrays travel little-endian and are copied as they are.
#ifndef ABSL_IS_LITTLE_ENDIAN
#error "The client copies little-endian wire arrays verbatim."
#endif

template <typename T>
constexpr v1::DType DTypeOf() {
  if constexpr (std::is_same_v<T, float>) {
    return v1::DTYPE_FLOAT32;
  } else if constexpr (std::is_same_v<T, uint8_t>) {
    return v1::DTYPE_UINT8;
  } else {
    static_assert(std::is_same_v<T, int32_t>);
    return v1::DTYPE_INT32;
  }
}

// Copies a column the server sent, checking its dtype and that its shape is
// `shape` (the documented one for this field).
template <typename T>
absl::Status DecodeColumn(const v1::Array& array, absl::string_view field,
                          std::initializer_list<int> shape,
                          std::vector<T>* out) {
  absl::Status status =
      CheckColumn(array, field, DTypeOf<T>(), sizeof(T),
                  absl::Span<const int>(shape.begin(), shape.size()));
  if (!status.ok()) return status;
  out->resize(array.data().size() / sizeof(T));
  if (!out->empty()) {
    std::memcpy(out->data(), array.data().data(), array.data().size());
  }
  return absl::OkStatus();
}

template <typename T>
void EncodeColumn(absl::Span<const T> values, std::initializer_list<int> shape,
                  v1::Array* proto) {
  proto->set_dtype(DTypeOf<T>());
  proto->mutable_shape()->Assign(shape.begin(), shape.end());
  proto->set_data(reinterpret_cast<const char*>(values.data()),
                  values.size() * sizeof(T));
}

// Decodes the columns every result has; the number of agents is read from
// the observations' shape.
template <typename Message>
absl::Status DecodeAgentColumns(const Message& proto, AgentColumns* columns) {
  const int n =
      proto.observations().shape_size() > 0 ? proto.observations().shape(0) : 0;
  columns->n_landers = n;
  std::vector<uint8_t> outcomes;
  absl::Status status =
      DecodeColumn(proto.observations(), "observations",
                   {n, kRemoteObservationSize}, &columns->observations);
  if (status.ok()) {
    status = DecodeColumn(proto.rewards(), "rewards", {n}, &columns->rewards);
  }
  if (status.ok()) {
    status = DecodeColumn(proto.terminations(), "terminations", {n},
                          &columns->terminations);
  }
  if (status.ok()) {
    status = DecodeColumn(proto.truncations(), "truncations", {n},
                          &columns->truncations);
  }
  if (status.ok()) {
    status = DecodeColumn(proto.outcomes(), "outcomes", {n}, &outcomes);
  }
  if (status.ok()) {
    status = DecodeColumn(proto.episode_returns(), "episode_returns", {n},
                          &columns->episode_returns);
  }
  if (status.ok()) {
    status = DecodeColumn(proto.episode_lengths(), "episode_lengths", {n},
                          &columns->episode_lengths);
  }
  columns->outcomes.resize(outcomes.size());
  for (size_t i = 0; i < outcomes.size(); ++i) {
    columns->outcomes[i] = static_cast<LanderOutcome>(outcomes[i]);
  }
  return status;
}

ElementType DecodeDType(v1::DType dtype) {
  switch (dtype) {
    case v1::DTYPE_FLOAT32:
      return ElementType::kFloat32;
    case v1::DTYPE_UINT8:
      return ElementType::kUint8;
    case v1::DTYPE_INT32:
      return ElementType::kInt32;
    default:
      return ElementType::kUnspecified;
  }
}

SpaceSpec DecodeSpace(const v1::Space& proto) {
  SpaceSpec space;
  switch (proto.kind()) {
    case v1::Space::KIND_BOX:
      space.kind = SpaceSpec::Kind::kBox;
      break;
    case v1::Space::KIND_DISCRETE:
      space.kind = SpaceSpec::Kind::kDiscrete;
      break;
    default:
      space.kind = SpaceSpec::Kind::kUnspecified;
  }
  space.dtype = DecodeDType(proto.dtype());
  space.shape.assign(proto.shape().begin(), proto.shape().end());
  space.low.assign(proto.low().begin(), proto.low().end());
  space.high.assign(proto.high().begin(), proto.high().end());
  space.n = proto.n();
  return space;
}

}  // namespace

absl::Status CheckColumn(const v1::Array& array, absl::string_view field,
                         v1::DType dtype, size_t element_size,
                         absl::Span<const int> shape) {
  size_t count = 1;
  for (int dimension : shape) count *= static_cast<size_t>(dimension);
  const bool shape_ok = std::equal(shape.begin(), shape.end(),
                                   array.shape().begin(), array.shape().end());
  if (array.dtype() != dtype || !shape_ok ||
      array.data().size() != count * element_size) {
    return absl::InternalError(absl::StrCat(
        "server sent ", field, " with dtype ", v1::DType_Name(array.dtype()),
        ", shape [", absl::StrJoin(array.shape(), ","), "] and ",
        array.data().size(), " bytes; expected ", v1::DType_Name(dtype), " [",
        absl::StrJoin(shape, ","), "]"));
  }
  return absl::OkStatus();
}

// Every option travels in the proto's field of the same name (an optional
// field: unset means the server's default).
void EncodeConfig(const RemoteEnvConfig& config, v1::EnvConfig* proto) {
#define MLL_ENCODE_OPTION(type, name, default_value, range, help) \
  if (config.name.has_value()) proto->set_##name(*config.name);
  MLL_ENV_OPTIONS(MLL_ENCODE_OPTION)
#undef MLL_ENCODE_OPTION
  proto->set_render_mode(config.render_rgb_array ? v1::RENDER_MODE_RGB_ARRAY
                                                 : v1::RENDER_MODE_NONE);
  proto->set_auto_reset(config.auto_reset);
}

RemoteEnvConfig DecodeConfig(const v1::EnvConfig& proto) {
  RemoteEnvConfig config;
#define MLL_DECODE_OPTION(type, name, default_value, range, help) \
  if (proto.has_##name()) config.name = proto.name();
  MLL_ENV_OPTIONS(MLL_DECODE_OPTION)
#undef MLL_DECODE_OPTION
  config.render_rgb_array = proto.render_mode() == v1::RENDER_MODE_RGB_ARRAY;
  config.auto_reset = proto.auto_reset();
  return config;
}

EnvInfo DecodeEnv(const v1::Env& proto) {
  EnvInfo info;
  info.name = proto.name();
  info.config = DecodeConfig(proto.config());
  info.possible_agents.assign(proto.possible_agents().begin(),
                              proto.possible_agents().end());
  info.observation_space = DecodeSpace(proto.observation_space());
  info.action_space = DecodeSpace(proto.action_space());
  info.render_fps = proto.render_fps();
  info.episode_started = proto.episode_started();
  info.episode_over = proto.episode_over();
  info.cycles = proto.cycles();
  info.episodes = proto.episodes();
  info.session_bound = proto.session_bound();
  info.idle_timeout_s = proto.idle_timeout_s();
  info.json = JsonOf(proto);
  return info;
}

std::string JsonOf(const google::protobuf::Message& message) {
  google::protobuf::util::JsonPrintOptions options;
  options.preserve_proto_field_names = true;
  options.always_print_primitive_fields = true;
  std::string json;
  // Printing a well-formed message cannot fail; an empty string would only
  // make the JSON field empty.
  (void)google::protobuf::util::MessageToJsonString(message, &json, options);
  return json;
}

absl::Status EncodeActions(const Actions& actions, v1::Array* proto) {
  if (actions.discrete.empty() == actions.continuous.empty()) {
    return absl::InvalidArgumentError(
        absl::StrCat("actions: set exactly one of discrete (has ",
                     actions.discrete.size(), " values) and continuous (has ",
                     actions.continuous.size(), " values)"));
  }
  if (!actions.discrete.empty()) {
    EncodeColumn(actions.discrete, {static_cast<int>(actions.discrete.size())},
                 proto);
    return absl::OkStatus();
  }
  // [n, 2] for a whole number of rows; otherwise the flat shape goes to the
  // server, which names the wrong count in its error.
  const int size = static_cast<int>(actions.continuous.size());
  if (size % kRemoteContinuousActionSize == 0) {
    EncodeColumn(
        actions.continuous,
        {size / kRemoteContinuousActionSize, kRemoteContinuousActionSize},
        proto);
  } else {
    EncodeColumn(actions.continuous, {size}, proto);
  }
  return absl::OkStatus();
}

void EncodeAgentAction(
    const std::array<float, kRemoteContinuousActionSize>& action,
    v1::Array* proto) {
  EncodeColumn(absl::MakeConstSpan(action), {kRemoteContinuousActionSize},
               proto);
}

absl::StatusOr<StepData> DecodeStepData(const v1::StepData& proto) {
  StepData data;
  absl::Status status = DecodeAgentColumns(proto, &data);
  if (status.ok()) {
    status = DecodeColumn(proto.stepped(), "stepped", {data.n_landers},
                          &data.stepped);
  }
  if (!status.ok()) return status;
  data.episode_over = proto.episode_over();
  data.auto_reset = proto.auto_reset();
  data.cycles = proto.cycles();
  return data;
}

absl::StatusOr<AecState> DecodeAecState(const v1::AecState& proto) {
  AecState state;
  absl::Status status = DecodeAgentColumns(proto, &state);
  if (status.ok()) {
    status = DecodeColumn(proto.cumulative_rewards(), "cumulative_rewards",
                          {state.n_landers}, &state.cumulative_rewards);
  }
  if (!status.ok()) return status;
  state.agents.assign(proto.agents().begin(), proto.agents().end());
  state.agent_selection = proto.agent_selection();
  state.world_stepped = proto.world_stepped();
  return state;
}

RenderedFrame DecodeFrame(const v1::Frame& proto) {
  RenderedFrame frame;
  frame.width = proto.width();
  frame.height = proto.height();
  frame.format = proto.format() == v1::FRAME_FORMAT_PNG ? FrameFormat::kPng
                                                        : FrameFormat::kRgb;
  frame.data = proto.data();
  return frame;
}

absl::string_view OutcomeName(int code) {
  // Built once from the descriptor, so a value added to the proto is named
  // without a change here.
  static const std::vector<std::string>* const kNames = [] {
    const google::protobuf::EnumDescriptor* outcomes = v1::Outcome_descriptor();
    auto* names = new std::vector<std::string>();
    for (int i = 0; i < outcomes->value_count(); ++i) {
      const google::protobuf::EnumValueDescriptor* value = outcomes->value(i);
      if (value->number() >= static_cast<int>(names->size())) {
        names->resize(value->number() + 1, "unknown");
      }
      (*names)[value->number()] = value->number() == v1::OUTCOME_UNSPECIFIED
                                      ? "none"
                                      : absl::AsciiStrToLower(absl::StripPrefix(
                                            value->name(), "OUTCOME_"));
    }
    return names;
  }();
  if (code < 0 || code >= static_cast<int>(kNames->size())) return "unknown";
  return (*kNames)[code];
}

}  // namespace internal
}  // namespace mll::client

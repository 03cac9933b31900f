// The one place where the client converts between its plain C++ types and the
// wire messages of proto/mll/v1.
#ifndef MLL_CLIENT_SRC_WIRE_H_
#define MLL_CLIENT_SRC_WIRE_H_

#include <array>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::client {
namespace internal {

// OK when a column the server sent has `dtype` (elements of `element_size`
// bytes) and `shape`; else INTERNAL naming `field` (a version mismatch, never
// a user error).
absl::Status CheckColumn(const v1::Array& array, absl::string_view field,
                         v1::DType dtype, size_t element_size,
                         absl::Span<const int> shape);

// Only the fields that are set travel; the server fills the defaults.
void EncodeConfig(const RemoteEnvConfig& config, v1::EnvConfig* proto);
RemoteEnvConfig DecodeConfig(const v1::EnvConfig& proto);

EnvInfo DecodeEnv(const v1::Env& proto);
// GetServerInfo's answer as the client's ServerInfo (server_info.cc).
ServerInfo DecodeServerInfo(const v1::ServerInfo& proto);

// A message in protobuf's JSON mapping with the proto's field names and
// every field printed, for EnvInfo::json and ServerInfo::json.
std::string JsonOf(const google::protobuf::Message& message);

// INVALID_ARGUMENT unless exactly one of the members is set.
absl::Status EncodeActions(const Actions& actions, v1::Array* proto);
// One agent's continuous action, float32 [2].
void EncodeAgentAction(
    const std::array<float, kRemoteContinuousActionSize>& action,
    v1::Array* proto);

// INTERNAL when the server's arrays do not have the documented dtype and
// shape (a version mismatch, never a user error).
absl::StatusOr<StepData> DecodeStepData(const v1::StepData& proto);
absl::StatusOr<AecState> DecodeAecState(const v1::AecState& proto);

RenderedFrame DecodeFrame(const v1::Frame& proto);

// The name of an mll.v1.Outcome code, from the proto's enum: OUTCOME_LANDED
// -> "landed"; OUTCOME_UNSPECIFIED (still flying) -> "none"; a code the proto
// does not know -> "unknown".
absl::string_view OutcomeName(int code);

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_WIRE_H_

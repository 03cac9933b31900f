// What GetServerInfo answers: the server's release, the wire protocol's
// version, its capabilities and its limits (proto: ServerInfo; policy:
// docs/server.md, "Versions and compatibility").
#ifndef MLL_SERVICE_SERVER_INFO_H_
#define MLL_SERVICE_SERVER_INFO_H_

#include "absl/strings/string_view.h"
#include "mll/service/service.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::service {

// The wire protocol this server speaks: mll.v1, minor 3. The minor goes up
// with every field, RPC or capability added within v1 (1: GetServerInfo; 2:
// PackedSteps.handle; 3: ServerInfo.load).
inline constexpr int kProtocolMajor = 1;
inline constexpr int kProtocolMinor = 3;

// Capability names (ServerInfo.capabilities); never reused for another
// meaning.
inline constexpr absl::string_view kCapabilityPackedStepBatch =
    "packed_step_batch";
inline constexpr absl::string_view kCapabilityAutoReset = "auto_reset";
inline constexpr absl::string_view kCapabilityKeepAlive = "keep_alive";
inline constexpr absl::string_view kCapabilitySharedMemorySessions =
    "shared_memory_sessions";
inline constexpr absl::string_view kCapabilityPackedBatchHandles =
    "packed_batch_handles";
inline constexpr absl::string_view kCapabilityServerLoad = "server_load";

// The project's version (CMake's PROJECT_VERSION), e.g. "0.1.0".
absl::string_view ServerVersion();

// The ServerInfo of a service run with `options`, less its load (filled at
// each answer).
v1::ServerInfo MakeServerInfo(const ServiceOptions& options);

}  // namespace mll::service

#endif  // MLL_SERVICE_SERVER_INFO_H_

#include "mll/service/server_info.h"

#include <string>

#include "absl/time/time.h"
#include "mll/core/env_config.h"

#ifndef MLL_PROJECT_VERSION
#error "MLL_PROJECT_VERSION must be defined (server/service/CMakeLists.txt)"
#endif

namespace mll::service {

absl::string_view ServerVersion() { return MLL_PROJECT_VERSION; }

v1::ServerInfo MakeServerInfo(const ServiceOptions& options) {
  v1::ServerInfo info;
  info.set_server_version(std::string(ServerVersion()));
  info.set_protocol_major(kProtocolMajor);
  info.set_protocol_minor(kProtocolMinor);
  for (absl::string_view capability :
       {kCapabilityPackedStepBatch, kCapabilityAutoReset, kCapabilityKeepAlive,
        kCapabilityPackedBatchHandles, kCapabilityServerLoad}) {
    info.add_capabilities(std::string(capability));
  }
  if (options.shared_memory_sessions > 0) {
    info.add_capabilities(std::string(kCapabilitySharedMemorySessions));
  }
  v1::ServerLimits& limits = *info.mutable_limits();
  limits.set_max_envs(options.max_envs);
  limits.set_max_envs_per_token(EffectiveMaxEnvsPerToken(options));
  limits.set_max_message_bytes(options.max_message_bytes);
  limits.set_idle_timeout_s(absl::ToDoubleSeconds(options.idle_timeout));
  limits.set_max_landers(core::kMaxLanders);
  limits.set_threads(options.threads);
  limits.set_shared_memory_sessions(options.shared_memory_sessions);
  return info;
}

}  // namespace mll::service

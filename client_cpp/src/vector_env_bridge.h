// What the C interface of VectorEnv (native/vector_c_api.cc) reads of it
// beyond the C++ API: the wire messages themselves, serialized, so that the
// Python client decodes them with its own stubs.
#ifndef MLL_CLIENT_SRC_VECTOR_ENV_BRIDGE_H_
#define MLL_CLIENT_SRC_VECTOR_ENV_BRIDGE_H_

#include <string>

#include "absl/status/statusor.h"
#include "mll/vector_env.h"

namespace mll::client {
namespace internal {

struct VectorEnvBridge {
  // Env 0's mll.v1.Env as its server created it (VectorEnv::Create; empty
  // for attached envs).
  static const std::string& Spec(const VectorEnv& envs);
  // The servers the VectorEnv knows (those of its address list, and those
  // that joined its names since), whether they hold envs or not.
  static int ServerCount(const VectorEnv& envs);
  // Server `server`'s address (0 <= server < ServerCount).
  static const std::string& ServerAddress(const VectorEnv& envs, int server);
  // Server `server`'s mll.v1.ServerInfo (GetServerInfo's answer, asked once
  // per stream), serialized.
  static absl::StatusOr<std::string> ServerInfo(VectorEnv& envs, int server);
};

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_VECTOR_ENV_BRIDGE_H_

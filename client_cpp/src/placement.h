// Where new envs go, and how a VectorEnv's envs even out over its servers:
// pure arithmetic, kept apart from the RPCs so that it is tested alone
// (tests/client_cpp/placement_test.cc).
#ifndef MLL_CLIENT_SRC_PLACEMENT_H_
#define MLL_CLIENT_SRC_PLACEMENT_H_

#include <vector>

#include "absl/types/span.h"
#include "mll/client_types.h"

namespace mll::client {
namespace internal {

// What a server reports of its load (ServerInfo.load and limits), as
// placement reads it.
struct ServerCapacity {
  // Envs hosted now, every tenant's (0 from a server that reports no load).
  int envs_hosted = 0;
  // limits.max_envs; 0: unknown (no bound, and counted as the largest known
  // bound when comparing fill levels).
  int max_envs = 0;
  // The tie-break: CPU used against the cores available (either 0: idle).
  double cpu_cores = 0;
  double cores_available = 0;
  // False: the server takes no new env (down, gone from its name, full).
  bool usable = true;
};

// What placement reads of a server's GetServerInfo answer (usable).
ServerCapacity CapacityOf(const ServerInfo& info);

// How many of `count` new envs each server gets (one entry per server):
// water-filling, each env in turn to the usable server with room whose fill
// after taking it, (envs_hosted + taken + 1) / max_envs, is lowest; ties to
// the lower CPU use (cpu_cores / cores_available), then the lower index.
// The fleet ends as even as the servers' hosting allows. The counts add up
// to less than `count` only when the usable servers' room runs out.
std::vector<int> PlanPlacement(absl::Span<const ServerCapacity> servers,
                               int count);

// The count of a VectorEnv's own envs each server should hold so that they
// are even within one over the `eligible` servers: the envs on eligible
// servers (`own[s]`, one entry per server) spread as evenly as possible, a
// server holding more keeping a remainder's extra env first (fewest moves).
// Ineligible servers keep what they hold.
std::vector<int> PlanEven(absl::Span<const int> own,
                          const std::vector<bool>& eligible);

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_PLACEMENT_H_

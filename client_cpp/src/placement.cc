#include "placement.h"

#include <algorithm>
#include <numeric>
#include <vector>

namespace mll::client {
namespace internal {
namespace {

double CpuUse(const ServerCapacity& server) {
  return server.cores_available > 0 ? server.cpu_cores / server.cores_available
                                    : 0.0;
}

}  // namespace

ServerCapacity CapacityOf(const ServerInfo& info) {
  ServerCapacity capacity;
  capacity.envs_hosted = info.load.envs_hosted;
  capacity.max_envs = info.max_envs;
  capacity.cpu_cores = info.load.cpu_cores;
  capacity.cores_available = info.load.cores_available;
  return capacity;
}

std::vector<int> PlanPlacement(absl::Span<const ServerCapacity> servers,
                               int count) {
  std::vector<int> taken(servers.size(), 0);
  // An unknown bound compares as the largest known one (1 when none is
  // known: the fill is then the count itself).
  long long unknown_bound = 1;
  for (const ServerCapacity& server : servers) {
    unknown_bound = std::max<long long>(unknown_bound, server.max_envs);
  }
  const auto bound = [&](size_t s) {
    return servers[s].max_envs > 0 ? servers[s].max_envs : unknown_bound;
  };
  const auto has_room = [&](size_t s) {
    return servers[s].usable &&
           (servers[s].max_envs <= 0 ||
            servers[s].envs_hosted + taken[s] < servers[s].max_envs);
  };
  for (int placed = 0; placed < count; ++placed) {
    int best = -1;
    for (size_t s = 0; s < servers.size(); ++s) {
      if (!has_room(s)) continue;
      if (best < 0) {
        best = static_cast<int>(s);
        continue;
      }
      // Fill after one more env, compared exactly: a/b < c/d as a*d < c*b.
      const long long mine =
          static_cast<long long>(servers[s].envs_hosted + taken[s] + 1) *
          bound(best);
      const long long theirs =
          static_cast<long long>(servers[best].envs_hosted + taken[best] + 1) *
          bound(s);
      if (mine < theirs ||
          (mine == theirs && CpuUse(servers[s]) < CpuUse(servers[best]))) {
        best = static_cast<int>(s);
      }
    }
    if (best < 0) break;
    ++taken[best];
  }
  return taken;
}

std::vector<int> PlanEven(absl::Span<const int> own,
                          const std::vector<bool>& eligible) {
  std::vector<int> target(own.begin(), own.end());
  std::vector<size_t> servers;
  int total = 0;
  for (size_t s = 0; s < own.size(); ++s) {
    if (s < eligible.size() && eligible[s]) {
      servers.push_back(s);
      total += own[s];
    }
  }
  if (servers.empty()) return target;
  const int base = total / static_cast<int>(servers.size());
  int extra = total % static_cast<int>(servers.size());
  // Those holding the most keep the remainder's extra envs.
  std::stable_sort(servers.begin(), servers.end(),
                   [&](size_t a, size_t b) { return own[a] > own[b]; });
  for (size_t s : servers) {
    target[s] = base + (extra > 0 ? 1 : 0);
    if (extra > 0) --extra;
  }
  return target;
}

}  // namespace internal
}  // namespace mll::client

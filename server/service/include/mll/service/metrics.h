// Counters of what the server does, rendered in Prometheus' text exposition
// format (version 0.0.4) for the /metrics endpoint. Recording is lock-free:
// relaxed atomics, one cache-line-aligned block per method so that calls of
// different methods on different threads do not share lines.
#ifndef MLL_SERVICE_METRICS_H_
#define MLL_SERVICE_METRICS_H_

#include <array>
#include <atomic>
#include <cstdint>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "google/protobuf/descriptor.h"
#include "mll/service/load_meter.h"
#include "mll/session_ops.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::service {

// The RPC methods of mll.v1.MultiLunarLander, as metric labels: enumerator i
// is the service descriptor's method i (same order as the proto), whose name
// is the label. Expanded from MLL_RPCS (mll/session_ops.h, one row per RPC);
// rpc_table_test checks the rows against the descriptor.
enum class Method {
#define MLL_METHOD_ENUMERATOR(method, ...) method,
  MLL_RPCS(MLL_METHOD_ENUMERATOR, MLL_METHOD_ENUMERATOR, MLL_METHOD_ENUMERATOR)
#undef MLL_METHOD_ENUMERATOR
};
#define MLL_METHOD_ONE(...) +1
inline constexpr int kMethodCount =
    0 MLL_RPCS(MLL_METHOD_ONE, MLL_METHOD_ONE, MLL_METHOD_ONE);
#undef MLL_METHOD_ONE

// The proto's service (mll.v1.MultiLunarLander), from the generated
// descriptors.
const google::protobuf::ServiceDescriptor& ServiceDescriptor();

// The method's name in the proto (its metric label).
absl::string_view MethodName(Method method);

class Metrics {
 public:
  // Upper bounds of the latency histogram's buckets in nanoseconds, 25 us to
  // 1 s in 1-2.5-5 steps: loopback calls take 40-300 us, batches and
  // renders milliseconds. A +Inf bucket follows.
  static constexpr std::array<int64_t, 15> kBucketBoundsNs = {
      25'000,     50'000,      100'000,     250'000,     500'000,
      1'000'000,  2'500'000,   5'000'000,   10'000'000,  25'000'000,
      50'000'000, 100'000'000, 250'000'000, 500'000'000, 1'000'000'000};

  Metrics();
  Metrics(const Metrics&) = delete;
  Metrics& operator=(const Metrics&) = delete;

  // One finished call (or Session request): its latency and, unless OK, its
  // code. Takes a load sample when one is due (LoadMeter).
  void RecordCall(Method method, absl::StatusCode code, int64_t latency_ns);
  // A successful parallel step's result: one env step and an agent-step per
  // agent that acted, or, for an auto-reset instead of a step, an episode.
  void RecordStepData(Method method, const v1::StepData& data);
  // Every stepped item of a StepBatch response (either form), as
  // RecordStepData.
  void RecordStepBatch(Method method, const v1::StepBatchResponse& response);
  // A successful StepAgent: one step; an agent-step unless it was a dead
  // step (no action).
  void RecordStepAgent(Method method, bool acted);
  // A successful ResetEnv.
  void RecordReset();
  // A successful packed StepBatch (any method), by how it gave its envs:
  // their names, or a declared handle alone (PackedSteps.handle).
  void RecordPackedBatch(bool by_handle);

  // CPU in cores and agent-steps per second over the last 10 s
  // (ServerInfo.load), taking a sample now.
  LoadMeter::Rates RecentLoad();

  // The exposition text, with `live_envs` as the environments gauge,
  // `live_by_tenant` (owner, envs; auth.h's owners, never a token) as the
  // per-tenant gauge, the process's resident memory read from
  // /proc/self/statm, and its CPU seconds and context switches (getrusage).
  std::string Render(int live_envs,
                     const std::vector<std::pair<std::string, int>>&
                         live_by_tenant = {}) const;

 private:
  static constexpr int kBuckets = kBucketBoundsNs.size() + 1;  // With +Inf.
  static constexpr int kCodes = 17;  // Canonical codes 0..16.

  // One env's successful step (or auto-reset), whatever form carried it;
  // `stepped` is its StepData.stepped bytes.
  void RecordEnvStep(Method method, bool auto_reset, absl::string_view stepped);

  struct alignas(64) PerMethod {
    std::atomic<uint64_t> buckets[kBuckets] = {};
    std::atomic<uint64_t> latency_sum_ns{0};
    std::atomic<uint64_t> errors[kCodes] = {};
    std::atomic<uint64_t> steps{0};
    std::atomic<uint64_t> agent_steps{0};
  };

  PerMethod& of(Method method) { return methods_[static_cast<int>(method)]; }
  // The counters LoadMeter samples, now.
  LoadMeter::Reading ReadLoad() const;

  std::array<PerMethod, kMethodCount> methods_;
  std::atomic<uint64_t> episodes_{0};
  std::atomic<uint64_t> packed_batches_[2] = {};  // [by_handle].
  LoadMeter load_;  // After methods_: its first reading sums their counters.
};

}  // namespace mll::service

#endif  // MLL_SERVICE_METRICS_H_

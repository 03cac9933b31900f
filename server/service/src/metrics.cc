#include "mll/service/metrics.h"

#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>

#include "absl/strings/str_cat.h"

namespace mll::service {
namespace {

constexpr std::memory_order kRelaxed = std::memory_order_relaxed;

// The methods that step environments, the only ones with step counters.
constexpr Method kStepMethods[] = {Method::kStepEnv, Method::kStepAgent,
                                   Method::kStepBatch, Method::kSession};

void Family(absl::string_view name, absl::string_view type,
            absl::string_view help, std::string* out) {
  absl::StrAppend(out, "# HELP ", name, " ", help, "\n# TYPE ", name, " ", type,
                  "\n");
}

int64_t SteadyNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

std::string MethodLabel(Method method) {
  return absl::StrCat("method=\"", MethodName(method), "\"");
}

// Resident set size from /proc/self/statm (pages), 0 if unreadable.
int64_t ResidentBytes() {
  FILE* statm = std::fopen("/proc/self/statm", "r");
  if (statm == nullptr) return 0;
  long total_pages = 0;
  long resident_pages = 0;
  const int read = std::fscanf(statm, "%ld %ld", &total_pages, &resident_pages);
  std::fclose(statm);
  if (read != 2) return 0;
  return static_cast<int64_t>(resident_pages) * sysconf(_SC_PAGESIZE);
}

// user + system CPU time as seconds with microseconds, in full: StrCat's
// six significant digits would round a long-running server's to seconds.
std::string CpuSeconds(const rusage& usage) {
  const int64_t us =
      (int64_t{usage.ru_utime.tv_sec} + usage.ru_stime.tv_sec) * 1'000'000 +
      usage.ru_utime.tv_usec + usage.ru_stime.tv_usec;
  char text[32];
  std::snprintf(text, sizeof(text), "%lld.%06lld",
                static_cast<long long>(us / 1'000'000),
                static_cast<long long>(us % 1'000'000));
  return text;
}

}  // namespace

const google::protobuf::ServiceDescriptor& ServiceDescriptor() {
  static const google::protobuf::ServiceDescriptor* const kService =
      v1::SessionRequest::descriptor()->file()->FindServiceByName(
          "MultiLunarLander");
  return *kService;
}

absl::string_view MethodName(Method method) {
  return ServiceDescriptor().method(static_cast<int>(method))->name();
}

Metrics::Metrics() : load_(ReadLoad()) {}

LoadMeter::Reading Metrics::ReadLoad() const {
  LoadMeter::Reading reading;
  reading.time_ns = SteadyNowNs();
  reading.cpu_ns = ProcessCpuNs();
  for (Method method : kStepMethods) {
    reading.agent_steps +=
        methods_[static_cast<int>(method)].agent_steps.load(kRelaxed);
  }
  return reading;
}

LoadMeter::Rates Metrics::RecentLoad() {
  const LoadMeter::Reading now = ReadLoad();
  const LoadMeter::Rates rates = load_.Over(now);
  load_.Add(now);
  return rates;
}

void Metrics::RecordCall(Method method, absl::StatusCode code,
                         int64_t latency_ns) {
  if (load_.Due(SteadyNowNs())) load_.Add(ReadLoad());
  PerMethod& m = of(method);
  const int bucket =
      static_cast<int>(std::lower_bound(kBucketBoundsNs.begin(),
                                        kBucketBoundsNs.end(), latency_ns) -
                       kBucketBoundsNs.begin());
  m.buckets[bucket].fetch_add(1, kRelaxed);
  m.latency_sum_ns.fetch_add(
      static_cast<uint64_t>(std::max<int64_t>(latency_ns, 0)), kRelaxed);
  const int code_index = static_cast<int>(code);
  if (code != absl::StatusCode::kOk && code_index >= 0 && code_index < kCodes) {
    m.errors[code_index].fetch_add(1, kRelaxed);
  }
}

void Metrics::RecordEnvStep(Method method, bool auto_reset,
                            absl::string_view stepped) {
  if (auto_reset) {
    episodes_.fetch_add(1, kRelaxed);
    return;
  }
  const uint64_t acted = static_cast<uint64_t>(
      stepped.size() - std::count(stepped.begin(), stepped.end(), '\0'));
  PerMethod& m = of(method);
  m.steps.fetch_add(1, kRelaxed);
  m.agent_steps.fetch_add(acted, kRelaxed);
}

void Metrics::RecordStepData(Method method, const v1::StepData& data) {
  RecordEnvStep(method, data.auto_reset(), data.stepped().data());
}

void Metrics::RecordStepBatch(Method method,
                              const v1::StepBatchResponse& response) {
  for (const v1::StepBatchResult& result : response.results()) {
    if (result.has_data()) RecordStepData(method, result.data());
  }
  if (!response.has_packed()) return;
  const v1::PackedStepData& packed = response.packed();
  const int num_envs = packed.auto_reset().data().size();
  if (num_envs == 0) return;
  const absl::string_view stepped = packed.stepped().data();
  const size_t n_landers = stepped.size() / num_envs;
  auto error = packed.errors().begin();  // In increasing index order.
  for (int e = 0; e < num_envs; ++e) {
    if (error != packed.errors().end() && error->index() == e) {
      ++error;
      continue;
    }
    RecordEnvStep(method, packed.auto_reset().data()[e] != 0,
                  stepped.substr(e * n_landers, n_landers));
  }
}

void Metrics::RecordStepAgent(Method method, bool acted) {
  PerMethod& m = of(method);
  m.steps.fetch_add(1, kRelaxed);
  if (acted) m.agent_steps.fetch_add(1, kRelaxed);
}

void Metrics::RecordReset() { episodes_.fetch_add(1, kRelaxed); }

void Metrics::RecordPackedBatch(bool by_handle) {
  packed_batches_[by_handle ? 1 : 0].fetch_add(1, kRelaxed);
}

std::string Metrics::Render(
    int live_envs,
    const std::vector<std::pair<std::string, int>>& live_by_tenant) const {
  std::string out;
  Family("mll_envs_live", "gauge", "Environments hosted now.", &out);
  absl::StrAppend(&out, "mll_envs_live ", live_envs, "\n");
  Family("mll_tenant_envs_live", "gauge",
         "Environments hosted now (or being built) per tenant: token#N is the "
         "N-th token of --auth_token_file, anonymous a server without tokens; "
         "tenants without environments are not listed.",
         &out);
  for (const auto& [tenant, count] : live_by_tenant) {
    absl::StrAppend(&out, "mll_tenant_envs_live{tenant=\"",
                    tenant.empty() ? "anonymous" : tenant, "\"} ", count, "\n");
  }
  Family("mll_episodes_started_total", "counter",
         "Episodes started, by ResetEnv or by an auto_reset step.", &out);
  absl::StrAppend(&out, "mll_episodes_started_total ", episodes_.load(kRelaxed),
                  "\n");
  Family("mll_steps_total", "counter",
         "Environment steps (StepAgent: agent turns), by method.", &out);
  for (Method method : kStepMethods) {
    absl::StrAppend(&out, "mll_steps_total{", MethodLabel(method), "} ",
                    methods_[static_cast<int>(method)].steps.load(kRelaxed),
                    "\n");
  }
  Family("mll_agent_steps_total", "counter",
         "Actions applied to active landers, by method.", &out);
  for (Method method : kStepMethods) {
    absl::StrAppend(
        &out, "mll_agent_steps_total{", MethodLabel(method), "} ",
        methods_[static_cast<int>(method)].agent_steps.load(kRelaxed), "\n");
  }
  Family("mll_packed_batches_total", "counter",
         "Packed StepBatches stepped, by how they gave their envs: names, or "
         "a handle declared on their Session (PackedSteps.handle).",
         &out);
  absl::StrAppend(&out, "mll_packed_batches_total{envs=\"names\"} ",
                  packed_batches_[0].load(kRelaxed), "\n");
  absl::StrAppend(&out, "mll_packed_batches_total{envs=\"handle\"} ",
                  packed_batches_[1].load(kRelaxed), "\n");
  Family("mll_rpc_duration_seconds", "histogram",
         "Time in the server from a call's (or Session request's) arrival at "
         "its handler to its status, by method.",
         &out);
  for (int i = 0; i < kMethodCount; ++i) {
    const PerMethod& m = methods_[i];
    const std::string label = MethodLabel(static_cast<Method>(i));
    // Cumulated here, so that _count always equals the +Inf bucket.
    uint64_t cumulative = 0;
    for (int b = 0; b < kBuckets; ++b) {
      cumulative += m.buckets[b].load(kRelaxed);
      const std::string le =
          b < kBuckets - 1 ? absl::StrCat(kBucketBoundsNs[b] * 1e-9) : "+Inf";
      absl::StrAppend(&out, "mll_rpc_duration_seconds_bucket{", label, ",le=\"",
                      le, "\"} ", cumulative, "\n");
    }
    absl::StrAppend(&out, "mll_rpc_duration_seconds_sum{", label, "} ",
                    m.latency_sum_ns.load(kRelaxed) * 1e-9, "\n");
    absl::StrAppend(&out, "mll_rpc_duration_seconds_count{", label, "} ",
                    cumulative, "\n");
  }
  Family("mll_rpc_errors_total", "counter",
         "Calls (and Session requests) that ended in an error, by method and "
         "gRPC code; combinations not seen yet are omitted.",
         &out);
  for (int i = 0; i < kMethodCount; ++i) {
    for (int code = 1; code < kCodes; ++code) {
      const uint64_t count = methods_[i].errors[code].load(kRelaxed);
      if (count == 0) continue;
      absl::StrAppend(
          &out, "mll_rpc_errors_total{", MethodLabel(static_cast<Method>(i)),
          ",code=\"",
          absl::StatusCodeToString(static_cast<absl::StatusCode>(code)), "\"} ",
          count, "\n");
    }
  }
  Family("process_resident_memory_bytes", "gauge",
         "Resident memory of the server process in bytes.", &out);
  absl::StrAppend(&out, "process_resident_memory_bytes ", ResidentBytes(),
                  "\n");
  // Every thread's: gRPC's, the workers', the shared-memory sessions'. Its
  // rate over mll_agent_steps_total's is the server's CPU per agent-step.
  rusage usage = {};
  getrusage(RUSAGE_SELF, &usage);
  Family("process_cpu_seconds_total", "counter",
         "User and system CPU time of the server process in seconds.", &out);
  absl::StrAppend(&out, "process_cpu_seconds_total ", CpuSeconds(usage), "\n");
  Family("mll_process_context_switches_total", "counter",
         "Context switches of the server's threads: voluntary (a thread "
         "blocked, e.g. to wait for work or a message: each is a later "
         "wake-up) and involuntary (preempted).",
         &out);
  absl::StrAppend(&out,
                  "mll_process_context_switches_total{kind=\"voluntary\"} ",
                  usage.ru_nvcsw, "\n");
  absl::StrAppend(&out,
                  "mll_process_context_switches_total{kind=\"involuntary\"} ",
                  usage.ru_nivcsw, "\n");
  return out;
}

}  // namespace mll::service

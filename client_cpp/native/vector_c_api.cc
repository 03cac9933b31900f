#include "vector_c_api.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <type_traits>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/ascii.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "absl/types/span.h"
#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.pb.h"
#include "mll/vector_env.h"
#include "native_options.h"
#include "result_columns.h"
#include "vector_env_bridge.h"
#include "wire.h"

namespace {

using ::mll::client::Client;
using ::mll::client::ClientOptions;
using ::mll::client::VectorEnv;
using ::mll::client::internal::CodeOf;
using ::mll::client::internal::kResultColumnCount;
using ::mll::client::internal::kResultColumns;
using ::mll::client::internal::VectorEnvBridge;

// The longest step timeout, in seconds (about 31 years).
constexpr double kMaxStepTimeoutS = 1e9;

// The VectorEnv of `config` (a serialized mll.v1.EnvConfig) on the servers
// of `addresses` (comma-separated).
absl::StatusOr<VectorEnv> CreateVectorEnv(
    const char* addresses, ClientOptions options, const char* config,
    size_t config_size, int num_envs, int batch_size, int failover,
    double step_timeout_s, double rediscover_interval_s) {
  if (std::isnan(rediscover_interval_s) ||
      rediscover_interval_s > kMaxStepTimeoutS) {
    return absl::InvalidArgumentError(
        absl::StrCat("rediscover_interval_s is ", rediscover_interval_s,
                     "; allowed: < 0 (the client's default), 0 (never) or up "
                     "to ",
                     kMaxStepTimeoutS, " seconds"));
  }
  if (rediscover_interval_s >= 0) {
    options.rediscover_interval = std::chrono::milliseconds(
        static_cast<int64_t>(std::llround(rediscover_interval_s * 1000)));
  }
  if (std::isnan(step_timeout_s) || step_timeout_s > kMaxStepTimeoutS) {
    return absl::InvalidArgumentError(
        absl::StrCat("step_timeout_s is ", step_timeout_s,
                     "; allowed: < 0 (the client's default), 0 (none) or up "
                     "to ",
                     kMaxStepTimeoutS, " seconds"));
  }
  if (step_timeout_s >= 0) {
    options.step_timeout = std::chrono::milliseconds(
        static_cast<int64_t>(std::llround(step_timeout_s * 1000)));
  }
  mll::v1::EnvConfig proto;
  if (config_size > 0 &&
      !proto.ParseFromArray(config, static_cast<int>(config_size))) {
    return absl::InvalidArgumentError(
        absl::StrCat("config is ", config_size,
                     " bytes that are not a serialized mll.v1.EnvConfig"));
  }
  if (failover < -1 || failover > 1) {
    return absl::InvalidArgumentError(absl::StrCat(
        "failover is ", failover, "; allowed: -1 (unset), 0 (off), 1 (on)"));
  }
  std::vector<std::string> servers;
  for (absl::string_view address :
       absl::StrSplit(addresses == nullptr ? "" : addresses, ',')) {
    servers.emplace_back(absl::StripAsciiWhitespace(address));
  }
  absl::StatusOr<Client> client = Client::Create(servers, options);
  if (!client.ok()) return client.status();
  // A server this client cannot use (another protocol major, or without
  // packed batches or auto-reset) is refused before anything is created on
  // it, as Client::CreateEnv refuses it.
  static constexpr absl::string_view kNeeds[] = {"packed_step_batch",
                                                 "auto_reset"};
  for (int server = 0; server < client->server_count(); ++server) {
    absl::StatusOr<mll::client::ServerInfo> info =
        client->GetServerInfo(server);
    // One of several that does not answer takes no env (VectorEnv::Create).
    if (!info.ok() && client->server_count() > 1 &&
        absl::IsUnavailable(info.status())) {
      continue;
    }
    if (!info.ok()) return info.status();
    if (absl::Status compatible =
            Client::CheckCompatible(*info, client->address(server), kNeeds);
        !compatible.ok()) {
      return compatible;
    }
  }
  return VectorEnv::Create(
      *client, num_envs, mll::client::internal::DecodeConfig(proto), batch_size,
      failover < 0 ? std::nullopt : std::optional<bool>(failover == 1));
}

// Copies the latest results' columns into `buffers` (one per column, in the
// table's order; NULL skips its column).
void CopyResults(const VectorEnv& envs, void* const* buffers) {
  int column = 0;
  // Each column's accessor of the same name, in the table's order.
#define MLL_COPY_COLUMN(name, type, per_agent, width)                          \
  {                                                                            \
    const auto values = envs.name();                                           \
    static_assert(                                                             \
        std::is_same_v<                                                        \
            std::remove_const_t<typename decltype(values)::value_type>, type>, \
        "VectorEnv::" #name "() has the column's element type");               \
    if (buffers[column] != nullptr) {                                          \
      std::memcpy(buffers[column], values.data(),                              \
                  values.size() * sizeof(type));                               \
    }                                                                          \
    ++column;                                                                  \
  }
  MLL_RESULT_COLUMNS(MLL_COPY_COLUMN)
#undef MLL_COPY_COLUMN
}

}  // namespace

struct mll_vector_env {
  absl::Status create_status;
  std::optional<VectorEnv> envs;
  // The last failure's message; the failover lines not yet taken, and the
  // ones handed out; what the latest call returned by pointer.
  std::string message;
  std::string events;
  std::string taken_events;
  std::string returned;
  std::string snapshot;

  // INVALID_ARGUMENT unless `rows` is a row count of results (num_envs or
  // batch_size).
  int CheckRows(int rows) {
    if (rows == envs->num_envs() || rows == envs->batch_size()) return 0;
    return Report(absl::InvalidArgumentError(absl::StrCat(
        "rows is ", rows, "; allowed: num_envs = ", envs->num_envs(),
        " or batch_size = ", envs->batch_size())));
  }

  // The code of `status` (its message kept).
  int Report(const absl::Status& status) {
    if (!status.ok()) message = std::string(status.message());
    return CodeOf(status);
  }
  // As Report, with MLL_NATIVE_STREAM_PENDING for a wait that timed out.
  int Report(const std::optional<absl::Status>& status) {
    return status.has_value() ? Report(*status) : MLL_NATIVE_STREAM_PENDING;
  }
  // As Report, for a call that makes results: once it succeeded, they go
  // into the buffers bound for their row count, if any.
  template <typename Status>
  int Deliver(const Status& status) {
    const int code = Report(status);
    if (code == 0) {
      const auto found = bound.find(static_cast<int>(envs->env_ids().size()));
      if (found != bound.end()) found->second.Write(*envs);
    }
    return code;
  }

  // The caller's buffers for results of one row count
  // (mll_vector_env_bind_results), and the caller's offset into them
  // (mll_vector_env_bind_results_offset).
  struct BoundResults {
    std::vector<void*> buffers;
    const int64_t* offset = nullptr;

    void Write(const VectorEnv& results) const {
      if (buffers.empty()) return;
      const int64_t shift = offset == nullptr ? 0 : *offset;
      void* moved[kResultColumnCount];
      for (int column = 0; column < kResultColumnCount; ++column) {
        moved[column] = buffers[column] == nullptr
                            ? nullptr
                            : static_cast<char*>(buffers[column]) + shift;
      }
      CopyResults(results, moved);
    }
  };
  std::map<int, BoundResults> bound;
  // send's env_ids as VectorEnv::Send takes them (kept: no allocation per
  // call).
  std::vector<int> send_ids;
  // The caller's flag of events waiting (mll_vector_env_bind_event_flag).
  int32_t* event_flag = nullptr;
};

namespace {

// The envs' actions as the span VectorEnv takes, then `call` of it.
template <typename Call>
absl::Status WithActions(const void* actions, size_t count, int continuous,
                         Call call) {
  if (actions == nullptr && count > 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("actions is NULL with a count of ", count));
  }
  if (continuous) {
    return call(absl::MakeConstSpan(static_cast<const float*>(actions), count));
  }
  return call(absl::MakeConstSpan(static_cast<const int32_t*>(actions), count));
}

}  // namespace

extern "C" {

int mll_vector_env_column_count(void) { return kResultColumnCount; }

const char* mll_vector_env_column_name(int column) {
  if (column < 0 || column >= kResultColumnCount) return nullptr;
  return kResultColumns[column].name;
}

int mll_vector_env_column_dtype(int column) {
  if (column < 0 || column >= kResultColumnCount) return 0;
  return kResultColumns[column].dtype;
}

int mll_vector_env_column_per_agent(int column) {
  if (column < 0 || column >= kResultColumnCount) return 0;
  return kResultColumns[column].per_agent ? 1 : 0;
}

int mll_vector_env_column_width(int column) {
  if (column < 0 || column >= kResultColumnCount) return 0;
  return kResultColumns[column].width;
}

mll_vector_env* mll_vector_env_new(
    const char* addresses, const char* root_cert_pem, size_t root_cert_size,
    const char* server_name, const char* token, int transport,
    const char* config, size_t config_size, int num_envs, int batch_size,
    int failover, double step_timeout_s, double rediscover_interval_s) {
  mll::client::internal::KeepGrpcInitialised();
  auto* handle = new mll_vector_env;
  absl::StatusOr<VectorEnv> envs = CreateVectorEnv(
      addresses,
      mll::client::internal::NativeClientOptions(root_cert_pem, root_cert_size,
                                                 server_name, token, transport),
      config, config_size, num_envs, batch_size, failover, step_timeout_s,
      rediscover_interval_s);
  if (!envs.ok()) {
    handle->create_status = envs.status();
    handle->Report(envs.status());
    return handle;
  }
  handle->envs.emplace(*std::move(envs));
  handle->envs->SetEventLog([handle](const std::string& line) {
    if (!handle->events.empty()) handle->events += '\n';
    handle->events += line;
    if (handle->event_flag != nullptr) *handle->event_flag = 1;
  });
  return handle;
}

int mll_vector_env_create_status(const mll_vector_env* env) {
  return CodeOf(env->create_status);
}

const char* mll_vector_env_message(const mll_vector_env* env) {
  return env->message.c_str();
}

void mll_vector_env_free(mll_vector_env* env) { delete env; }

int mll_vector_env_num_envs(const mll_vector_env* env) {
  return env->envs ? env->envs->num_envs() : 0;
}

int mll_vector_env_n_landers(const mll_vector_env* env) {
  return env->envs ? env->envs->n_landers() : 0;
}

int mll_vector_env_continuous(const mll_vector_env* env) {
  return env->envs && env->envs->continuous() ? 1 : 0;
}

int mll_vector_env_batch_size(const mll_vector_env* env) {
  return env->envs ? env->envs->batch_size() : 0;
}

int mll_vector_env_failover(const mll_vector_env* env) {
  return env->envs && env->envs->failover() ? 1 : 0;
}

int mll_vector_env_rebalances(const mll_vector_env* env) {
  return env->envs ? env->envs->rebalances() : 0;
}

int mll_vector_env_failovers(const mll_vector_env* env) {
  return env->envs ? env->envs->failovers() : 0;
}

int mll_vector_env_spec(const mll_vector_env* env, const char** data,
                        size_t* size) {
  if (!env->envs) return CodeOf(env->create_status);
  const std::string& spec = VectorEnvBridge::Spec(*env->envs);
  *data = spec.data();
  *size = spec.size();
  return 0;
}

const char* mll_vector_env_name(const mll_vector_env* env, int index) {
  if (!env->envs || index < 0 || index >= env->envs->num_envs()) {
    return nullptr;
  }
  return env->envs->names()[index].c_str();
}

const char* mll_vector_env_env_address(const mll_vector_env* env, int index) {
  if (!env->envs || index < 0 || index >= env->envs->num_envs()) {
    return nullptr;
  }
  // The handle's own copy, so that the pointer lives past this call.
  auto* mutable_env = const_cast<mll_vector_env*>(env);
  mutable_env->returned = env->envs->address(index);
  return mutable_env->returned.c_str();
}

int mll_vector_env_server_count(const mll_vector_env* env) {
  return env->envs ? VectorEnvBridge::ServerCount(*env->envs) : 0;
}

const char* mll_vector_env_server_address(const mll_vector_env* env,
                                          int server) {
  if (server < 0 || server >= mll_vector_env_server_count(env)) {
    return nullptr;
  }
  return VectorEnvBridge::ServerAddress(*env->envs, server).c_str();
}

int mll_vector_env_server_info(const mll_vector_env* env, int server,
                               const char** data, size_t* size) {
  auto* handle = const_cast<mll_vector_env*>(env);
  if (!env->envs) return CodeOf(env->create_status);
  if (server < 0 || server >= mll_vector_env_server_count(env)) {
    return handle->Report(absl::InvalidArgumentError(
        absl::StrCat("server is ", server, "; allowed: 0..",
                     mll_vector_env_server_count(env) - 1)));
  }
  absl::StatusOr<std::string> info =
      VectorEnvBridge::ServerInfo(*handle->envs, server);
  if (!info.ok()) return handle->Report(info.status());
  handle->returned = *std::move(info);
  *data = handle->returned.data();
  *size = handle->returned.size();
  return 0;
}

const char* mll_vector_env_transport(mll_vector_env* env) {
  if (!env->envs) return "";
  env->returned = env->envs->transport();
  return env->returned.c_str();
}

const char* mll_vector_env_take_events(mll_vector_env* env) {
  env->taken_events.swap(env->events);
  env->events.clear();
  if (env->event_flag != nullptr) *env->event_flag = 0;
  return env->taken_events.c_str();
}

void mll_vector_env_bind_event_flag(mll_vector_env* env, int32_t* flag) {
  env->event_flag = flag;
  if (flag != nullptr) *flag = env->events.empty() ? 0 : 1;
}

int mll_vector_env_reset(mll_vector_env* env, int has_seed, uint64_t seed) {
  if (!env->envs) return CodeOf(env->create_status);
  return env->Deliver(env->envs->Reset(has_seed ? std::optional<uint64_t>(seed)
                                                : std::nullopt));
}

int mll_vector_env_step_async(mll_vector_env* env, const void* actions,
                              size_t count, int continuous) {
  if (!env->envs) return CodeOf(env->create_status);
  return env->Report(WithActions(actions, count, continuous, [&](auto span) {
    return env->envs->StepAsync(span);
  }));
}

int mll_vector_env_step(mll_vector_env* env, const void* actions, size_t count,
                        int continuous, int timeout_ms) {
  const int code = mll_vector_env_step_async(env, actions, count, continuous);
  return code != 0 ? code : mll_vector_env_step_wait(env, timeout_ms);
}

int mll_vector_env_step_wait(mll_vector_env* env, int timeout_ms) {
  if (!env->envs) return CodeOf(env->create_status);
  if (timeout_ms < 0) return env->Deliver(env->envs->StepWait());
  return env->Deliver(
      env->envs->StepWait(std::chrono::milliseconds(timeout_ms)));
}

int mll_vector_env_async_reset(mll_vector_env* env, int has_seed,
                               uint64_t seed) {
  if (!env->envs) return CodeOf(env->create_status);
  return env->Report(env->envs->AsyncReset(
      has_seed ? std::optional<uint64_t>(seed) : std::nullopt));
}

int mll_vector_env_send(mll_vector_env* env, const void* actions, size_t count,
                        int continuous, const int64_t* env_ids,
                        size_t env_count) {
  if (!env->envs) return CodeOf(env->create_status);
  if (env_ids == nullptr && env_count > 0) {
    return env->Report(absl::InvalidArgumentError(
        absl::StrCat("env_ids is NULL with a count of ", env_count)));
  }
  // VectorEnv::Send checks the indices (range, repeats, in flight); only
  // those that no int holds are refused here.
  std::vector<int>& ids = env->send_ids;
  ids.resize(env_count);
  for (size_t k = 0; k < env_count; ++k) {
    if (env_ids[k] < std::numeric_limits<int>::min() ||
        env_ids[k] > std::numeric_limits<int>::max()) {
      return env->Report(absl::InvalidArgumentError(
          absl::StrCat("env_ids holds ", env_ids[k], "; allowed: 0..",
                       env->envs->num_envs() - 1)));
    }
    ids[k] = static_cast<int>(env_ids[k]);
  }
  return env->Report(WithActions(actions, count, continuous, [&](auto span) {
    return env->envs->Send(span, absl::MakeConstSpan(ids));
  }));
}

int mll_vector_env_recv(mll_vector_env* env, int timeout_ms) {
  if (!env->envs) return CodeOf(env->create_status);
  if (timeout_ms < 0) return env->Deliver(env->envs->Recv());
  return env->Deliver(env->envs->Recv(std::chrono::milliseconds(timeout_ms)));
}

int mll_vector_env_in_flight(const mll_vector_env* env) {
  return env->envs ? env->envs->in_flight() : 0;
}

int mll_vector_env_rows(const mll_vector_env* env) {
  return env->envs ? static_cast<int>(env->envs->env_ids().size()) : 0;
}

void mll_vector_env_results(const mll_vector_env* env, void* const* buffers) {
  if (env->envs) CopyResults(*env->envs, buffers);
}

int mll_vector_env_bind_results(mll_vector_env* env, int rows,
                                void* const* buffers) {
  if (!env->envs) return CodeOf(env->create_status);
  if (const int code = env->CheckRows(rows); code != 0) return code;
  if (buffers == nullptr) {
    env->bound[rows].buffers.clear();
  } else {
    env->bound[rows].buffers.assign(buffers, buffers + kResultColumnCount);
  }
  return 0;
}

int mll_vector_env_bind_results_offset(mll_vector_env* env, int rows,
                                       const int64_t* offset) {
  if (!env->envs) return CodeOf(env->create_status);
  if (const int code = env->CheckRows(rows); code != 0) return code;
  env->bound[rows].offset = offset;
  return 0;
}

int mll_vector_env_snapshot(mll_vector_env* env, int index, const char** data,
                            size_t* size) {
  if (!env->envs) return CodeOf(env->create_status);
  absl::StatusOr<std::string> snapshot = env->envs->EnvSnapshot(index);
  if (!snapshot.ok()) return env->Report(snapshot.status());
  env->snapshot = *std::move(snapshot);
  *data = env->snapshot.data();
  *size = env->snapshot.size();
  return 0;
}

int mll_vector_env_restore(mll_vector_env* env, int index, const char* snapshot,
                           size_t size, float* observations) {
  if (!env->envs) return CodeOf(env->create_status);
  absl::StatusOr<std::vector<float>> restored =
      env->envs->RestoreEnv(index, absl::string_view(snapshot, size));
  if (!restored.ok()) return env->Report(restored.status());
  std::memcpy(observations, restored->data(), restored->size() * sizeof(float));
  return 0;
}

}  // extern "C"

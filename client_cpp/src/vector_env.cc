#include "mll/vector_env.h"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <deque>
#include <functional>
#include <future>
#include <map>
#include <optional>
#include <set>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "absl/time/clock.h"
#include "absl/time/time.h"
#include "channel.h"
#include "discovery.h"
#include "env_record.h"
#include "grpcpp/client_context.h"
#include "placement.h"
#include "result_columns.h"
#include "transport.h"
#include "vector_env_bridge.h"
#include "wire.h"

namespace mll::client {

using internal::AddressEntry;
using internal::EnvRecord;
using internal::ServerCapacity;
using internal::StreamTransport;

namespace {

constexpr int kMaxVectorEnvs = 65536;
// Replay requests in flight on one stream at once: enough to keep the server
// busy, few enough that a long record does not queue all its requests.
constexpr size_t kReplayWindow = 64;
// How long failover waits for a server found down to answer its probe.
constexpr absl::Duration kProbeDeadline = absl::Seconds(2);

// Whether `error` says the server is lost: unreachable (UNAVAILABLE, a
// draining server's "draining: ..." included), or stalled (it missed its
// deadline, ClientOptions::step_timeout: DEADLINE_EXCEEDED, after which its
// Session stream is cancelled).
bool ServerLost(const absl::Status& error) {
  return absl::IsUnavailable(error) || absl::IsDeadlineExceeded(error);
}

// When a wait that may return early (StepWait, Recv with a timeout) gives
// up; kNoDeadline never comes.
using Deadline = std::chrono::steady_clock::time_point;
constexpr Deadline kNoDeadline = Deadline::max();

Deadline DeadlineAfter(std::chrono::milliseconds timeout) {
  return std::chrono::steady_clock::now() + timeout;
}

// The time left until `deadline` (none left: zero).
absl::Duration Remaining(Deadline deadline) {
  if (deadline == kNoDeadline) return absl::InfiniteDuration();
  return std::max(absl::FromChrono(deadline - std::chrono::steady_clock::now()),
                  absl::ZeroDuration());
}

// Every request of `requests` sent on `transport` before any answer is
// awaited (pipelined), then the answers in order; the first failure, with the
// others still received.
absl::Status CallPipelined(StreamTransport& transport,
                           std::vector<v1::SessionRequest>& requests,
                           std::vector<v1::SessionResponse>* responses,
                           std::vector<absl::Status>* statuses = nullptr) {
  responses->assign(requests.size(), v1::SessionResponse());
  std::vector<absl::StatusOr<uint64_t>> sequences;
  sequences.reserve(requests.size());
  for (v1::SessionRequest& request : requests) {
    // A failed Send ended the stream; another would open a new one, which
    // forgets the requests lost with this one: the rest fail alike.
    if (!sequences.empty() && !sequences.back().ok()) {
      sequences.push_back(sequences.back().status());
    } else {
      sequences.push_back(transport.Send(request));
    }
  }
  absl::Status first = absl::OkStatus();
  for (size_t k = 0; k < requests.size(); ++k) {
    absl::Status status = sequences[k].status();
    if (status.ok())
      status = transport.Receive(*sequences[k], &(*responses)[k]);
    if (statuses != nullptr) statuses->push_back(status);
    if (first.ok()) first = status;
  }
  return first;
}

// One server's share of a step: env rows `rows` (in env order), and its
// packed StepBatch request, of which each step of every env replaces only
// the action bytes.
struct Shard {
  int server = 0;
  StreamTransport* transport = nullptr;
  std::vector<int> rows;
  v1::SessionRequest request;
  v1::SessionResponse response;
};

// Envs, each with its error (e.g. the status that lost it, for failover), in
// env order.
using EnvErrors = std::map<int, absl::Status>;

// Result columns of some envs (rows), env-major: one member per column of
// MLL_RESULT_COLUMNS.
struct Columns {
#define MLL_COLUMN_MEMBER(name, type, per_agent, width) std::vector<type> name;
  MLL_RESULT_COLUMNS(MLL_COLUMN_MEMBER)
#undef MLL_COLUMN_MEMBER

  // Elements per row of a column, with n landers.
  static size_t RowSize(bool per_agent, int width, int n) {
    return static_cast<size_t>(per_agent ? n : 1) * width;
  }

  // `rows` rows of n landers, zero.
  void Resize(size_t rows, int n) {
#define MLL_COLUMN_RESIZE(name, type, per_agent, width) \
  name.assign(rows* RowSize(per_agent, width, n), type{0});
    MLL_RESULT_COLUMNS(MLL_COLUMN_RESIZE)
#undef MLL_COLUMN_RESIZE
  }

  // Marks the rows that carry a transition: stepped (already in `active`)
  // and not an auto-reset.
  void MaskAutoResetRows(int n) {
    for (size_t row = 0; row < auto_reset.size(); ++row) {
      if (auto_reset[row]) std::memset(active.data() + row * n, 0, n);
    }
  }

  // Row `from` of `source` into row `to`.
  void CopyRow(const Columns& source, size_t from, size_t to, int n) {
#define MLL_COLUMN_COPY_ROW(name, type, per_agent, width) \
  {                                                       \
    const size_t size = RowSize(per_agent, width, n);     \
    std::copy_n(source.name.begin() + from * size, size,  \
                name.begin() + to * size);                \
  }
    MLL_RESULT_COLUMNS(MLL_COLUMN_COPY_ROW)
#undef MLL_COLUMN_COPY_ROW
  }
};

// Results received by the async API and not yet returned by Recv: the env
// of each row, in the order they came.
struct ReadyChunk {
  std::vector<int> envs;
  Columns columns;
  size_t taken = 0;  // Rows already returned.
};

// An async request in flight: its server, its sequence (or the loss of its
// server that kept it from going out, which the Recv that meets it fails
// over), its envs and their action rows (row_bytes each, in `envs` order):
// what their records take, and what failover sends again.
// `answer` holds the status of the answer once a Recv with a timeout has
// received it (the answer itself in `response`), until the Recv takes it.
struct PendingRequest {
  int server = 0;
  absl::StatusOr<uint64_t> sequence;
  std::vector<int> envs;
  std::string actions;
  std::optional<absl::Status> answer;
  v1::SessionResponse response;
};

// Copies a packed column's rows (`width` elements each) into `out` at rows
// `rows` (row k of the column to row rows[k]); INTERNAL when the column has
// the wrong dtype or shape.
template <typename T>
absl::Status Scatter(const v1::Array& column, absl::string_view field,
                     v1::DType dtype, const std::vector<int>& rows,
                     std::vector<int> shape, size_t width, T* out) {
  absl::Status status = internal::CheckColumn(column, field, dtype, sizeof(T),
                                              absl::MakeConstSpan(shape));
  if (!status.ok()) return status;
  const char* data = column.data().data();
  const size_t row_bytes = width * sizeof(T);
  if (rows.size() == 1 ||
      (rows.size() > 1 &&
       rows.back() == rows[0] + static_cast<int>(rows.size()) - 1)) {
    // Consecutive rows (one server): one copy.
    std::memcpy(out + rows[0] * width, data, rows.size() * row_bytes);
    return absl::OkStatus();
  }
  for (size_t k = 0; k < rows.size(); ++k) {
    std::memcpy(out + rows[k] * width, data + k * row_bytes, row_bytes);
  }
  return absl::OkStatus();
}

// A packed StepBatch's results into `out` at rows `rows`; INTERNAL when a
// column has the wrong dtype or shape.
absl::Status DecodePacked(const v1::PackedStepData& packed,
                          const std::vector<int>& rows, int n, Columns* out) {
  const int count = static_cast<int>(rows.size());
  const size_t agents = static_cast<size_t>(n);
  absl::Status status = absl::OkStatus();
  // Each column in turn, until one is wrong.
  const auto column = [&](const v1::Array& array, absl::string_view field,
                          v1::DType dtype, std::vector<int> shape, size_t width,
                          auto* into) {
    if (status.ok()) {
      status =
          Scatter(array, field, dtype, rows, std::move(shape), width, into);
    }
  };
  column(packed.observations(), "observations", v1::DTYPE_FLOAT32,
         {count, n, kRemoteObservationSize}, agents * kRemoteObservationSize,
         out->observations.data());
  column(packed.rewards(), "rewards", v1::DTYPE_FLOAT32, {count, n}, agents,
         out->rewards.data());
  column(packed.episode_returns(), "episode_returns", v1::DTYPE_FLOAT32,
         {count, n}, agents, out->episode_returns.data());
  column(packed.episode_lengths(), "episode_lengths", v1::DTYPE_INT32,
         {count, n}, agents, out->episode_lengths.data());
  // The uint8 columns: one byte per agent, or per env.
  struct ByteColumn {
    const v1::Array& array;
    absl::string_view field;
    std::vector<uint8_t>& into;
    bool per_agent;
  };
  const ByteColumn byte_columns[] = {
      {packed.terminations(), "terminations", out->terminations, true},
      {packed.truncations(), "truncations", out->truncations, true},
      {packed.stepped(), "stepped", out->active, true},
      {packed.outcomes(), "outcomes", out->outcomes, true},
      {packed.auto_reset(), "auto_reset", out->auto_reset, false},
      {packed.episode_over(), "episode_over", out->episode_over, false},
  };
  for (const ByteColumn& byte_column : byte_columns) {
    column(byte_column.array, byte_column.field, v1::DTYPE_UINT8,
           byte_column.per_agent ? std::vector<int>{count, n}
                                 : std::vector<int>{count},
           byte_column.per_agent ? agents : 1, byte_column.into.data());
  }
  return status;
}

// A packed StepBatch of `envs` (of one server) with their action rows
// (`action_rows[k]` for envs[k]; none: the caller fills the data in).
v1::SessionRequest PackedStepRequest(
    const std::vector<int>& envs, const std::vector<std::string>& names,
    const std::vector<absl::string_view>& action_rows, int n_landers,
    bool continuous) {
  v1::SessionRequest request;
  v1::PackedSteps* packed = request.mutable_step_batch()->mutable_packed();
  v1::Array* actions = packed->mutable_actions();
  actions->set_dtype(continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32);
  for (size_t k = 0; k < envs.size(); ++k) {
    packed->add_names(names[envs[k]]);
    if (!action_rows.empty())
      actions->mutable_data()->append(action_rows[k].data(),
                                      action_rows[k].size());
  }
  actions->add_shape(static_cast<int>(envs.size()));
  actions->add_shape(n_landers);
  if (continuous) actions->add_shape(kRemoteContinuousActionSize);
  return request;
}

// One env to recreate by replay: its config, its record (none: a new env,
// for an operation that starts afresh, with nothing to replay), the
// observations its replay must end on, and its name in messages.
struct ReplayJob {
  const v1::EnvConfig* config = nullptr;
  const EnvRecord* record = nullptr;
  absl::string_view expected_observations;
  std::string label;
};

// The request that replays operation `round` of `record` (round 0: its
// seeded reset) on env `name`.
v1::SessionRequest ReplayRequest(const EnvRecord& record, size_t round,
                                 const std::string& name,
                                 const v1::EnvConfig& config) {
  v1::SessionRequest request;
  if (round == 0) {
    v1::ResetEnvRequest* reset = request.mutable_reset_env();
    reset->set_name(name);
    reset->set_seed(*record.seed);
    return request;
  }
  const auto operation =
      static_cast<internal::RecordOperation>(record.operations[round - 1]);
  if (operation == internal::kReset ||
      (operation == internal::kAutoReset && !config.auto_reset())) {
    request.mutable_reset_env()->set_name(name);
    return request;
  }
  const size_t row_bytes = record.actions.size() / record.operations.size();
  v1::StepEnvRequest* step = request.mutable_step_env();
  step->set_name(name);
  v1::Array* actions = step->mutable_actions();
  actions->set_dtype(config.continuous() ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32);
  actions->add_shape(config.n_landers());
  if (config.continuous()) actions->add_shape(kRemoteContinuousActionSize);
  actions->set_data(record.actions.substr((round - 1) * row_bytes, row_bytes));
  return request;
}

// Replays each job's record on its env `infos[k]` (all envs a round at a
// time, kReplayWindow requests in flight) and checks each ends on the
// observations the client last saw: DATA_LOSS naming the env whose bits
// differ.
absl::Status ReplayRecords(StreamTransport& transport,
                           const std::vector<ReplayJob>& jobs,
                           const std::vector<EnvInfo>& infos) {
  size_t rounds = 0;
  for (const ReplayJob& job : jobs) {
    if (job.record != nullptr) {
      rounds = std::max(rounds, job.record->operations.size() + 1);
    }
  }
  std::vector<std::string> last(jobs.size());
  std::deque<std::pair<absl::StatusOr<uint64_t>, size_t>> in_flight;
  const auto receive_oldest = [&]() {
    auto [sequence, job] = std::move(in_flight.front());
    in_flight.pop_front();
    if (!sequence.ok()) return sequence.status();
    v1::SessionResponse response;
    absl::Status status = transport.Receive(*sequence, &response);
    if (!status.ok()) return status;
    last[job] = response.has_reset_env()
                    ? response.reset_env().data().observations().data()
                    : response.step_env().data().observations().data();
    return absl::OkStatus();
  };
  absl::Status status = absl::OkStatus();
  for (size_t round = 0; round < rounds && status.ok(); ++round) {
    for (size_t k = 0; k < jobs.size() && status.ok(); ++k) {
      const EnvRecord* record = jobs[k].record;
      if (record == nullptr || round > record->operations.size()) continue;
      // A failed Receive or Send ended the stream: sending on would open a
      // new one, which forgets the requests lost with the old one.
      if (in_flight.size() == kReplayWindow) {
        status = receive_oldest();
        if (!status.ok()) break;
      }
      v1::SessionRequest request =
          ReplayRequest(*record, round, infos[k].name, *jobs[k].config);
      in_flight.emplace_back(transport.Send(request), k);
      status = in_flight.back().first.status();
    }
  }
  // Every answer is read, so the stream is ready for what follows.
  while (!in_flight.empty()) {
    absl::Status answer = receive_oldest();
    if (status.ok()) status = answer;
  }
  if (!status.ok()) return status;
  for (size_t k = 0; k < jobs.size(); ++k) {
    const EnvRecord* record = jobs[k].record;
    if (record != nullptr && last[k] != jobs[k].expected_observations) {
      return absl::DataLossError(absl::StrCat(
          jobs[k].label, ": replaying its ", record->operations.size(),
          " operations since seed ", *record->seed, " on ", transport.address(),
          " gave other observations than the last ones seen; the server's "
          "release (physics) differs from the one that ran it, or the record "
          "is wrong"));
    }
  }
  return absl::OkStatus();
}

// Deletes the envs `infos` on `transport`, errors ignored (gone already, or
// the server went: either way it holds them no more).
void DeleteEnvs(StreamTransport& transport, const std::vector<EnvInfo>& infos) {
  std::vector<v1::SessionRequest> requests(infos.size());
  for (size_t k = 0; k < infos.size(); ++k) {
    requests[k].mutable_delete_env()->set_name(infos[k].name);
  }
  std::vector<v1::SessionResponse> responses;
  (void)CallPipelined(transport, requests, &responses);
}

// Creates one env per job on `transport`'s server (on its stream, so it goes
// with the VectorEnv) and replays the job's record; returns the new envs in
// job order. On any error the envs created here are deleted.
absl::StatusOr<std::vector<EnvInfo>> Replay(
    StreamTransport& transport, const std::vector<ReplayJob>& jobs) {
  std::vector<v1::SessionRequest> requests(jobs.size());
  for (size_t k = 0; k < jobs.size(); ++k) {
    *requests[k].mutable_create_env()->mutable_config() = *jobs[k].config;
  }
  std::vector<v1::SessionResponse> responses;
  absl::Status status = CallPipelined(transport, requests, &responses);
  std::vector<EnvInfo> infos;
  for (const v1::SessionResponse& response : responses) {
    if (response.has_env())
      infos.push_back(internal::DecodeEnv(response.env()));
  }
  if (status.ok()) status = ReplayRecords(transport, jobs, infos);
  if (!status.ok()) {
    DeleteEnvs(transport, infos);
    return status;
  }
  return infos;
}

// What a VectorEnv needs of a server to place envs on it.
constexpr absl::string_view kVectorNeeds[] = {"packed_step_batch",
                                              "auto_reset"};

// A server's load as placement reads it.
ServerCapacity CapacityOf(const v1::ServerInfo& proto) {
  return internal::CapacityOf(internal::DecodeServerInfo(proto));
}

// A resolution of a VectorEnv's address list (made off its thread, taken
// in at one of its calls): each entry's addresses or why none, every
// server they name, and the servers to take in (new ones, or ones found
// down), each probed: it answered GetServerInfo with a protocol this client
// speaks and its health check SERVING within kProbeDeadline, on a channel
// of its own.
struct Discovery {
  std::vector<std::vector<std::string>> resolved;
  std::vector<absl::Status> failures;
  std::set<std::string> current;
  struct Joiner {
    std::string address;
    ClientOptions options;
    std::shared_ptr<grpc::Channel> channel;
  };
  std::vector<Joiner> joiners;
};

// Resolves `entries` and probes the servers of them not in `known`, and
// those in `probe` (known, found down).
Discovery Discover(const std::vector<AddressEntry>& entries,
                   const ClientOptions& options,
                   const std::set<std::string>& known,
                   const std::set<std::string>& probe) {
  Discovery found;
  for (size_t i = 0; i < entries.size(); ++i) {
    absl::StatusOr<std::vector<std::string>> addresses =
        internal::ResolveEntry(entries[i]);
    found.failures.push_back(addresses.status());
    found.resolved.push_back(addresses.ok() ? *addresses
                                            : std::vector<std::string>());
    if (!addresses.ok()) continue;
    const ClientOptions endpoint =
        internal::EndpointOptions(entries[i], options);
    for (const std::string& address : *addresses) {
      if (!found.current.insert(address).second) continue;
      if (known.count(address) != 0 && probe.count(address) == 0) continue;
      ClientOptions probing = endpoint;
      probing.call_timeout = absl::ToChronoMilliseconds(kProbeDeadline);
      absl::StatusOr<std::shared_ptr<internal::Transport>> transport =
          internal::MakeUnaryTransport(address, probing);
      if (!transport.ok()) continue;
      absl::StatusOr<v1::ServerInfo> info = (*transport)->ServerInfo();
      if (!info.ok() ||
          !Client::CheckCompatible(internal::DecodeServerInfo(*info), address,
                                   kVectorNeeds)
               .ok() ||
          !(*transport)->CheckHealth("").ok()) {
        continue;
      }
      absl::StatusOr<std::shared_ptr<grpc::Channel>> channel =
          internal::OpenChannel(address, endpoint);
      if (!channel.ok()) continue;
      found.joiners.push_back({address, endpoint, *std::move(channel)});
    }
  }
  return found;
}

}  // namespace

struct VectorEnv::State {
  explicit State(Client session_client) : session(std::move(session_client)) {}
  // Unholds the leases; the envs created on the session's streams go with
  // the streams (when `session` goes, after this).
  ~State() {
    for (size_t env = 0; env < names.size(); ++env) {
      TransportOf(placement[env]).Unhold(names[env]);
    }
  }

  Client session;
  // Env i is on server placement[i] (as Create placed it by load, until
  // failover or rebalancing moves it); shards: one per server holding envs.
  std::vector<int> placement;
  std::vector<Shard> shards;
  std::vector<std::string> names;
  // Each env's options as the server filled them in: what failover and
  // RestoreEnv recreate, and what EnvSnapshot writes.
  std::vector<v1::EnvConfig> configs;
  int n_landers = 0;
  bool continuous = false;

  // Failover (see vector_env.h): whether it is on, whether the envs are the
  // VectorEnv's own (Create; Attach's belong to others), the events so far,
  // the servers found unreachable, each env's record and the observations
  // the client last saw of it (float32 [num_envs, n_landers, 12]).
  bool failover = false;
  bool created = false;
  int failovers = 0;
  std::vector<bool> down;
  std::vector<EnvRecord> records;
  std::vector<float> last_observations;

  // The latest results (num_envs rows after Reset and Step, batch_size rows
  // after Recv, whose envs are in `results.env_ids`).
  Columns results;

  // The async API: batch_size, which envs have a step (or AsyncReset) whose
  // results Recv has not returned, the requests in flight in send order, and
  // the results received and not yet returned.
  int batch_size = 0;
  std::vector<bool> in_flight;
  int in_flight_count = 0;
  std::deque<PendingRequest> pending;
  std::deque<ReadyChunk> ready;
  size_t ready_rows = 0;

  // StepAsync's step until StepWait has its answers: its actions (env-major),
  // the sequence of each shard's request (or the failure that kept it from
  // going out) and each answer's status once received.
  bool step_in_flight = false;
  std::string step_actions;
  std::vector<absl::StatusOr<uint64_t>> step_sequences;
  std::vector<std::optional<absl::Status>> step_answers;

  // Discovery and rebalancing (vector_env.h): the address list parsed, the
  // servers gone from their names (they take no new env; theirs stay while
  // they answer), each entry's latest resolution or why it has none, when
  // to resolve next (none: never), a resolution under way off this thread,
  // whether a server joined since the envs were last evened out, and the
  // rebalancing events so far.
  std::vector<AddressEntry> entries;
  std::vector<bool> departed;
  std::vector<std::vector<std::string>> resolved;
  std::vector<absl::Status> resolve_failures;
  std::optional<absl::Time> next_discovery;
  std::future<Discovery> discovery;
  bool rebalance_pending = false;
  int rebalances = 0;

  // Where failover event lines go (SetEventLog); none: stderr.
  EventLog event_log;
  // Create: env 0's mll.v1.Env as its server created it, serialized.
  std::string spec;

  int num_envs() const { return static_cast<int>(names.size()); }
  int server_count() const { return session.server_count(); }
  size_t row_bytes() const {
    return static_cast<size_t>(n_landers) * sizeof(float) *
           (continuous ? kRemoteContinuousActionSize : 1);
  }
  StreamTransport& TransportOf(int server) const {
    return static_cast<StreamTransport&>(*session.transports_[server]);
  }
  std::string Label(int env) const {
    return absl::StrCat("env ", env, " (", names[env], ")");
  }
  absl::string_view LastObservations(int env) const {
    const size_t size = static_cast<size_t>(n_landers) * kRemoteObservationSize;
    return absl::string_view(
        reinterpret_cast<const char*>(last_observations.data() + env * size),
        size * sizeof(float));
  }

  // The shards of `envs` (grouped by server, in `envs` order within each),
  // their requests carrying `action_rows` (one per env, in `envs` order; none:
  // filled in by each step).
  std::vector<Shard> ShardsOf(
      const std::vector<int>& envs,
      const std::vector<absl::string_view>& action_rows) const {
    std::map<int, std::vector<size_t>> by_server;
    for (size_t k = 0; k < envs.size(); ++k) {
      by_server[placement[envs[k]]].push_back(k);
    }
    std::vector<Shard> out;
    for (const auto& [server, positions] : by_server) {
      Shard& shard = out.emplace_back();
      shard.server = server;
      shard.transport = &TransportOf(server);
      std::vector<absl::string_view> rows;
      for (size_t k : positions) {
        shard.rows.push_back(envs[k]);
        if (!action_rows.empty()) rows.push_back(action_rows[k]);
      }
      shard.request =
          PackedStepRequest(shard.rows, names, rows, n_landers, continuous);
    }
    return out;
  }
  std::vector<int> AllEnvs() const {
    std::vector<int> envs(names.size());
    for (int env = 0; env < num_envs(); ++env) envs[env] = env;
    return envs;
  }

  // Whether env `env`'s `error` is one failover handles: its server is lost
  // (ServerLost), or it lost the env (NOT_FOUND naming it).
  bool Lost(const absl::Status& error, int env) const {
    return failover && (ServerLost(error) ||
                        (absl::IsNotFound(error) &&
                         absl::StrContains(error.message(), names[env])));
  }

  // The packed results of `response` to a packed StepBatch of the envs
  // `envs` (in request order) into `out` at rows `rows`; the envs' own
  // errors (prefixed "env {i} ({name}): ") into `lost` when failover handles
  // them (and `lost` is given), else into `failed`. A failure of the whole
  // answer is returned.
  absl::Status CollectPacked(const v1::SessionResponse& response,
                             const std::vector<int>& envs,
                             const std::vector<int>& rows,
                             const std::string& address, Columns* out,
                             EnvErrors* lost, EnvErrors* failed) const {
    if (!response.step_batch().has_packed()) {
      return absl::UnimplementedError(absl::StrCat(
          address,
          " answered a packed StepBatch without packed results; its "
          "mll_server predates StepBatchRequest.packed: upgrade it"));
    }
    const v1::PackedStepData& packed = response.step_batch().packed();
    for (const v1::IndexedItemError& item : packed.errors()) {
      if (item.index() < 0 || item.index() >= static_cast<int>(envs.size())) {
        return absl::InternalError(
            absl::StrCat(address, " reported an error for row ", item.index(),
                         " of a packed StepBatch of ", envs.size(), " envs"));
      }
      const int env = envs[item.index()];
      const absl::Status error = internal::FromItemError(item.error());
      absl::Status status(error.code(),
                          absl::StrCat(Label(env), ": ", error.message()));
      EnvErrors* into = lost != nullptr && Lost(status, env) ? lost : failed;
      into->emplace(env, std::move(status));
    }
    return DecodePacked(packed, rows, n_landers, out);
  }

  // Sends every shard's request (all in flight at once): the sequence of
  // each, or the failure that kept it from going out.
  static std::vector<absl::StatusOr<uint64_t>> SendBatches(
      std::vector<Shard>& batches) {
    std::vector<absl::StatusOr<uint64_t>> sequences;
    for (Shard& shard : batches) {
      sequences.push_back(shard.transport->Send(shard.request));
    }
    return sequences;
  }

  // Waits until `deadline` for the answer to each shard's request that has
  // none yet in `answers` (its status there, the answer in the shard's
  // response); false when the deadline passed first (the answers still due
  // stay due).
  static bool AwaitBatches(
      std::vector<Shard>& batches,
      const std::vector<absl::StatusOr<uint64_t>>& sequences,
      std::vector<std::optional<absl::Status>>* answers, Deadline deadline) {
    answers->resize(batches.size());
    for (size_t s = 0; s < batches.size(); ++s) {
      std::optional<absl::Status>& answer = (*answers)[s];
      if (answer.has_value()) continue;
      if (!sequences[s].ok()) {
        answer = sequences[s].status();
        continue;
      }
      answer = batches[s].transport->Receive(
          *sequences[s], &batches[s].response, Remaining(deadline));
      if (!answer.has_value()) return false;
    }
    return true;
  }

  // Decodes each shard's answer (`answers`, as AwaitBatches left them) into
  // `out` at the shard's rows; the envs whose results came go to `stepped`,
  // those failover handles to `lost`. Returns the first other failure in env
  // order (a server's failure counts as its first env's).
  absl::Status CollectBatches(
      std::vector<Shard>& batches,
      const std::vector<std::optional<absl::Status>>& answers, Columns* out,
      EnvErrors* lost, std::vector<int>* stepped) const {
    EnvErrors failed;
    for (size_t s = 0; s < batches.size(); ++s) {
      Shard& shard = batches[s];
      absl::Status status = *answers[s];
      if (status.ok()) {
        status = CollectPacked(shard.response, shard.rows, shard.rows,
                               shard.transport->address(), out, lost, &failed);
      }
      if (status.ok()) {
        for (int row : shard.rows) {
          if (lost->count(row) == 0 && failed.count(row) == 0) {
            stepped->push_back(row);
          }
        }
      } else if (Lost(status, shard.rows[0])) {
        for (int row : shard.rows) lost->emplace(row, status);
      } else {
        failed.emplace(shard.rows[0], status);
      }
    }
    std::sort(stepped->begin(), stepped->end());
    return failed.empty() ? absl::OkStatus() : failed.begin()->second;
  }

  // SendBatches, AwaitBatches with no deadline, then CollectBatches.
  absl::Status RunStepBatches(std::vector<Shard>& batches, Columns* out,
                              EnvErrors* lost, std::vector<int>* stepped) {
    const std::vector<absl::StatusOr<uint64_t>> sequences =
        SendBatches(batches);
    std::vector<std::optional<absl::Status>> answers;
    AwaitBatches(batches, sequences, &answers, kNoDeadline);
    return CollectBatches(batches, answers, out, lost, stepped);
  }

  // Resets the envs `envs` (seeds[env] each; none: no reseed), their
  // results into `out`; as RunStepBatches for the envs reset and lost.
  absl::Status ResetEnvs(const std::vector<int>& envs,
                         absl::Span<const uint64_t> seeds, Columns* out,
                         EnvErrors* lost) {
    std::vector<absl::StatusOr<uint64_t>> sequences;
    for (int env : envs) {
      v1::SessionRequest request;
      v1::ResetEnvRequest* reset = request.mutable_reset_env();
      reset->set_name(names[env]);
      if (!seeds.empty()) reset->set_seed(seeds[env]);
      sequences.push_back(TransportOf(placement[env]).Send(request));
    }
    absl::Status first = absl::OkStatus();
    const int n = n_landers;
    const std::string zero_actions(row_bytes(), '\0');
    for (size_t k = 0; k < envs.size(); ++k) {
      const int env = envs[k];
      v1::SessionResponse response;
      absl::Status status = sequences[k].status();
      if (status.ok()) {
        status = TransportOf(placement[env]).Receive(*sequences[k], &response);
      }
      absl::StatusOr<StepData> data =
          status.ok() ? internal::DecodeStepData(response.reset_env().data())
                      : absl::StatusOr<StepData>(status);
      if (!data.ok()) {
        const absl::Status error(
            data.status().code(),
            absl::StrCat(Label(env), ": ", data.status().message()));
        if (Lost(error, env)) {
          lost->emplace(env, error);
        } else if (first.ok()) {
          first = error;
        }
        continue;
      }
      const size_t row = static_cast<size_t>(env) * n;
      std::memcpy(&out->observations[row * kRemoteObservationSize],
                  data->observations.data(),
                  data->observations.size() * sizeof(float));
      for (int a = 0; a < n; ++a) {
        out->rewards[row + a] = data->rewards[a];
        out->terminations[row + a] = data->terminations[a];
        out->truncations[row + a] = data->truncations[a];
        out->active[row + a] = data->stepped[a];
        out->outcomes[row + a] = static_cast<uint8_t>(data->outcomes[a]);
        out->episode_returns[row + a] = data->episode_returns[a];
        out->episode_lengths[row + a] = data->episode_lengths[a];
      }
      out->auto_reset[env] = data->auto_reset;
      out->episode_over[env] = data->episode_over;
      if (response.reset_env().has_seed()) {
        records[env].Restart(response.reset_env().seed());
      } else {
        records[env].Append(internal::kReset, zero_actions);
      }
      KeepObservations(env, *out, env);
    }
    return first;
  }

  // Appends the step of `envs` (their rows of `action_bytes`, env-indexed)
  // to their records, with its results in `out` (env-indexed too).
  void RecordSteps(const std::vector<int>& envs, absl::string_view action_bytes,
                   const Columns& out) {
    for (int env : envs) {
      RecordStep(env, action_bytes.substr(env * row_bytes(), row_bytes()), out,
                 env);
    }
  }
  // Appends one step of env `env` with `action_row` to its record, its
  // results in row `row` of `out`.
  void RecordStep(int env, absl::string_view action_row, const Columns& out,
                  size_t row) {
    records[env].Append(
        out.auto_reset[row] ? internal::kAutoReset : internal::kStep,
        action_row);
    KeepObservations(env, out, row);
  }
  void KeepObservations(int env, const Columns& out, size_t row) {
    const size_t size = static_cast<size_t>(n_landers) * kRemoteObservationSize;
    std::copy_n(out.observations.begin() + row * size, size,
                last_observations.begin() + env * size);
  }

  // OK when env `env`'s record recreates it; else FAILED_PRECONDITION
  // naming it and why.
  absl::Status RecordProblem(int env) const {
    const EnvRecord& record = records[env];
    if (record.seed.has_value() && record.gap.empty()) return absl::OkStatus();
    return absl::FailedPreconditionError(absl::StrCat(
        Label(env), " cannot be recreated: ",
        record.seed.has_value() ? record.gap
                                : "it was never reset (no known seed)",
        "; Reset with a seed starts a new record"));
  }

  // Runs `operation` on the envs `envs`, then again on those it lost after
  // failing them over (`fresh`: the operation starts them afresh, so nothing
  // is replayed), at most server_count() + 2 times.
  absl::Status WithFailover(
      std::vector<int> envs, bool fresh,
      const std::function<absl::Status(const std::vector<int>&, EnvErrors*)>&
          operation) {
    const int tries = server_count() + 2;
    for (int attempt = 0; attempt < tries; ++attempt) {
      EnvErrors lost;
      absl::Status status = operation(envs, &lost);
      if (!status.ok() || lost.empty()) return status;
      status = FailOver(lost, fresh);
      if (!status.ok()) return status;
      envs.clear();
      for (const auto& [env, error] : lost) envs.push_back(env);
    }
    return absl::UnavailableError(
        absl::StrCat("failover gave up after ", tries, " tries"));
  }

  // Servers in their names and not found unreachable, and those found
  // unreachable (but not in `skip`) that answer a probe again (Rejoin): so a
  // server replaced at its address (a StatefulSet pod in a rolling update)
  // takes envs again at the next failover, not only once every other server
  // is lost. None of `skip` is returned.
  std::vector<int> UsableServers(const std::map<int, absl::Status>& skip) {
    std::vector<int> usable;
    for (int server = 0; server < server_count(); ++server) {
      if (departed[server] || skip.count(server) != 0) continue;
      if (down[server]) Rejoin(server);
      if (!down[server]) usable.push_back(server);
    }
    return usable;
  }

  // Probes server `server`, found down, on a new channel (its name resolved
  // again; subchannels of its own, so none of the old channel's reconnect
  // backoff): when it answers GetServerInfo within kProbeDeadline (a
  // draining server refuses it with UNAVAILABLE; one from before the RPC
  // answers UNIMPLEMENTED), a session stream on the new channel replaces the
  // old one and the server is no longer down. The old stream goes, and with
  // it the envs bound to it there (an env still placed on the server meets
  // NOT_FOUND and is recreated there).
  void Rejoin(int server) {
    const StreamTransport& old = TransportOf(server);
    const ClientOptions& options = old.options();
    absl::StatusOr<std::shared_ptr<grpc::Channel>> channel =
        internal::OpenChannel(old.address(), options);
    if (!channel.ok()) return;
    grpc::ClientContext context;
    internal::AddToken(&context, options.token);
    context.set_deadline(absl::ToChronoTime(absl::Now() + kProbeDeadline));
    v1::ServerInfo info;
    const grpc::Status answer =
        v1::MultiLunarLander::NewStub(*channel)->GetServerInfo(
            &context, v1::GetServerInfoRequest(), &info);
    if (!answer.ok() &&
        answer.error_code() != grpc::StatusCode::UNIMPLEMENTED) {
      return;
    }
    (void)Adopt(server, old.address(), *std::move(channel), options);
  }

  // Recreates the `lost` envs on reachable servers (round robin; an env
  // whose server answers NOT_FOUND stays there) and replays their records
  // to the bits the client last saw: one failover event, logged. A target
  // that turns out unreachable during the replay (it began to drain, or
  // died) is passed over for the next one; UNAVAILABLE naming the servers
  // tried when none is left.
  absl::Status FailOver(const EnvErrors& lost, bool fresh) {
    const absl::Time began = absl::Now();
    std::map<int, int> targets;  // Env -> the server it is replayed on.
    std::vector<int> homeless;   // Envs that need a server still.
    // Servers that have just missed a deadline: not probed in this event
    // (a probe would wait out its own deadline) while others can take the
    // envs.
    std::map<int, absl::Status> stalled;
    for (const auto& [env, error] : lost) {
      if (ServerLost(error)) down[placement[env]] = true;
      if (absl::IsDeadlineExceeded(error))
        stalled.emplace(placement[env], error);
      if (!fresh) {
        if (absl::Status problem = RecordProblem(env); !problem.ok()) {
          return problem;
        }
      }
    }
    // Servers that joined take envs now; those gone from their names none.
    DiscoverNow();
    for (const auto& [env, error] : lost) {
      if (down[placement[env]]) {
        homeless.push_back(env);
      } else {
        targets[env] = placement[env];
      }
    }
    // Server -> why the replay there failed, as "passed over" clauses.
    std::map<int, absl::Status> refused;
    // Envs replaced before a failure stay where they are now: the shards
    // follow them.
    const auto fail = [&](absl::Status error) {
      shards = ShardsOf(AllEnvs(), {});
      return error;
    };
    size_t replayed = 0;
    std::set<std::string> where;
    // Each round either places every env or refuses one more server.
    while (!targets.empty() || !homeless.empty()) {
      if (!homeless.empty()) {
        // Those passed over are down, and not probed again in this event.
        std::map<int, absl::Status> skip = refused;
        skip.insert(stalled.begin(), stalled.end());
        std::vector<int> usable = UsableServers(skip);
        if (usable.empty() && !stalled.empty()) {
          usable = UsableServers(refused);
        }
        if (usable.empty()) return fail(NoServerLeft(lost, refused));
        const std::vector<int> places = Place(usable, homeless.size());
        for (size_t k = 0; k < homeless.size(); ++k) {
          targets[homeless[k]] = places[k];
        }
        homeless.clear();
      }
      std::map<int, std::vector<int>> moves;  // Target server -> envs.
      for (const auto& [env, target] : targets) moves[target].push_back(env);
      targets.clear();
      for (const auto& [target, envs] : moves) {
        std::vector<ReplayJob> jobs;
        for (int env : envs) {
          jobs.push_back({&configs[env], fresh ? nullptr : &records[env],
                          LastObservations(env), Label(env)});
        }
        absl::StatusOr<std::vector<EnvInfo>> created =
            Replay(TransportOf(target), jobs);
        if (!created.ok()) {
          // A server without room (its max_envs, or the token's quota)
          // is passed over as an unreachable one is, and stays up.
          const bool full = absl::IsResourceExhausted(created.status());
          if (!ServerLost(created.status()) && !full) {
            return fail(created.status());
          }
          refused.emplace(target, created.status());
          if (!full) {
            down[target] = true;
            SettleRequestsOf(target, created.status());
          }
          homeless.insert(homeless.end(), envs.begin(), envs.end());
          continue;
        }
        for (size_t k = 0; k < envs.size(); ++k) {
          Replace(envs[k], target, (*created)[k]);
          if (!fresh) replayed += records[envs[k]].operations.size();
        }
        where.insert(session.address(target));
      }
    }
    shards = ShardsOf(AllEnvs(), {});
    ++failovers;
    const absl::Status& first = lost.begin()->second;
    char seconds[32];
    std::snprintf(seconds, sizeof(seconds), "%.3f",
                  absl::ToDoubleSeconds(absl::Now() - began));
    LogEvent(absl::StrCat(
        "VectorEnv failover: ", lost.size(), " env(s) lost (",
        absl::StatusCodeToString(first.code()), ": ", first.message(),
        "); recreated on ", absl::StrJoin(where, ", "), " and replayed (",
        replayed, " steps) in ", seconds, " s", Refusals(refused)));
    return absl::OkStatus();
  }

  // ----------------------------------------------- discovery and rebalancing

  bool HasNames() const {
    for (const AddressEntry& entry : entries) {
      if (entry.is_name) return true;
    }
    return false;
  }

  // The addresses of the servers known, and of those found down.
  std::set<std::string> Addresses(bool down_only) const {
    std::set<std::string> out;
    for (int server = 0; server < server_count(); ++server) {
      if (!down_only || down[server]) out.insert(session.address(server));
    }
    return out;
  }

  // At the start of a call with nothing in flight for the envs it moves:
  // starts a resolution when one is due, takes in one that is done, and
  // evens the envs out when a server joined (`seeded_reset`: the call is a
  // seeded Reset, which starts the moved envs afresh).
  void Maintain(bool seeded_reset) {
    if (next_discovery.has_value() && !discovery.valid() &&
        absl::Now() >= *next_discovery) {
      discovery =
          std::async(std::launch::async, Discover, entries, session.options_,
                     Addresses(false), Addresses(true));
    }
    if (discovery.valid() && discovery.wait_for(std::chrono::seconds(0)) ==
                                 std::future_status::ready) {
      TakeIn(discovery.get());
      next_discovery =
          absl::Now() + absl::FromChrono(session.options_.rediscover_interval);
    }
    if (rebalance_pending) Rebalance(seeded_reset);
  }

  // Resolves the names now (at a failover): servers that joined take envs
  // in this failover, those gone from their names none.
  void DiscoverNow() {
    if (!HasNames()) return;
    if (discovery.valid()) {
      // Its probes of servers now found down predate the failure: dropped.
      Discovery found = discovery.get();
      const std::set<std::string> known = Addresses(false);
      found.joiners.erase(
          std::remove_if(found.joiners.begin(), found.joiners.end(),
                         [&](const Discovery::Joiner& joiner) {
                           return known.count(joiner.address) != 0;
                         }),
          found.joiners.end());
      TakeIn(std::move(found));
    }
    // Servers found down are probed by UsableServers, which knows which
    // ones just stalled.
    TakeIn(Discover(entries, session.options_, Addresses(false), {}));
  }

  // Takes in a resolution: servers gone from their names are marked so,
  // servers that came back to them are not, and the servers that joined
  // (new ones, or ones found down that answer again) get streams.
  void TakeIn(Discovery found) {
    resolved = std::move(found.resolved);
    resolve_failures = std::move(found.failures);
    for (int server = 0; server < server_count(); ++server) {
      const bool gone = found.current.count(session.address(server)) == 0;
      if (departed[server] && !gone && !down[server]) rebalance_pending = true;
      departed[server] = gone;
    }
    const std::set<std::string> known = Addresses(false);
    for (Discovery::Joiner& joiner : found.joiners) {
      int server = -1;
      if (known.count(joiner.address) != 0) {
        for (int s = 0; s < server_count(); ++s) {
          if (session.address(s) == joiner.address) server = s;
        }
        // Answered the probe but found down since (a failover meanwhile)
        // or up all along: nothing to take in.
        if (!down[server]) continue;
      }
      if (Adopt(server, joiner.address, joiner.channel, joiner.options)) {
        rebalance_pending = true;
      }
    }
  }

  // A session stream on `channel` for server `server` (-1: a new server at
  // `address`), which is then not down: false when shared memory was asked
  // for by name and the stream cannot have it. A known server's requests
  // still in flight on its old stream are read off it first; the envs bound
  // to that stream go with it (an env still placed there meets NOT_FOUND
  // and is recreated).
  bool Adopt(int server, const std::string& address,
             std::shared_ptr<grpc::Channel> channel,
             const ClientOptions& options) {
    auto fresh =
        std::make_shared<StreamTransport>(address, std::move(channel), options);
    if (options.session_transport == SessionTransport::kSharedMemory &&
        !fresh->Open().ok()) {
      return false;
    }
    if (server < 0) {
      session.transports_.push_back(std::move(fresh));
      down.push_back(false);
      departed.push_back(false);
      return true;
    }
    SettleRequestsOf(server, absl::UnavailableError(absl::StrCat(
                                 address, ": stream replaced by a new one")));
    session.transports_[server] = std::move(fresh);
    down[server] = false;
    return true;
  }

  // Server `server`'s load as it reports it now (as last reported when it
  // cannot be asked; nothing known: zero).
  ServerCapacity LoadOf(int server) {
    absl::StatusOr<v1::ServerInfo> info =
        TransportOf(server).ServerInfo(/*fresh=*/true);
    if (!info.ok()) info = TransportOf(server).ServerInfo();
    return info.ok() ? CapacityOf(*info) : ServerCapacity();
  }

  // A server of `usable` for each of `count` new envs: the least loaded
  // first (PlanPlacement); past the servers' room, round robin (their
  // creates then answer RESOURCE_EXHAUSTED).
  std::vector<int> Place(const std::vector<int>& usable, size_t count) {
    std::vector<ServerCapacity> capacity(server_count());
    for (ServerCapacity& server : capacity) server.usable = false;
    for (int server : usable) capacity[server] = LoadOf(server);
    const std::vector<int> plan =
        internal::PlanPlacement(capacity, static_cast<int>(count));
    std::vector<int> targets;
    for (int server = 0; server < server_count(); ++server) {
      targets.insert(targets.end(), plan[server], server);
    }
    for (size_t k = 0; targets.size() < count; ++k) {
      targets.push_back(usable[k % usable.size()]);
    }
    return targets;
  }

  // Moves envs onto the servers that joined until the VectorEnv's own envs
  // are even within one over the servers up and in their names (PlanEven):
  // from each server holding more than its share, its highest-numbered envs
  // with nothing in flight. `fresh`: a seeded Reset follows, so the moved
  // envs are created afresh; else each is recreated and its record replayed
  // (checked to the bits), and an env whose record cannot (never reset, or
  // too long) waits for a seeded Reset. Each target's move is one event.
  void Rebalance(bool fresh) {
    rebalance_pending = false;
    if (!created) return;
    const int servers = server_count();
    std::vector<bool> eligible(servers);
    std::vector<int> own(servers, 0);
    for (int server = 0; server < servers; ++server) {
      eligible[server] = !down[server] && !departed[server];
    }
    for (int server : placement) ++own[server];
    const std::vector<int> target = internal::PlanEven(own, eligible);
    std::vector<int> movers;
    for (int server = 0; server < servers; ++server) {
      int surplus = own[server] - target[server];
      for (int env = num_envs() - 1; env >= 0 && surplus > 0; --env) {
        if (placement[env] != server) continue;
        if (in_flight[env] || (!fresh && !RecordProblem(env).ok())) {
          rebalance_pending = true;  // Tried again at the next call.
          continue;
        }
        movers.push_back(env);
        --surplus;
      }
    }
    size_t next = 0;
    for (int server = 0; server < servers && next < movers.size(); ++server) {
      std::vector<int> envs;
      for (int k = own[server]; k < target[server] && next < movers.size();
           ++k) {
        envs.push_back(movers[next++]);
      }
      if (!envs.empty()) MoveEnvs(envs, server, fresh);
    }
    shards = ShardsOf(AllEnvs(), {});
  }

  // Recreates `envs` on server `target` (replaying their records unless
  // `fresh`), then deletes them where they were: one rebalancing event,
  // logged. On failure they stay where they are (and a target found
  // unreachable is down).
  void MoveEnvs(const std::vector<int>& envs, int target, bool fresh) {
    const absl::Time began = absl::Now();
    std::vector<ReplayJob> jobs;
    for (int env : envs) {
      jobs.push_back({&configs[env], fresh ? nullptr : &records[env],
                      LastObservations(env), Label(env)});
    }
    absl::StatusOr<std::vector<EnvInfo>> created_envs =
        Replay(TransportOf(target), jobs);
    if (!created_envs.ok()) {
      if (ServerLost(created_envs.status())) {
        down[target] = true;
        SettleRequestsOf(target, created_envs.status());
      }
      LogEvent(absl::StrCat(
          "VectorEnv rebalance: moving ", envs.size(), " env(s) onto ",
          session.address(target), " failed (",
          absl::StatusCodeToString(created_envs.status().code()), ": ",
          created_envs.status().message(), "); they stay where they are"));
      return;
    }
    std::map<int, std::vector<EnvInfo>> old;  // Server -> envs moved off it.
    size_t replayed = 0;
    for (size_t k = 0; k < envs.size(); ++k) {
      EnvInfo& moved = old[placement[envs[k]]].emplace_back();
      moved.name = names[envs[k]];
      Replace(envs[k], target, (*created_envs)[k]);
      if (!fresh) replayed += records[envs[k]].operations.size();
    }
    std::vector<std::string> sources;
    for (const auto& [server, infos] : old) {
      DeleteEnvs(TransportOf(server), infos);
      sources.push_back(
          absl::StrCat(session.address(server), " (", infos.size(), ")"));
    }
    ++rebalances;
    char seconds[32];
    std::snprintf(seconds, sizeof(seconds), "%.3f",
                  absl::ToDoubleSeconds(absl::Now() - began));
    LogEvent(absl::StrCat(
        "VectorEnv rebalance: ", envs.size(), " env(s) moved onto ",
        session.address(target), " from ", absl::StrJoin(sources, ", "),
        fresh ? ", created afresh for a seeded reset"
              : absl::StrCat(", replayed (", replayed, " steps)"),
        " in ", seconds, " s"));
  }

  // "; NAME:PORT resolves to ..." for each name in the address list.
  std::string Resolutions() const {
    std::string out;
    for (size_t i = 0; i < entries.size() && i < resolved.size(); ++i) {
      const std::string text = internal::DescribeResolution(
          entries[i], resolved[i], resolve_failures[i]);
      if (!text.empty()) absl::StrAppend(&out, "; ", text);
    }
    return out;
  }

  // One event line to the event log (SetEventLog), else to stderr.
  void LogEvent(const std::string& line) const {
    if (event_log) {
      event_log(line);
    } else {
      std::fprintf(stderr, "mll_client: %s\n", line.c_str());
    }
  }

  // "; passed over {address} ({code}: {message})" for each server whose
  // replay failed, or "".
  std::string Refusals(const std::map<int, absl::Status>& refused) const {
    std::string out;
    for (const auto& [server, error] : refused) {
      absl::StrAppend(
          &out, "; passed over mll_server at ", session.address(server), " (",
          absl::StatusCodeToString(error.code()), ": ", error.message(), ")");
    }
    return out;
  }

  // UNAVAILABLE: no server is left to fail the `lost` envs over to.
  absl::Status NoServerLeft(const EnvErrors& lost,
                            const std::map<int, absl::Status>& refused) const {
    std::vector<std::string> addresses;
    for (int server = 0; server < server_count(); ++server) {
      addresses.push_back(session.address(server));
    }
    return absl::UnavailableError(absl::StrCat(
        "failover of ", lost.size(), " envs found no reachable server of ",
        absl::StrJoin(addresses, ", "), ": ", lost.begin()->second.message(),
        Refusals(refused), Resolutions()));
  }

  // Env `env` is now `info`, on server `server`: the lease moves with it.
  void Replace(int env, int server, const EnvInfo& info) {
    TransportOf(placement[env]).Unhold(names[env]);
    names[env] = info.name;
    placement[env] = server;
    TransportOf(server).Hold(info.name, info.idle_timeout_s);
  }

  // ------------------------------------------- EnvPool's async API in flight

  // Sends one step of `envs` with `action_rows` (one per env, in `envs`
  // order): one packed StepBatch per server, in flight (with its envs) until
  // Recv receives it. A request that cannot go out because its server is
  // lost stays in flight too: the Recv that meets it fails its envs over.
  // Another failure is returned at once; the servers before it were sent.
  absl::Status SendSteps(const std::vector<int>& envs,
                         const std::vector<absl::string_view>& action_rows) {
    for (Shard& shard : ShardsOf(envs, action_rows)) {
      absl::StatusOr<uint64_t> sequence = shard.transport->Send(shard.request);
      if (!sequence.ok()) {
        if (!failover || !ServerLost(sequence.status())) {
          return sequence.status();
        }
        SettleRequestsOf(shard.server, sequence.status());
      }
      for (int env : shard.rows) in_flight[env] = true;
      in_flight_count += static_cast<int>(shard.rows.size());
      PendingRequest& request = pending.emplace_back();
      request.server = shard.server;
      request.sequence = std::move(sequence);
      request.envs = std::move(shard.rows);
      request.actions = std::move(*shard.request.mutable_step_batch()
                                       ->mutable_packed()
                                       ->mutable_actions()
                                       ->mutable_data());
    }
    return absl::OkStatus();
  }

  // Waits until `deadline` for the answer to the oldest request in flight
  // (kept in it for ReceiveOne); false when the deadline passed first.
  bool AwaitOldest(Deadline deadline) {
    PendingRequest& request = pending.front();
    if (request.answer.has_value() || !request.sequence.ok()) return true;
    request.answer =
        TransportOf(request.server)
            .Receive(*request.sequence, &request.response, Remaining(deadline));
    return request.answer.has_value();
  }

  // The envs `envs` have no step in flight any more (their results are lost,
  // or about to be sent again).
  void Release(const std::vector<int>& envs) {
    for (int env : envs) {
      if (!in_flight[env]) continue;
      in_flight[env] = false;
      --in_flight_count;
    }
  }

  // Settles the requests in flight on the lost server `server`: each is
  // read off its stream (its answer, or the loss), because the stream counts
  // the requests it lost only until it is opened again, and takes `loss` as
  // its status, so that the Recv that meets it fails its envs over.
  void SettleRequestsOf(int server, const absl::Status& loss) {
    for (PendingRequest& request : pending) {
      if (request.server != server || !request.sequence.ok()) continue;
      if (!request.answer.has_value()) {
        v1::SessionResponse unused;
        (void)TransportOf(server).Receive(*request.sequence, &unused);
      }
      request.sequence = loss;
      request.answer.reset();
    }
  }

  // Moves the (settled) requests in flight on the lost server `server` from
  // `pending` to `requests`, oldest first.
  void TakeRequestsOf(int server, std::vector<PendingRequest>* requests) {
    std::deque<PendingRequest> others;
    for (PendingRequest& request : pending) {
      if (request.server == server) {
        requests->push_back(std::move(request));
      } else {
        others.push_back(std::move(request));
      }
    }
    pending = std::move(others);
  }

  // Fails the `lost` envs over (replayed to the last results received),
  // then sends `requests` (their steps in flight where they were lost,
  // oldest first) again on the envs' new servers, so that Recv returns the
  // results it would have. If that fails, those envs are no longer in
  // flight.
  absl::Status FailOverAndResend(const EnvErrors& lost,
                                 std::vector<PendingRequest>& requests) {
    absl::Status status = FailOver(lost, /*fresh=*/false);
    for (PendingRequest& request : requests) {
      Release(request.envs);
      if (!status.ok()) continue;
      std::vector<absl::string_view> action_rows;
      for (size_t k = 0; k < request.envs.size(); ++k) {
        action_rows.push_back(absl::string_view(request.actions)
                                  .substr(k * row_bytes(), row_bytes()));
      }
      status = SendSteps(request.envs, action_rows);
    }
    return status;
  }
};

VectorEnv::VectorEnv(std::unique_ptr<State> state) : state_(std::move(state)) {}
VectorEnv::VectorEnv(VectorEnv&&) noexcept = default;
VectorEnv& VectorEnv::operator=(VectorEnv&&) noexcept = default;
VectorEnv::~VectorEnv() = default;

absl::StatusOr<VectorEnv> VectorEnv::Create(const Client& client, int num_envs,
                                            RemoteEnvConfig config,
                                            int batch_size,
                                            std::optional<bool> failover) {
  if (num_envs < 1 || num_envs > kMaxVectorEnvs) {
    return absl::InvalidArgumentError(absl::StrCat(
        "num_envs is ", num_envs, "; allowed: 1..", kMaxVectorEnvs));
  }
  if (batch_size == 0) batch_size = num_envs;
  if (batch_size < 1 || batch_size > num_envs) {
    return absl::InvalidArgumentError(
        absl::StrCat("batch_size is ", batch_size,
                     "; allowed: 0 (num_envs) or 1..num_envs = 1..", num_envs));
  }
  absl::StatusOr<Client> session = client.OpenSession();
  if (!session.ok()) return session.status();
  config.auto_reset = true;
  // Each server's load as it reports it now; one that does not answer takes
  // no env (failover may bring it back), unless none answers.
  const int servers = session->server_count();
  std::vector<ServerCapacity> capacity(servers);
  std::vector<bool> down(servers, false);
  absl::Status unanswered = absl::OkStatus();
  for (int server = 0; server < servers; ++server) {
    auto& transport =
        static_cast<StreamTransport&>(*session->transports_[server]);
    // Asked now and remembered, so that the first StepAsync, which decides
    // the stream's batch handles from it, does not wait for it.
    absl::StatusOr<v1::ServerInfo> info = transport.ServerInfo(/*fresh=*/true);
    if (!info.ok()) {
      if (!ServerLost(info.status()) || servers == 1) return info.status();
      if (unanswered.ok()) unanswered = info.status();
      down[server] = true;
      capacity[server].usable = false;
      continue;
    }
    capacity[server] = CapacityOf(*info);
  }
  if (std::find(down.begin(), down.end(), false) == down.end()) {
    return unanswered;
  }
  // The envs still to create, placed by load (PlanPlacement), each server's
  // share a run of consecutive envs; a server that answers RESOURCE_EXHAUSTED
  // (its max_envs, or the token's quota) takes no more, and its share goes
  // to the others, as long as they have room.
  std::vector<int> remaining(num_envs);
  for (int env = 0; env < num_envs; ++env) remaining[env] = env;
  std::vector<EnvInfo> infos(num_envs);
  std::string spec;
  absl::Status full = absl::OkStatus();
  for (int round = 0; round <= servers && !remaining.empty(); ++round) {
    const std::vector<int> plan =
        internal::PlanPlacement(capacity, static_cast<int>(remaining.size()));
    int planned = 0;
    for (int count : plan) planned += count;
    if (planned < static_cast<int>(remaining.size())) {
      std::vector<std::string> room;
      for (int server = 0; server < servers; ++server) {
        room.push_back(absl::StrCat(
            session->address(server), " ",
            down[server]
                ? "unreachable"
                : absl::StrCat("hosting ", capacity[server].envs_hosted,
                               " of max_envs ", capacity[server].max_envs,
                               capacity[server].usable
                                   ? ""
                                   : ", refusing more (RESOURCE_EXHAUSTED)")));
      }
      return absl::ResourceExhaustedError(absl::StrCat(
          "no room for ", remaining.size() - planned, " of ", num_envs,
          " envs on the servers (", absl::StrJoin(room, "; "), ")",
          full.ok() ? "" : absl::StrCat(": ", full.message())));
    }
    std::vector<int> retry;
    size_t next = 0;
    for (int server = 0; server < servers; ++server) {
      if (plan[server] == 0) continue;
      std::vector<int> envs(remaining.begin() + next,
                            remaining.begin() + next + plan[server]);
      next += plan[server];
      auto& transport =
          static_cast<StreamTransport&>(*session->transports_[server]);
      std::vector<v1::SessionRequest> requests(envs.size());
      for (v1::SessionRequest& request : requests) {
        internal::EncodeConfig(config,
                               request.mutable_create_env()->mutable_config());
      }
      std::vector<v1::SessionResponse> responses;
      std::vector<absl::Status> statuses;
      (void)CallPipelined(transport, requests, &responses, &statuses);
      for (size_t k = 0; k < envs.size(); ++k) {
        if (absl::IsResourceExhausted(statuses[k])) {
          capacity[server].usable = false;
          full = absl::Status(statuses[k].code(),
                              absl::StrCat(session->address(server), ": ",
                                           statuses[k].message()));
          retry.push_back(envs[k]);
          continue;
        }
        // A failure leaves what was made to the session's end.
        if (!statuses[k].ok()) return statuses[k];
        if (envs[k] == 0) spec = responses[k].env().SerializeAsString();
        infos[envs[k]] = internal::DecodeEnv(responses[k].env());
        infos[envs[k]].server = server;
        ++capacity[server].envs_hosted;
      }
    }
    remaining = std::move(retry);
  }
  if (!remaining.empty()) return full;
  bool names = false;
  std::vector<AddressEntry> entries;
  for (const std::string& text : session->entries_) {
    absl::StatusOr<AddressEntry> entry = internal::ParseAddressEntry(text);
    if (!entry.ok()) return entry.status();
    names = names || entry->is_name;
    entries.push_back(*std::move(entry));
  }
  const std::chrono::milliseconds interval =
      session->options_.rediscover_interval;
  absl::StatusOr<VectorEnv> envs =
      Assemble(*std::move(session), std::move(infos), batch_size);
  if (envs.ok()) {
    State& state = *envs->state_;
    state.created = true;
    state.spec = std::move(spec);
    // A name may bring more servers: failover is on by default then too.
    state.failover = failover.value_or(servers > 1 || names);
    state.down = std::move(down);
    state.entries = std::move(entries);
    if (names && interval.count() > 0) {
      state.next_discovery = absl::Now() + absl::FromChrono(interval);
    }
  }
  return envs;
}

absl::StatusOr<VectorEnv> VectorEnv::Attach(
    const Client& client, const std::vector<std::string>& names) {
  if (names.empty() || names.size() > kMaxVectorEnvs) {
    return absl::InvalidArgumentError(absl::StrCat(
        "names has ", names.size(), " entries; allowed: 1..", kMaxVectorEnvs));
  }
  absl::StatusOr<Client> session = client.OpenSession();
  if (!session.ok()) return session.status();
  std::vector<EnvInfo> infos;
  for (const std::string& name : names) {
    absl::StatusOr<EnvInfo> info = session->GetEnv(name);
    if (!info.ok()) return info.status();
    if (!infos.empty() && (info->n_landers() != infos[0].n_landers() ||
                           info->continuous() != infos[0].continuous())) {
      return absl::InvalidArgumentError(
          absl::StrCat("names[", infos.size(), "] (", name, ") has n_landers ",
                       info->n_landers(), " and ",
                       info->continuous() ? "continuous" : "discrete",
                       " actions; allowed: those of names[0] (", infos[0].name,
                       "): ", infos[0].n_landers(), ", ",
                       infos[0].continuous() ? "continuous" : "discrete"));
    }
    infos.push_back(*std::move(info));
  }
  // Each env stays on the server that has it; the packed batches are per
  // server, so env i must be on server i mod S as for Create.
  const int servers =
      std::min(session->server_count(), static_cast<int>(names.size()));
  for (size_t i = 0; i < infos.size(); ++i) {
    if (infos[i].server != static_cast<int>(i) % servers) {
      return absl::InvalidArgumentError(
          absl::StrCat("names[", i, "] (", names[i], ") is on server ",
                       session->address(infos[i].server),
                       "; allowed: env i on server i mod ", servers, " (",
                       session->address(static_cast<int>(i) % servers), ")"));
    }
  }
  return Assemble(*std::move(session), std::move(infos),
                  static_cast<int>(names.size()));
}

// Created envs are bound to the session (they go with its streams);
// attached ones are not.
absl::StatusOr<VectorEnv> VectorEnv::Assemble(Client session,
                                              std::vector<EnvInfo> infos,
                                              int batch_size) {
  auto state = std::make_unique<State>(std::move(session));
  State& built = *state;
  built.n_landers = infos[0].n_landers();
  built.continuous = infos[0].continuous();
  for (const EnvInfo& info : infos) {
    built.names.push_back(info.name);
    built.placement.push_back(info.server);
    internal::EncodeConfig(info.config, &built.configs.emplace_back());
    built.TransportOf(info.server).Hold(info.name, info.idle_timeout_s);
  }
  built.shards = built.ShardsOf(built.AllEnvs(), {});
  built.down.assign(built.server_count(), false);
  built.departed.assign(built.server_count(), false);
  built.records.resize(infos.size());
  built.last_observations.assign(
      infos.size() * built.n_landers * kRemoteObservationSize, 0.0f);
  built.results.Resize(infos.size(), built.n_landers);
  built.batch_size = batch_size;
  built.in_flight.assign(infos.size(), false);
  return VectorEnv(std::move(state));
}

int VectorEnv::num_envs() const { return state_->num_envs(); }
int VectorEnv::n_landers() const { return state_->n_landers; }
bool VectorEnv::continuous() const { return state_->continuous; }
const std::vector<std::string>& VectorEnv::names() const {
  return state_->names;
}

std::string VectorEnv::address(int env) const {
  return state_->session.address(state_->placement[env]);
}

std::string VectorEnv::transport() {
  for (Shard& shard : state_->shards) {
    if (shard.transport->transport_name() != "shared_memory") return "native";
  }
  return "shared_memory";
}

void VectorEnv::SetEventLog(EventLog log) {
  state_->event_log = std::move(log);
}

bool VectorEnv::failover() const { return state_->failover; }
int VectorEnv::failovers() const { return state_->failovers; }
int VectorEnv::rebalances() const { return state_->rebalances; }

absl::Status VectorEnv::Reset(std::optional<uint64_t> seed) {
  if (!seed.has_value()) return Reset(absl::Span<const uint64_t>());
  std::vector<uint64_t> seeds(num_envs());
  for (int env = 0; env < num_envs(); ++env) seeds[env] = *seed + env;
  return Reset(absl::MakeConstSpan(seeds));
}

absl::Status VectorEnv::CheckNothingInFlight() const {
  if (state_->step_in_flight) {
    return absl::FailedPreconditionError(
        "a step sent by StepAsync (step_async) is in flight; StepWait "
        "(step_wait) for its results first");
  }
  if (state_->in_flight_count == 0) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      state_->in_flight_count,
      " envs have a Send (or AsyncReset) whose results Recv has not "
      "returned; Recv them first"));
}

absl::Status VectorEnv::Reset(absl::Span<const uint64_t> seeds) {
  State& state = *state_;
  if (absl::Status status = CheckNothingInFlight(); !status.ok()) return status;
  // Empty from Reset(nullopt): no reseed.
  if (!seeds.empty() && seeds.size() != state.names.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat("seeds has ", seeds.size(),
                     " entries; expected num_envs = ", state.names.size()));
  }
  state.Maintain(/*seeded_reset=*/!seeds.empty());
  Columns& out = state.results;
  out.Resize(state.names.size(), state.n_landers);
  // A seeded reset starts its envs afresh: failover has nothing to replay.
  absl::Status status =
      state.WithFailover(state.AllEnvs(), /*fresh=*/!seeds.empty(),
                         [&](const std::vector<int>& envs, EnvErrors* lost) {
                           return state.ResetEnvs(envs, seeds, &out, lost);
                         });
  state.results.env_ids = state.AllEnvs();
  return status;
}

absl::Status VectorEnv::Step(absl::Span<const int32_t> discrete_actions) {
  absl::Status status = StepAsync(discrete_actions);
  return status.ok() ? StepWait() : status;
}

absl::Status VectorEnv::Step(absl::Span<const float> continuous_actions) {
  absl::Status status = StepAsync(continuous_actions);
  return status.ok() ? StepWait() : status;
}

absl::Status VectorEnv::CheckActions(size_t count, bool continuous_actions,
                                     size_t envs) const {
  const State& state = *state_;
  if (continuous_actions != state.continuous) {
    return absl::InvalidArgumentError(absl::StrCat(
        "actions are ", continuous_actions ? "continuous" : "discrete",
        "; the envs take ", state.continuous ? "continuous" : "discrete",
        " actions"));
  }
  const size_t per_env =
      state.n_landers * (continuous_actions ? kRemoteContinuousActionSize : 1);
  if (count != per_env * envs) {
    return absl::InvalidArgumentError(
        absl::StrCat("actions has ", count, " values; expected ",
                     envs == state.names.size() ? "num_envs" : "len(env_ids)",
                     " * n_landers", continuous_actions ? " * 2" : "", " = ",
                     per_env * envs));
  }
  return absl::OkStatus();
}

absl::Status VectorEnv::StepAsync(absl::Span<const int32_t> discrete_actions) {
  return StepAsyncWith(
      absl::string_view(reinterpret_cast<const char*>(discrete_actions.data()),
                        discrete_actions.size() * sizeof(int32_t)),
      discrete_actions.size(), /*continuous_actions=*/false);
}

absl::Status VectorEnv::StepAsync(absl::Span<const float> continuous_actions) {
  return StepAsyncWith(
      absl::string_view(
          reinterpret_cast<const char*>(continuous_actions.data()),
          continuous_actions.size() * sizeof(float)),
      continuous_actions.size(), /*continuous_actions=*/true);
}

absl::Status VectorEnv::StepAsyncWith(absl::string_view action_bytes,
                                      size_t count, bool continuous_actions) {
  State& state = *state_;
  if (absl::Status status = CheckNothingInFlight(); !status.ok()) return status;
  if (absl::Status status =
          CheckActions(count, continuous_actions, state.names.size());
      !status.ok()) {
    return status;
  }
  state.Maintain(/*seeded_reset=*/false);
  const size_t env_bytes = state.row_bytes();
  for (Shard& shard : state.shards) {
    std::string* data = shard.request.mutable_step_batch()
                            ->mutable_packed()
                            ->mutable_actions()
                            ->mutable_data();
    data->resize(shard.rows.size() * env_bytes);
    for (size_t k = 0; k < shard.rows.size(); ++k) {
      std::memcpy(data->data() + k * env_bytes,
                  action_bytes.data() + shard.rows[k] * env_bytes, env_bytes);
    }
  }
  state.step_actions.assign(action_bytes.data(), action_bytes.size());
  state.step_sequences = State::SendBatches(state.shards);
  state.step_answers.assign(state.shards.size(), std::nullopt);
  state.step_in_flight = true;
  return absl::OkStatus();
}

absl::Status VectorEnv::StepWait() { return *StepWaitUntil(kNoDeadline); }

std::optional<absl::Status> VectorEnv::StepWait(
    std::chrono::milliseconds timeout) {
  return StepWaitUntil(DeadlineAfter(timeout));
}

std::optional<absl::Status> VectorEnv::StepWaitUntil(
    std::chrono::steady_clock::time_point deadline) {
  State& state = *state_;
  if (!state.step_in_flight) {
    return absl::FailedPreconditionError(
        "StepWait (step_wait) without a StepAsync (step_async) in flight");
  }
  if (!State::AwaitBatches(state.shards, state.step_sequences,
                           &state.step_answers, deadline)) {
    return std::nullopt;
  }
  state.step_in_flight = false;
  const absl::string_view action_bytes = state.step_actions;
  const size_t env_bytes = state.row_bytes();
  Columns& out = state.results;
  out.Resize(state.names.size(), state.n_landers);
  // The first try collects the answers to the shards' requests; a retry
  // after a failover steps the envs it moved, with this step's actions.
  bool first_try = true;
  absl::Status status = state.WithFailover(
      state.AllEnvs(), /*fresh=*/false,
      [&](const std::vector<int>& envs, EnvErrors* lost) {
        std::vector<int> stepped;
        absl::Status result;
        if (first_try) {
          first_try = false;
          result = state.CollectBatches(state.shards, state.step_answers, &out,
                                        lost, &stepped);
        } else {
          std::vector<absl::string_view> rows;
          for (int env : envs) {
            rows.push_back(action_bytes.substr(env * env_bytes, env_bytes));
          }
          std::vector<Shard> retry = state.ShardsOf(envs, rows);
          result = state.RunStepBatches(retry, &out, lost, &stepped);
        }
        state.RecordSteps(stepped, action_bytes, out);
        return result;
      });
  out.MaskAutoResetRows(state.n_landers);
  out.env_ids = state.AllEnvs();
  state.step_answers.clear();
  state.step_sequences.clear();
  return status;
}

// ----------------------------------------------------- EnvPool's async API

int VectorEnv::batch_size() const { return state_->batch_size; }
int VectorEnv::in_flight() const { return state_->in_flight_count; }

absl::Status VectorEnv::AsyncReset(std::optional<uint64_t> seed) {
  State& state = *state_;
  absl::Status status = Reset(seed);
  if (!status.ok()) return status;
  ReadyChunk chunk;
  chunk.envs = state.results.env_ids;
  chunk.columns = state.results;
  std::fill(chunk.columns.active.begin(), chunk.columns.active.end(), 0);
  state.ready_rows += chunk.envs.size();
  state.ready.push_back(std::move(chunk));
  state.in_flight.assign(state.names.size(), true);
  state.in_flight_count = state.num_envs();
  return absl::OkStatus();
}

absl::Status VectorEnv::Send(absl::Span<const int32_t> discrete_actions,
                             absl::Span<const int> env_ids) {
  return SendWith(
      absl::string_view(reinterpret_cast<const char*>(discrete_actions.data()),
                        discrete_actions.size() * sizeof(int32_t)),
      discrete_actions.size(), /*continuous_actions=*/false, env_ids);
}

absl::Status VectorEnv::Send(absl::Span<const float> continuous_actions,
                             absl::Span<const int> env_ids) {
  return SendWith(absl::string_view(
                      reinterpret_cast<const char*>(continuous_actions.data()),
                      continuous_actions.size() * sizeof(float)),
                  continuous_actions.size(), /*continuous_actions=*/true,
                  env_ids);
}

absl::Status VectorEnv::SendWith(absl::string_view action_bytes, size_t count,
                                 bool continuous_actions,
                                 absl::Span<const int> env_ids) {
  State& state = *state_;
  if (state.step_in_flight) return CheckNothingInFlight();
  if (env_ids.empty()) {
    return absl::InvalidArgumentError(
        "env_ids is empty; expected distinct env indices");
  }
  std::vector<bool> seen(state.names.size(), false);
  for (int env : env_ids) {
    if (env < 0 || env >= state.num_envs()) {
      return absl::InvalidArgumentError(absl::StrCat(
          "env_ids holds ", env, "; allowed: 0..", state.num_envs() - 1));
    }
    if (seen[env]) {
      return absl::InvalidArgumentError(absl::StrCat(
          "env_ids holds ", env, " more than once; each env at most once"));
    }
    seen[env] = true;
    if (state.in_flight[env]) {
      return absl::FailedPreconditionError(absl::StrCat(
          "env ", env,
          " has a step in flight (sent, or reset by AsyncReset); Recv its "
          "result before sending it another"));
    }
  }
  if (absl::Status status =
          CheckActions(count, continuous_actions, env_ids.size());
      !status.ok()) {
    return status;
  }
  state.Maintain(/*seeded_reset=*/false);
  const size_t env_bytes = state.row_bytes();
  const std::vector<int> envs(env_ids.begin(), env_ids.end());
  std::vector<absl::string_view> rows;
  for (size_t k = 0; k < envs.size(); ++k) {
    rows.push_back(action_bytes.substr(k * env_bytes, env_bytes));
  }
  return state.SendSteps(envs, rows);
}

absl::Status VectorEnv::ReceiveOne() {
  State& state = *state_;
  PendingRequest request = std::move(state.pending.front());
  state.pending.pop_front();
  StreamTransport& transport = state.TransportOf(request.server);
  v1::SessionResponse response;
  absl::Status status = request.sequence.status();
  if (request.answer.has_value()) {
    status = *std::move(request.answer);
    request.answer.reset();
    response = std::move(request.response);
  } else if (status.ok()) {
    status = transport.Receive(*request.sequence, &response);
  }
  if (!status.ok()) {
    if (!state.Lost(status, request.envs[0])) {
      state.Release(request.envs);
      return status;
    }
    EnvErrors lost;
    std::vector<PendingRequest> requests;
    if (ServerLost(status)) {
      // The server is lost with every request in flight on it: all its envs
      // move, and those requests go again.
      for (int env = 0; env < state.num_envs(); ++env) {
        if (state.placement[env] == request.server) lost.emplace(env, status);
      }
      state.SettleRequestsOf(request.server, status);
      requests.push_back(std::move(request));
      state.TakeRequestsOf(requests[0].server, &requests);
    } else {
      for (int env : request.envs) lost.emplace(env, status);
      requests.push_back(std::move(request));
    }
    return state.FailOverAndResend(lost, requests);
  }
  const int n = state.n_landers;
  Columns columns;
  columns.Resize(request.envs.size(), n);
  std::vector<int> rows(request.envs.size());
  for (size_t k = 0; k < rows.size(); ++k) rows[k] = static_cast<int>(k);
  EnvErrors lost;
  EnvErrors failed;
  status = state.CollectPacked(response, request.envs, rows,
                               transport.address(), &columns, &lost, &failed);
  if (!status.ok()) {
    state.Release(request.envs);
    return status;
  }
  // The envs that stepped go into their records (what their server did,
  // even when another env's error is returned); those lost go again.
  std::vector<size_t> stepped;
  PendingRequest retry;
  retry.server = request.server;
  const size_t row_bytes = state.row_bytes();
  for (size_t k = 0; k < request.envs.size(); ++k) {
    const int env = request.envs[k];
    const absl::string_view action_row =
        absl::string_view(request.actions).substr(k * row_bytes, row_bytes);
    if (lost.count(env) != 0) {
      retry.envs.push_back(env);
      retry.actions.append(action_row.data(), action_row.size());
    } else if (failed.count(env) == 0) {
      state.RecordStep(env, action_row, columns, k);
      stepped.push_back(k);
    }
  }
  if (!failed.empty()) {
    state.Release(request.envs);
    return failed.begin()->second;
  }
  columns.MaskAutoResetRows(n);
  ReadyChunk chunk;
  if (lost.empty()) {
    chunk.envs = std::move(request.envs);
    chunk.columns = std::move(columns);
  } else {
    chunk.columns.Resize(stepped.size(), n);
    for (size_t row = 0; row < stepped.size(); ++row) {
      chunk.columns.CopyRow(columns, stepped[row], row, n);
      chunk.envs.push_back(request.envs[stepped[row]]);
    }
  }
  state.ready_rows += chunk.envs.size();
  if (!chunk.envs.empty()) state.ready.push_back(std::move(chunk));
  if (lost.empty()) return absl::OkStatus();
  std::vector<PendingRequest> requests;
  requests.push_back(std::move(retry));
  return state.FailOverAndResend(lost, requests);
}

// ------------------------------------------------------------ env snapshot

absl::Status VectorEnv::CheckEnvIndex(int env) const {
  if (env >= 0 && env < num_envs()) return absl::OkStatus();
  return absl::InvalidArgumentError(
      absl::StrCat("env index is ", env, "; allowed: 0..", num_envs() - 1));
}

absl::StatusOr<std::string> VectorEnv::EnvSnapshot(int env) const {
  const State& state = *state_;
  if (absl::Status status = CheckNothingInFlight(); !status.ok()) return status;
  if (absl::Status status = CheckEnvIndex(env); !status.ok()) return status;
  if (absl::Status status = state.RecordProblem(env); !status.ok()) {
    return status;
  }
  absl::StatusOr<v1::ServerInfo> server =
      state.TransportOf(state.placement[env]).ServerInfo();
  if (!server.ok()) return server.status();
  return internal::EncodeSnapshot(
      state.configs[env], *server, state.records[env],
      state.continuous ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32,
      static_cast<uint32_t>(state.row_bytes()), state.LastObservations(env));
}

absl::StatusOr<std::vector<float>> VectorEnv::RestoreEnv(
    int env, absl::string_view snapshot) {
  State& state = *state_;
  if (absl::Status status = CheckNothingInFlight(); !status.ok()) return status;
  if (absl::Status status = CheckEnvIndex(env); !status.ok()) return status;
  if (!state.created) {
    return absl::FailedPreconditionError(absl::StrCat(
        state.Label(env),
        " was attached, not created by this VectorEnv: RestoreEnv replaces "
        "an env, and this one is not the VectorEnv's to delete"));
  }
  absl::StatusOr<internal::DecodedSnapshot> decoded =
      internal::DecodeSnapshot(snapshot);
  if (!decoded.ok()) return decoded.status();
  const int server = state.placement[env];
  StreamTransport& transport = state.TransportOf(server);
  absl::StatusOr<v1::ServerInfo> server_info = transport.ServerInfo();
  if (!server_info.ok()) return server_info.status();
  if (absl::Status status =
          internal::CheckRestorable(*decoded, state.configs[env], *server_info);
      !status.ok()) {
    return status;
  }
  absl::StatusOr<std::vector<EnvInfo>> created = Replay(
      transport,
      {{&state.configs[env], &decoded->record, decoded->last_observations,
        absl::StrCat("env ", env, " (restored)")}});
  if (!created.ok()) return created.status();
  EnvInfo replaced;
  replaced.name = state.names[env];
  state.Replace(env, server, (*created)[0]);
  DeleteEnvs(transport, {replaced});
  state.shards = state.ShardsOf(state.AllEnvs(), {});
  state.records[env] = std::move(decoded->record);
  std::vector<float> observations(static_cast<size_t>(state.n_landers) *
                                  kRemoteObservationSize);
  std::memcpy(observations.data(), decoded->last_observations.data(),
              observations.size() * sizeof(float));
  std::copy(observations.begin(), observations.end(),
            state.last_observations.begin() + env * observations.size());
  return observations;
}

absl::Status VectorEnv::Recv() { return *RecvUntil(kNoDeadline); }

std::optional<absl::Status> VectorEnv::Recv(std::chrono::milliseconds timeout) {
  return RecvUntil(DeadlineAfter(timeout));
}

std::optional<absl::Status> VectorEnv::RecvUntil(
    std::chrono::steady_clock::time_point deadline) {
  State& state = *state_;
  if (state.in_flight_count < state.batch_size) {
    return absl::FailedPreconditionError(
        absl::StrCat("Recv needs batch_size = ", state.batch_size,
                     " envs with a step in flight; ", state.in_flight_count,
                     " have one (Send or AsyncReset first)"));
  }
  while (state.ready_rows < static_cast<size_t>(state.batch_size)) {
    if (!state.AwaitOldest(deadline)) return std::nullopt;
    if (absl::Status status = ReceiveOne(); !status.ok()) return status;
  }
  Columns& out = state.results;
  out.Resize(state.batch_size, state.n_landers);
  for (int row = 0; row < state.batch_size; ++row) {
    ReadyChunk& chunk = state.ready.front();
    out.CopyRow(chunk.columns, chunk.taken, row, state.n_landers);
    const int env = chunk.envs[chunk.taken];
    out.env_ids[row] = env;
    state.in_flight[env] = false;
    if (++chunk.taken == chunk.envs.size()) state.ready.pop_front();
  }
  state.ready_rows -= state.batch_size;
  state.in_flight_count -= state.batch_size;
  return absl::OkStatus();
}

absl::Span<const int> VectorEnv::env_ids() const {
  return state_->results.env_ids;
}

absl::Span<const float> VectorEnv::observations() const {
  return state_->results.observations;
}
absl::Span<const float> VectorEnv::rewards() const {
  return state_->results.rewards;
}
absl::Span<const uint8_t> VectorEnv::terminations() const {
  return state_->results.terminations;
}
absl::Span<const uint8_t> VectorEnv::truncations() const {
  return state_->results.truncations;
}
absl::Span<const uint8_t> VectorEnv::active() const {
  return state_->results.active;
}
absl::Span<const uint8_t> VectorEnv::outcomes() const {
  return state_->results.outcomes;
}
absl::Span<const float> VectorEnv::episode_returns() const {
  return state_->results.episode_returns;
}
absl::Span<const int32_t> VectorEnv::episode_lengths() const {
  return state_->results.episode_lengths;
}
absl::Span<const uint8_t> VectorEnv::auto_reset() const {
  return state_->results.auto_reset;
}
absl::Span<const uint8_t> VectorEnv::episode_over() const {
  return state_->results.episode_over;
}

StepData VectorEnv::Result(int row) const {
  const Columns& results = state_->results;
  const int n = state_->n_landers;
  const size_t first = static_cast<size_t>(row) * n;
  const auto slice = [&](const auto& column) {
    return std::vector<typename std::decay_t<decltype(column)>::value_type>(
        column.begin() + first, column.begin() + first + n);
  };
  StepData data;
  data.n_landers = n;
  data.observations.assign(
      results.observations.begin() + first * kRemoteObservationSize,
      results.observations.begin() + (first + n) * kRemoteObservationSize);
  data.rewards = slice(results.rewards);
  data.terminations = slice(results.terminations);
  data.truncations = slice(results.truncations);
  data.stepped = slice(results.active);
  for (uint8_t outcome : slice(results.outcomes)) {
    data.outcomes.push_back(static_cast<LanderOutcome>(outcome));
  }
  data.episode_returns = slice(results.episode_returns);
  data.episode_lengths = slice(results.episode_lengths);
  data.episode_over = results.episode_over[row] != 0;
  data.auto_reset = results.auto_reset[row] != 0;
  return data;
}

}  // namespace mll::client

namespace mll::client::internal {

const std::string& VectorEnvBridge::Spec(const VectorEnv& envs) {
  return envs.state_->spec;
}

int VectorEnvBridge::ServerCount(const VectorEnv& envs) {
  return envs.state_->server_count();
}

const std::string& VectorEnvBridge::ServerAddress(const VectorEnv& envs,
                                                  int server) {
  return envs.state_->session.address(server);
}

absl::StatusOr<std::string> VectorEnvBridge::ServerInfo(VectorEnv& envs,
                                                        int server) {
  absl::StatusOr<v1::ServerInfo> info =
      envs.state_->TransportOf(server).ServerInfo();
  if (!info.ok()) return info.status();
  return info->SerializeAsString();
}

}  // namespace mll::client::internal

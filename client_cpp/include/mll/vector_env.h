// Many environments stepped together, arrays in and out: the C++ counterpart
// of the Python client's `vector_env`, with the same layout and the same
// bits.
//
//   mll::client::ClientOptions options;  // session_transport: kAuto
//   auto client = mll::client::Client::Create("127.0.0.1:50051", options);
//   mll::client::RemoteEnvConfig config;
//   config.n_landers = 3;
//   auto envs = mll::client::VectorEnv::Create(*client, 64, config);
//   envs->Reset(/*seed=*/0);
//   std::vector<int32_t> actions(envs->num_envs() * envs->n_landers());
//   envs->Step(actions);  // envs->observations(), rewards(), active(), ...
//
// Placement: Create puts the envs on the client's servers by the load each
// reports (GetServerInfo: envs hosted by every tenant against its max_envs,
// CPU used against its cores as the tie-break), water-filling: each env to
// the server that is least full after taking it, so the fleet ends as even as
// it can (a server half full of another tenant's envs gets fewer). A server
// that answers RESOURCE_EXHAUSTED (its max_envs, or the token's quota) takes
// no more and its share goes to the others with room; RESOURCE_EXHAUSTED
// when none has. Each server's envs are a run of consecutive env indices;
// address(i) says where env i is. Each step sends one packed StepBatch to
// every server at once (pipelined on each server's Session stream: shared
// memory for a server on this host, as ClientOptions::session_transport
// chooses) and puts the results back in env order. The envs are created on
// those streams with the server's auto_reset, so they die with the VectorEnv
// (or its process).
//
// Discovery: a host name in the client's address list (e.g. a Kubernetes
// headless Service, "mll.default.svc.cluster.local:50051") stands for every
// address it resolves to (Client::Create). The VectorEnv resolves it again
// every ClientOptions::rediscover_interval (10 s by default; off its thread,
// taken in at its next Reset, StepAsync/Step or Send) and at every failover.
// A server that joins the name, answers GetServerInfo with this client's
// protocol major and its health check SERVING, is used: new envs may go
// there, and the envs are rebalanced onto it (below). A server gone from the
// name takes no new env; its envs stay while it answers (scale-down is a
// drain: the server's SIGTERM makes failover move them). Every server of a
// name gone and down: the failover's UNAVAILABLE names the name and what it
// resolved to.
//
// Rebalancing: when a server joins (or one found down answers again), the
// VectorEnv moves its own envs onto it until they are even within one env
// per server (over the servers up and in their names), at its next call,
// envs with nothing in flight only. At a seeded Reset the moved envs are
// created afresh on their new servers (nothing to replay); else each is
// recreated there, its record replayed and checked to the bits, and the old
// env deleted. Either way every env gives the same bits as an undisturbed
// run. An env whose record cannot be replayed (never reset, or past its
// bound) moves at the next seeded Reset. Each move onto a server counts in
// rebalances() and is logged once, as failover events are.
//
// Episode ends (auto-reset): when an env's episode is over (no lander
// active), its next step ignores the actions and starts a new episode,
// continuing that env's generator stream (no reseed): its rows hold the new
// episode's first observations, zero rewards, no terminations/truncations,
// auto_reset()[i] is 1 and active() is 0 for its landers. Rows of landers that
// are done (before the episode is over) are zero, and not active.
//
// Results are views of arrays the VectorEnv owns, env-major, valid until the
// next call that makes results (Reset, Step, StepWait, Recv). Errors: a step
// that fails for some envs on their server (e.g. an env deleted behind the
// VectorEnv's back: NOT_FOUND) returns the server's code and message for the
// first of them in env order, prefixed "env {i} ({name}): "; the other envs did
// step. One thread at a time.
//
// Failover: the VectorEnv keeps each env's record (its options, the seed of
// its last seeded reset, and every operation since: each step's actions,
// auto-reset steps, unseeded resets). When a server becomes unreachable
// (UNAVAILABLE, a draining server's "draining: ..." included), stalls (it
// misses its deadline, ClientOptions::step_timeout: DEADLINE_EXCEEDED; its
// stream is cancelled, so nothing it answers late is taken) or loses an env
// (NOT_FOUND naming it) during Reset, Step or Recv, the VectorEnv recreates
// each lost env on a reachable server (placed by load as Create places,
// over the servers in their names not found down, those that joined, and
// those found down that answer again on a new channel, asked at each
// failover; a server without room is passed over), replays
// its record, checks that the replayed observations equal the last ones seen
// (else DATA_LOSS naming the env), and retries the operation: the caller
// sees the same observations, rewards and episode boundaries as without the
// fault. A target that turns out unreachable during the replay (draining, or
// dead) is passed over for the next; when none is left, UNAVAILABLE names the
// servers tried. EnvPool's Send/Recv steps are recorded per env as their
// results come: a server lost during Recv has every env on it recreated and
// replayed to the last results received, and the steps that were in flight
// on it sent again on the envs' new servers, so Recv returns the same
// per-env results as without the fault. Each event counts in failovers() and
// is logged once with its cause (on stderr, or where SetEventLog says). A
// record holds at most 100,000 operations since its seeded reset; past it
// failover and EnvSnapshot of that env fail FAILED_PRECONDITION naming it,
// until its next seeded reset.
//
// Snapshots: EnvSnapshot(i) gives env i's record as bytes in the Python
// client's format (multi_lunar_lander/_record.py: "MLLS", format version, the
// server's wire protocol and release, the EnvConfig, the seed, the operations
// and their actions, the last observations, a CRC-32), and
// RestoreEnv(i, snapshot) puts env i at the point a snapshot (from either
// client) describes.
#ifndef MLL_VECTOR_ENV_H_
#define MLL_VECTOR_ENV_H_

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/types/span.h"
#include "mll/client.h"

namespace mll::client {

namespace internal {
struct VectorEnvBridge;
}  // namespace internal

// Receives each failover event's line (VectorEnv::SetEventLog).
using EventLog = std::function<void(const std::string& line)>;

class VectorEnv {
 public:
  // `num_envs` (1..65536) new environments with `config` (auto_reset is
  // forced on) on the servers of `client` (placed by load, above), over a
  // session of its own (Client::OpenSession with the client's options).
  // batch_size: how many envs Recv returns (EnvPool's async API, below);
  // 0 means num_envs. failover (above): unset turns it on with several
  // servers or a host name and off with one address; false turns it off
  // (errors reach the caller as they are), true turns it on with one server
  // too (the VectorEnv then retries that server once it answers again).
  static absl::StatusOr<VectorEnv> Create(
      const Client& client, int num_envs, RemoteEnvConfig config = {},
      int batch_size = 0, std::optional<bool> failover = std::nullopt);
  // Existing environments, by name, which must share n_landers and the
  // action type (INVALID_ARGUMENT naming the first that does not); they are
  // not deleted by the VectorEnv. Without auto_reset, a step of an env whose
  // episode is over fails FAILED_PRECONDITION. Failover is off: the envs are
  // not the VectorEnv's to recreate.
  static absl::StatusOr<VectorEnv> Attach(
      const Client& client, const std::vector<std::string>& names);

  VectorEnv(VectorEnv&&) noexcept;
  VectorEnv& operator=(VectorEnv&&) noexcept;
  ~VectorEnv();

  int num_envs() const;
  int n_landers() const;
  bool continuous() const;
  // `envs/{id}` of each env, in env order.
  const std::vector<std::string>& names() const;
  // The address of env `env`'s server.
  std::string address(int env) const;
  // "shared_memory" when every server's stream passes its messages through
  // shared memory, else "native" (opening the streams if none is open).
  std::string transport();

  // Starts an episode in every env: `seed` s gives env i the seed s + i;
  // nothing continues each env's generator stream.
  absl::Status Reset(std::optional<uint64_t> seed = std::nullopt);
  // The same with one seed per env (seeds.size() == num_envs()).
  absl::Status Reset(absl::Span<const uint64_t> seeds);

  // One step of every env: discrete actions int32 [num_envs, n_landers] or
  // continuous float32 [num_envs, n_landers, 2], row-major. Entries of done
  // agents are ignored. INVALID_ARGUMENT for the wrong size or action type.
  absl::Status Step(absl::Span<const int32_t> discrete_actions);
  absl::Status Step(absl::Span<const float> continuous_actions);

  // Step split in two (Step is StepAsync then StepWait): StepAsync checks
  // the actions and sends the step (one packed StepBatch per server, all in
  // flight at once) and returns; StepWait waits for the answers and makes
  // them the results, the same bits as Step (the latest results stay as
  // they were until then). Failover and the step's errors are StepWait's.
  // One step in flight at a time: Reset, Step, StepAsync, AsyncReset, Send,
  // EnvSnapshot and RestoreEnv fail FAILED_PRECONDITION while it is, as does
  // StepWait without one.
  absl::Status StepAsync(absl::Span<const int32_t> discrete_actions);
  absl::Status StepAsync(absl::Span<const float> continuous_actions);
  absl::Status StepWait();
  // StepWait waiting at most `timeout`: nothing when it passed first (the
  // step stays in flight; call again: nothing is lost or repeated), so a
  // caller can wait in slices and handle its signals between them.
  std::optional<absl::Status> StepWait(std::chrono::milliseconds timeout);

  // EnvPool's async API: AsyncReset resets every env (seeds as Reset) and
  // makes their first observations the results of the next Recv calls. Send
  // sends one step of the envs `env_ids` (distinct, 0..num_envs-1, none with
  // a step in flight) with their actions ([len(env_ids), n_landers] or
  // [len(env_ids), n_landers, 2]) and returns at once: one packed StepBatch
  // per server concerned, pipelined behind those in flight on its stream.
  // Recv waits for the first batch_size envs whose steps are done and makes
  // them the results below (batch_size rows, in the order they came; env_ids()
  // names each row's env). Each env's results are the same bits as with
  // Step for the same actions. Errors: INVALID_ARGUMENT for bad env_ids or
  // actions; FAILED_PRECONDITION for a Send to an env in flight, a Recv with
  // fewer than batch_size envs in flight, and Reset or Step while any is.
  // With failover on, a Send that finds its server lost stays in flight and
  // the Recv that meets it fails over (above); an error that Recv returns
  // ends the steps in flight of the envs it concerns (their results are
  // lost).
  int batch_size() const;
  // Envs with a step (or AsyncReset) in flight whose results Recv has not
  // returned.
  int in_flight() const;
  absl::Status AsyncReset(std::optional<uint64_t> seed = std::nullopt);
  absl::Status Send(absl::Span<const int32_t> discrete_actions,
                    absl::Span<const int> env_ids);
  absl::Status Send(absl::Span<const float> continuous_actions,
                    absl::Span<const int> env_ids);
  absl::Status Recv();
  // Recv waiting at most `timeout`, as StepWait(timeout): nothing when it
  // passed first (the answers received meanwhile are kept for the next Recv).
  std::optional<absl::Status> Recv(std::chrono::milliseconds timeout);
  // The env of each row of the latest results (0..num_envs-1 after Reset and
  // Step).
  absl::Span<const int> env_ids() const;

  // The results of the latest Reset, Step or Recv, row-major (num_envs rows
  // after Reset and Step, env i in row i; batch_size rows after Recv).
  // float32 [rows, n_landers, 12].
  absl::Span<const float> observations() const;
  // [rows, n_landers].
  absl::Span<const float> rewards() const;
  absl::Span<const uint8_t> terminations() const;
  absl::Span<const uint8_t> truncations() const;
  // 1 where the row carries a transition: the lander was active at the start
  // of the step and the step was not an auto-reset.
  absl::Span<const uint8_t> active() const;
  // LanderOutcome codes so far in the episode (final once done).
  absl::Span<const uint8_t> outcomes() const;
  absl::Span<const float> episode_returns() const;
  absl::Span<const int32_t> episode_lengths() const;
  // [rows].
  absl::Span<const uint8_t> auto_reset() const;
  absl::Span<const uint8_t> episode_over() const;

  // Row `row` of the latest results as a StepData (a copy), e.g. for a
  // pilot that acts on one env.
  StepData Result(int row) const;

  // Whether failover is on, and the failover events so far.
  bool failover() const;
  int failovers() const;
  // The rebalancing events so far: each a move of envs onto one server
  // (Rebalancing, above).
  int rebalances() const;
  // Where each failover (and rebalancing) event's line goes (one line, no
  // newline): by default stderr, prefixed "mll_client: "; to `log` instead once
  // set (none to stderr then); an empty `log` restores stderr.
  void SetEventLog(EventLog log);

  // Env `env`'s snapshot: bytes that recreate it at this point to the same
  // bits on any server of the same release (RestoreEnv here, restore_env or
  // parallel_env's restore in Python). FAILED_PRECONDITION naming the env
  // when its record cannot (never reset, or past 100,000 operations), or
  // while any env is in flight.
  absl::StatusOr<std::string> EnvSnapshot(int env) const;
  // Puts env `env` at the point `snapshot` describes: a new env on the same
  // server replays it, checked to the bits, then replaces the old one (a new
  // name). Returns its observations, float32 [n_landers, 12]; the latest
  // results are unchanged. INVALID_ARGUMENT naming what is wrong for a
  // damaged snapshot (CRC, magic, format version, truncation) or one of an
  // env with other options; DATA_LOSS when the replay gives other bits
  // (another release's physics); FAILED_PRECONDITION for an attached env. On
  // any error the env is untouched.
  absl::StatusOr<std::vector<float>> RestoreEnv(int env,
                                                absl::string_view snapshot);

 private:
  friend struct internal::VectorEnvBridge;
  struct State;
  explicit VectorEnv(std::unique_ptr<State> state);
  static absl::StatusOr<VectorEnv> Assemble(Client session,
                                            std::vector<EnvInfo> infos,
                                            int batch_size);
  absl::Status CheckNothingInFlight() const;
  absl::Status CheckActions(size_t count, bool continuous_actions,
                            size_t envs) const;
  absl::Status StepAsyncWith(absl::string_view action_bytes, size_t count,
                             bool continuous_actions);
  std::optional<absl::Status> StepWaitUntil(
      std::chrono::steady_clock::time_point deadline);
  std::optional<absl::Status> RecvUntil(
      std::chrono::steady_clock::time_point deadline);
  absl::Status SendWith(absl::string_view action_bytes, size_t count,
                        bool continuous_actions, absl::Span<const int> env_ids);
  absl::Status ReceiveOne();
  absl::Status CheckEnvIndex(int env) const;

  std::unique_ptr<State> state_;
};

}  // namespace mll::client

#endif  // MLL_VECTOR_ENV_H_

// C++ client of the Multi Lunar Lander server (proto/mll/v1).
//
// A `Client` is made from an address; it creates environments on the server
// and hands back `RemoteEnv` handles, which delete their environment when
// destroyed unless released. Every call has a unary form; `Client::
// OpenSession()` returns a client whose calls travel over one bidirectional
// `Session` stream instead (the lowest latency), with the same methods.
//
// Several servers (scale-out): `Client::Create(addresses)` makes one client
// over a list of servers. Each environment lives on one server for its life:
// CreateEnv places them round-robin (CreateEnvOn picks the server), and the
// handle's calls go to that server only. StepBatch splits a batch by server,
// sends one StepBatch per server, all in flight at once, and returns results
// in the caller's order. ListEnvs concatenates every server's list; GetEnv,
// Attach and DeleteEnv look a name up on each server in turn. A session
// client over several servers holds one stream per server.
//
// Security: `ClientOptions` selects TLS (root certificates, target name
// override) and a bearer token, which is sent on every call: unary calls,
// Session streams and health checks (a server with tokens answers health
// checks without one too).
//
// Results are plain C++ types; no protobuf or gRPC type appears here. Errors
// are absl::Status values carrying the server's canonical code and message
// (INVALID_ARGUMENT, NOT_FOUND, FAILED_PRECONDITION, UNAVAILABLE, ...).
//
// Threading: a unary Client and its handles may be used from many threads
// (one RemoteEnv at a time per env, as the server serialises each env anyway).
// A session client serialises its calls on its one stream.
//
// Everything here is in namespace mll::client; the simulation core's types
// are in mll::core, so a program may link both, as the equivalence test does.
#ifndef MLL_CLIENT_H_
#define MLL_CLIENT_H_

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/types/span.h"
#include "mll/core/env_config.h"

namespace mll::client {

namespace internal {
class Transport;
}  // namespace internal

// How the messages of a session client (Client::OpenSession, VectorEnv)
// travel; the names are those of the Python client's `transport=`.
enum class SessionTransport {
  // "auto": shared memory where the server grants it and this process can
  // map its region (a server on this host, outside other containers), else
  // the gRPC stream.
  kAuto,
  // "shared_memory": shared memory, or FAILED_PRECONDITION saying why not
  // (the server's refusal, or a region this process cannot map).
  kSharedMemory,
  // "native": the gRPC stream always.
  kNative,
};

// "auto", "shared_memory" or "native".
absl::string_view SessionTransportName(SessionTransport transport);

// How the client reaches the server.
struct ClientOptions {
  // TLS instead of a plaintext channel.
  bool use_tls = false;
  // PEM root certificates for TLS (the text, not a path); empty uses gRPC's
  // default roots. A self-signed server certificate is its own root.
  std::string tls_root_certificates;
  // TLS: when non-empty, the name the server's certificate is checked
  // against instead of the address's host (e.g. a certificate for
  // "mll.internal" reached as 10.0.0.7:50051).
  std::string tls_target_name_override;
  // When non-empty, sent as `authorization: Bearer <token>` on every call
  // (the server answers UNAUTHENTICATED when it wants one and this is wrong).
  // Printable ASCII without spaces, else Create fails INVALID_ARGUMENT.
  std::string token;
  // Deadline of each unary call; zero means none. Session calls have none:
  // the stream lives as long as the session.
  std::chrono::milliseconds call_timeout{0};
  // Largest message the client accepts (a batch of many 32-lander envs, or a
  // raw frame, exceeds gRPC's 4 MB default).
  int max_receive_message_bytes = 256 << 20;
  // How session clients carry their messages (unary calls are unaffected).
  SessionTransport session_transport = SessionTransport::kAuto;
};

// How a lander's episode ended (wire codes of StepData.outcomes).
enum class LanderOutcome : uint8_t {
  kNone = 0,
  kLanded = 1,
  kCrashed = 2,
  kOutOfBounds = 3,
  kTruncated = 4,
  kAborted = 5,  // Terminated because another lander was damaged.
};

// "none", "landed", "crashed", "out_of_bounds", "truncated", "aborted".
absl::string_view LanderOutcomeName(LanderOutcome outcome);

// Element type of a space.
enum class ElementType { kUnspecified = 0, kFloat32, kUint8, kInt32 };

// A gymnasium space as the server describes it.
struct SpaceSpec {
  enum class Kind { kUnspecified = 0, kBox, kDiscrete };
  Kind kind = Kind::kUnspecified;
  ElementType dtype = ElementType::kUnspecified;
  // Shape of one element (empty for Discrete).
  std::vector<int> shape;
  // Box bounds per element (may be infinite).
  std::vector<double> low;
  std::vector<double> high;
  // Discrete: number of actions.
  int64_t n = 0;
};

// Options of a new environment (docs/environment.md). One optional member
// per option of MLL_ENV_OPTIONS (mll/core/env_config.h, the one definition
// of every option's type, name, default, range and help), e.g. n_landers
// (1..32, default 3), continuous, max_cycles, gravity, ... An unset member
// takes the server's default; the server validates every value
// (INVALID_ARGUMENT naming the field, the value and the range).
struct RemoteEnvConfig {
#define MLL_REMOTE_ENV_OPTION(type, name, default_value, range, help) \
  std::optional<type> name;
  MLL_ENV_OPTIONS(MLL_REMOTE_ENV_OPTION)
#undef MLL_REMOTE_ENV_OPTION
  // render_mode rgb_array (frames through Render) instead of none.
  bool render_rgb_array = false;
  // The step after an episode ends starts a new one instead of failing.
  bool auto_reset = false;
};

// An environment's resource as the server reports it.
struct EnvInfo {
  // `envs/{id}`.
  std::string name;
  // Every field filled in by the server.
  RemoteEnvConfig config;
  // `lander_0` .. `lander_{n-1}`.
  std::vector<std::string> possible_agents;
  SpaceSpec observation_space;
  SpaceSpec action_space;
  int render_fps = 0;
  bool episode_started = false;
  bool episode_over = false;
  int cycles = 0;
  int64_t episodes = 0;
  bool session_bound = false;
  // The server's --idle_timeout_s (0 from a server without KeepAlive): an
  // environment no call touches this long is destroyed. While a RemoteEnv
  // handle lives, a background thread of its client renews the lease every
  // third of it, so a paused program keeps its environments; a dead one
  // loses them after this long.
  double idle_timeout_s = 0;
  // Index of the server hosting the environment in the client's address
  // list (0 with one server).
  int server = 0;
  // The whole resource in protobuf's JSON mapping (field names as in the
  // proto), for logs and tools such as mll_cli.
  std::string json;

  int n_landers() const { return config.n_landers.value_or(0); }
  bool continuous() const { return config.continuous.value_or(false); }
};

inline constexpr int kRemoteObservationSize = 12;
inline constexpr int kRemoteContinuousActionSize = 2;

// The per-agent columns that a reset, a parallel step and an AEC step all
// report, indexed by agent.
struct AgentColumns {
  int n_landers = 0;
  // [n_landers * 12], row-major.
  std::vector<float> observations;
  std::vector<float> rewards;
  std::vector<uint8_t> terminations;
  std::vector<uint8_t> truncations;
  // Every agent's outcome so far (done agents included).
  std::vector<LanderOutcome> outcomes;
  // Every agent's return and length so far in this episode.
  std::vector<float> episode_returns;
  std::vector<int32_t> episode_lengths;

  absl::Span<const float> observation(int agent) const {
    return absl::MakeConstSpan(observations)
        .subspan(static_cast<size_t>(agent) * kRemoteObservationSize,
                 kRemoteObservationSize);
  }
};

// The result of a reset or a parallel step. Observation, reward and flag rows
// of agents not stepped (done before this step) are zero.
struct StepData : AgentColumns {
  // 1 when the agent was active at the start of the step (its row is valid).
  std::vector<uint8_t> stepped;
  bool episode_over = false;
  // auto_reset: the actions were ignored; this is the new episode's start.
  bool auto_reset = false;
  // Steps taken in the current episode.
  int cycles = 0;
  // Reset only: the seed used when the reset reseeded.
  std::optional<uint64_t> seed;

  // Not terminated and not truncated.
  bool active(int agent) const {
    return !terminations[agent] && !truncations[agent];
  }
};

// PettingZoo's last(): what agent_selection sees before it acts.
struct AecTurn {
  int agent = -1;
  absl::Span<const float> observation;
  float cumulative_reward = 0.0f;
  bool termination = false;
  bool truncation = false;
  LanderOutcome outcome = LanderOutcome::kNone;
  float episode_return = 0.0f;
  int32_t episode_length = 0;
  // A done agent must take a dead step (StepAgentDead).
  bool done() const { return termination || truncation; }
};

// The state a pettingzoo.AECEnv exposes, after a reset or an AEC step
// (`rewards` are PettingZoo's rewards of the latest step).
struct AecState : AgentColumns {
  // Agent indices still in the cycle (done ones until their dead step).
  std::vector<int> agents;
  // -1 when `agents` is empty.
  int agent_selection = -1;
  std::vector<float> cumulative_rewards;
  // The last live agent acted and the world stepped.
  bool world_stepped = false;

  // last() for `agent` (agent_selection by default); agent must be valid.
  AecTurn Last(int agent) const;
  AecTurn Last() const { return Last(agent_selection); }
};

// Encoding of a rendered frame.
enum class FrameFormat { kRgb, kPng };

// A rendered frame: raw RGB rows top to bottom ([height][width][3]) or PNG.
struct RenderedFrame {
  int width = 0;
  int height = 0;
  FrameFormat format = FrameFormat::kRgb;
  std::string data;
};

// The actions of one parallel step, a view. Set exactly the member matching
// the env's action space: `discrete` [n_landers] values 0..3, or `continuous`
// [n_landers * 2] row-major [main, lateral]. Entries of done agents are
// ignored by the server.
struct Actions {
  absl::Span<const int32_t> discrete;
  absl::Span<const float> continuous;

  static Actions Discrete(absl::Span<const int32_t> values) {
    return {values, {}};
  }
  static Actions Continuous(absl::Span<const float> values) {
    return {{}, values};
  }
};

// A handle to one environment on the server. Move-only. When it owns its
// environment, destroying it deletes the environment (errors are ignored
// there; call Delete() to see them). While it lives, the environment's lease
// is renewed (EnvInfo::idle_timeout_s), owned or not.
class RemoteEnv {
 public:
  RemoteEnv(RemoteEnv&& other) noexcept;
  RemoteEnv& operator=(RemoteEnv&& other) noexcept;
  RemoteEnv(const RemoteEnv&) = delete;
  RemoteEnv& operator=(const RemoteEnv&) = delete;
  ~RemoteEnv();

  const std::string& name() const { return info_.name; }
  // The resource as of creation (or the last Refresh()).
  const EnvInfo& info() const { return info_; }
  int n_landers() const { return info_.n_landers(); }
  bool continuous() const { return info_.continuous(); }
  // Index of the environment's server in its client's address list.
  int server() const { return info_.server; }
  // Whether destruction deletes the environment.
  bool owned() const { return owned_; }

  // Starts an episode; `seed` reseeds, absent continues the generator's
  // stream. Also starts the AEC view (aec()).
  absl::StatusOr<StepData> Reset(std::optional<uint64_t> seed = std::nullopt);
  // One parallel step.
  absl::StatusOr<StepData> Step(const Actions& actions);

  // AEC: the action of agent_selection (discrete or continuous), or a dead
  // step for a done agent. The client also tells the server which agent it
  // believes is agent_selection, so a stale view fails with
  // FAILED_PRECONDITION instead of acting for the wrong lander.
  absl::Status StepAgent(int32_t discrete_action);
  absl::Status StepAgent(std::array<float, kRemoteContinuousActionSize> action);
  absl::Status StepAgentDead();
  // The AEC view after the latest Reset or StepAgent on this handle.
  const AecState& aec() const { return aec_; }
  // PettingZoo's last() for agent_selection; FAILED_PRECONDITION before the
  // first Reset through this handle or when no agent is left.
  absl::StatusOr<AecTurn> Last() const;

  absl::StatusOr<RenderedFrame> Render(FrameFormat format = FrameFormat::kRgb);
  // GetEnv: re-reads the resource (episode state) into info().
  absl::StatusOr<EnvInfo> Refresh();
  // Deletes the environment now; the handle is then empty.
  absl::Status Delete();
  // Gives up ownership: destruction will not delete. Returns the name.
  std::string Release();

 private:
  friend class Client;
  RemoteEnv(std::shared_ptr<internal::Transport> transport, EnvInfo info,
            bool owned);
  // The action of one AEC step: none (dead step), discrete or continuous.
  struct AgentMove {
    enum class Kind { kDead, kDiscrete, kContinuous };
    Kind kind = Kind::kDead;
    int32_t discrete = 0;
    std::array<float, kRemoteContinuousActionSize> continuous = {0.0f, 0.0f};
  };
  absl::Status StepAgentImpl(const AgentMove& move);

  std::shared_ptr<internal::Transport> transport_;
  EnvInfo info_;
  bool owned_ = false;
  AecState aec_;
};

// One item of Client::StepBatch.
struct BatchStep {
  const RemoteEnv* env = nullptr;
  Actions actions;
};

// What a server is and offers (Client::GetServerInfo; the proto's
// ServerInfo, whose comments say more). A server that predates
// GetServerInfo is reported as protocol 1.0 with an empty server_version,
// no capabilities (unknown) and zero limits (unknown).
struct ServerInfo {
  // The mll_server release, e.g. "0.1.0".
  std::string server_version;
  // The wire protocol: mll.v<major>, minor raised by each addition.
  int protocol_major = 1;
  int protocol_minor = 0;
  // Optional features offered, e.g. "packed_step_batch", "keep_alive",
  // "shared_memory_sessions".
  std::vector<std::string> capabilities;
  // Limits (the server's flags); 0 where the server did not say.
  int max_envs = 0;
  int max_envs_per_token = 0;  // 0 also: unlimited (no tokens).
  int64_t max_message_bytes = 0;
  double idle_timeout_s = 0;
  int max_landers = 0;
  int threads = 0;
  int shared_memory_sessions = 0;
  // The answer in protobuf's JSON mapping (field names as in the proto),
  // for logs and tools such as `mll_cli info`.
  std::string json;

  bool has_capability(absl::string_view name) const;
};

class Client {
 public:
  // A client for the server at `address` ("host:port", or any gRPC target).
  // Connects lazily: an unreachable server shows as UNAVAILABLE on the first
  // call. INVALID_ARGUMENT for an empty address or bad options.
  static absl::StatusOr<Client> Create(absl::string_view address,
                                       const ClientOptions& options = {});
  // A client over several servers (see the top of this file), all with the
  // same options; server i is addresses[i]. INVALID_ARGUMENT when the list is
  // empty, an address is empty or appears twice.
  static absl::StatusOr<Client> Create(
      const std::vector<std::string>& addresses,
      const ClientOptions& options = {});

  Client(Client&&) noexcept;
  Client& operator=(Client&&) noexcept;
  ~Client();

  // A client with the same methods whose environment calls go over one
  // Session stream. Environments it creates die with the stream (when the
  // session client and all its handles are gone) unless created detached.
  absl::StatusOr<Client> OpenSession() const;
  bool is_session() const;

  // Number of servers, and the address of server `server`, which must be in
  // 0..server_count()-1 (as RemoteEnv::server() and EnvInfo::server are).
  int server_count() const { return static_cast<int>(transports_.size()); }
  const std::string& address(int server) const;

  // grpc.health.v1 Check of `service` ("" is the whole server) on every
  // server: OK when all are SERVING; else the first failure (UNAVAILABLE when
  // not SERVING), prefixed with its address when there are several servers.
  absl::Status CheckHealth(absl::string_view service = "") const;

  // Creates an environment on the next server in round-robin order (shared
  // by the threads using this client); the handle owns it. `detached`
  // matters on a session only: the env outlives the stream.
  absl::StatusOr<RemoteEnv> CreateEnv(const RemoteEnvConfig& config = {},
                                      bool detached = false) const;
  // Creates an environment on server `server`; INVALID_ARGUMENT when it is
  // not in 0..server_count()-1.
  absl::StatusOr<RemoteEnv> CreateEnvOn(int server,
                                        const RemoteEnvConfig& config = {},
                                        bool detached = false) const;
  // A handle to an existing environment that does not own it.
  absl::StatusOr<RemoteEnv> Attach(absl::string_view name) const;
  // With several servers, each is asked in order until one does not answer
  // NOT_FOUND; NOT_FOUND when none has the name.
  absl::StatusOr<EnvInfo> GetEnv(absl::string_view name) const;
  // Every environment of every server (server 0's first), following the
  // pages (always unary). A server's failure fails the whole list.
  absl::StatusOr<std::vector<EnvInfo>> ListEnvs() const;
  // Looks the name up as GetEnv does.
  absl::Status DeleteEnv(absl::string_view name) const;
  // One parallel step of many environments; results in `steps` order. Each
  // item goes to its handle's server, which must be one of this client's
  // (INVALID_ARGUMENT otherwise); each server gets one StepBatch call, all in
  // flight at once. Each item has its own status (errors of one env leave the
  // others); when a server's call fails (e.g. UNAVAILABLE), each of its items
  // carries that status, prefixed with the server's address when there are
  // several. The outer status fails on bad input, or when every server's
  // call failed (the first such status).
  absl::StatusOr<std::vector<absl::StatusOr<StepData>>> StepBatch(
      absl::Span<const BatchStep> steps) const;

  // Server information and compatibility (server_info.cc). The wire
  // protocol this client speaks: mll.v1 up to minor 2.
  static constexpr int kProtocolMajor = 1;
  static constexpr int kProtocolMinor = 2;
  // This library's release (the project's version), e.g. "0.1.0".
  static absl::string_view Version();
  // GetServerInfo of server `server` (INVALID_ARGUMENT when it is not in
  // 0..server_count()-1), asked once per connection and then remembered.
  // Needs the token as every call does. CreateEnv asks it first, and fails
  // with CheckCompatible's error on a server this client cannot use.
  absl::StatusOr<ServerInfo> GetServerInfo(int server = 0) const;
  // OK when this client can use the server `info` describes (at `address`,
  // named in errors) for features needing `capabilities`; else
  // FAILED_PRECONDITION naming both protocol versions, both releases and
  // what to upgrade: a protocol major other than kProtocolMajor, or a
  // capability missing from a server that lists its capabilities (protocol
  // 1.1 and later; a 1.0 server is given the benefit of the doubt).
  static absl::Status CheckCompatible(
      const ServerInfo& info, absl::string_view address,
      absl::Span<const absl::string_view> capabilities = {});

 private:
  friend class RemoteEnv;
  friend class VectorEnv;
  explicit Client(std::vector<std::shared_ptr<internal::Transport>> transports);
  absl::StatusOr<RemoteEnv> CreateEnvAt(size_t server,
                                        const RemoteEnvConfig& config,
                                        bool detached) const;
  // Index of the server whose transport `env` uses; INVALID_ARGUMENT naming
  // `what` when it is not a live handle or none of this client's servers has
  // its address.
  absl::StatusOr<size_t> ServerOf(const RemoteEnv* env,
                                  absl::string_view what) const;

  std::vector<std::shared_ptr<internal::Transport>> transports_;
  // Round-robin placement counter; on the heap because atomics cannot move.
  std::shared_ptr<std::atomic<uint64_t>> next_server_;
};

}  // namespace mll::client

#endif  // MLL_CLIENT_H_

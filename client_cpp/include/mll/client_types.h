// Plain types of the C++ client of the Multi Lunar Lander server
// (proto/mll/v1): how a client reaches its servers (ClientOptions), the
// options of a new environment (RemoteEnvConfig), what the server reports
// (EnvInfo, SpaceSpec, ServerInfo) and what a reset, step or render returns
// (StepData, AecState, RenderedFrame). mll/client.h's Client and RemoteEnv,
// and mll/vector_env.h's VectorEnv, take and return these.
//
// No protobuf or gRPC type appears here, and nothing of the simulation core:
// the option list and the observation size come from mll/env_spec.h, beside
// the wire contract.
//
// Everything here is in namespace mll::client.
#ifndef MLL_CLIENT_TYPES_H_
#define MLL_CLIENT_TYPES_H_

#include <chrono>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "absl/strings/string_view.h"
#include "absl/types/span.h"
#include "mll/env_spec.h"

namespace mll::client {

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
  // Deadline of each unary call; zero means step_timeout's.
  std::chrono::milliseconds call_timeout{0};
  // How long a server may take to answer a request before it counts as
  // stalled (stopped, frozen, or cut off with its connection open): every
  // request on a Session stream (session clients, VectorEnv), and every
  // unary call when call_timeout is zero. A StepBatch gets 1 ms more per
  // lander action it carries. A server that misses it fails the request with
  // DEADLINE_EXCEEDED naming the server and the timeout, and its Session
  // stream is cancelled (a late answer is never taken); VectorEnv then fails
  // its envs over (mll/vector_env.h). Zero: no deadline. The default is far
  // above a loaded server's slowest answers (docs/benchmarks.md, "Step
  // deadline").
  std::chrono::milliseconds step_timeout{5000};
  // Largest message the client accepts (a batch of many 32-lander envs, or a
  // raw frame, exceeds gRPC's 4 MB default).
  int max_receive_message_bytes = 256 << 20;
  // How session clients carry their messages (unary calls are unaffected).
  SessionTransport session_transport = SessionTransport::kAuto;
  // How often a VectorEnv resolves the names in its address list again
  // (mll/vector_env.h, "Discovery"), to find servers that joined a name and
  // those gone from it; zero: never (names are still resolved again at each
  // failover). Negative: Create fails INVALID_ARGUMENT.
  std::chrono::milliseconds rediscover_interval{10000};
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
// per option of MLL_ENV_OPTIONS (mll/env_spec.h, the one definition of
// every option's type, name, default, range and help), e.g. n_landers
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

// An agent's observation and continuous action sizes (mll/env_spec.h).
inline constexpr int kRemoteObservationSize = ::mll::kObservationSize;
inline constexpr int kRemoteContinuousActionSize = ::mll::kContinuousActionSize;

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
  // The server's load (protocol 1.3, capability "server_load"; all zero from
  // an older server): envs hosted now by all tenants, CPU used over the last
  // 10 s in cores, the cores it may use, and agent-steps per second. Placement
  // (mll/vector_env.h) puts new envs on the least-loaded servers by these.
  struct Load {
    int envs_hosted = 0;
    double cpu_cores = 0;
    double cores_available = 0;
    double agent_steps_per_s = 0;
  };
  Load load;
  // The answer in protobuf's JSON mapping (field names as in the proto),
  // for logs and tools such as `mll_cli info`.
  std::string json;

  bool has_capability(absl::string_view name) const;
};

}  // namespace mll::client

#endif  // MLL_CLIENT_TYPES_H_

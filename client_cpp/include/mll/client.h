// C++ client of the Multi Lunar Lander server (proto/mll/v1).
//
// A `Client` is made from an address; it creates environments on the server
// and hands back `RemoteEnv` handles, which delete their environment when
// destroyed unless released. Every call has a unary form; `Client::
// OpenSession()` returns a client whose calls travel over one bidirectional
// `Session` stream instead (the lowest latency), with the same methods.
//
// Several servers (scale-out): `Client::Create(addresses)` makes one client
// over a list of servers; a host name in it stands for every address it
// resolves to (discovery, below at Create). Each environment lives on one
// server for its life: CreateEnv places each on the least-loaded server
// (CreateEnvOn picks the server), and the handle's calls go to that server
// only. StepBatch splits a batch by server, sends one StepBatch per server, all
// in flight at once, and returns results in the caller's order. ListEnvs
// concatenates every server's list; GetEnv, Attach and DeleteEnv look a name up
// on each server in turn. A session client over several servers holds one
// stream per server.
//
// Security: `ClientOptions` selects TLS (root certificates, target name
// override) and a bearer token, which is sent on every call: unary calls,
// Session streams and health checks (a server with tokens answers health
// checks without one too).
//
// Results are plain C++ types (mll/client_types.h); no protobuf or gRPC type
// appears here. Errors are absl::Status values carrying the server's
// canonical code and message (INVALID_ARGUMENT, NOT_FOUND,
// FAILED_PRECONDITION, UNAVAILABLE, ...).
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
#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/types/span.h"
#include "mll/client_types.h"

namespace mll::client {

namespace internal {
class Transport;
}  // namespace internal

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

class Client {
 public:
  // A client for the server at `address` ("host:port", or any gRPC target).
  // A host that is a name stands for every address it resolves to (below).
  // Connects lazily: an unreachable server shows as UNAVAILABLE on the first
  // call. INVALID_ARGUMENT for an empty address or bad options.
  static absl::StatusOr<Client> Create(absl::string_view address,
                                       const ClientOptions& options = {});
  // A client over several servers (see the top of this file), all with the
  // same options. Each entry is "host:port" (an IPv6 host in brackets) or a
  // gRPC target with a scheme ("unix:PATH"). An IP literal or a target is
  // one server; a host name is every address it resolves to now
  // (getaddrinfo, IPv4 and IPv6; a Kubernetes headless Service's name is
  // its ready pods), each one server with its own channel, in entry order
  // and within an entry in address order; an address two entries yield is
  // one server. With TLS, their certificates are checked against the name
  // (unless tls_target_name_override). INVALID_ARGUMENT when the list is
  // empty, an entry is malformed or appears twice; UNAVAILABLE naming the
  // entry when a name resolves to no address. A plain Client keeps the
  // servers it found; a VectorEnv resolves the names again
  // (ClientOptions::rediscover_interval).
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

  // Creates an environment on the least-loaded server by what each reports
  // now (GetServerInfo's load: envs hosted against max_envs, then CPU use;
  // the rule of VectorEnv's placement), passing over a server that does not
  // answer (UNAVAILABLE) or refuses it (RESOURCE_EXHAUSTED: full, or the
  // token's quota there) for the next; the last such error, naming its
  // server, when none is left. The handle owns the env. `detached` matters on a
  // session only: the env outlives the stream.
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
  // protocol this client speaks: mll.v1 up to minor 3.
  static constexpr int kProtocolMajor = 1;
  static constexpr int kProtocolMinor = 3;
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
  // The address list as given (names unresolved) and the options: what a
  // VectorEnv resolves again to find servers that joined a name.
  std::vector<std::string> entries_;
  ClientOptions options_;
};

}  // namespace mll::client

#endif  // MLL_CLIENT_H_

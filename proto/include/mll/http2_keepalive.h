// HTTP/2 keepalive of every client channel, and the server's policy for the
// clients' pings, chosen together. A connection that carries nothing (an idle
// trainer, a lease renewer between renewals) is pinged by the client every
// kKeepaliveTimeMs; a server that does not acknowledge within
// kKeepaliveTimeoutMs (its host lost power or network) has the connection
// closed, so the next call opens a new one instead of waiting on a dead
// socket, and middleboxes do not drop the idle connection. The server accepts
// pings up to twice as often as clients send them, with or without calls in
// flight, so it never answers GOAWAY "too_many_pings". A stalled server with
// a request in flight is found sooner by the request's deadline
// (ClientOptions::step_timeout, step_timeout_s in Python).
//
// The Python client sets the same values on its grpcio channels
// (multi_lunar_lander/_channel.py, CHANNEL_OPTIONS).
#ifndef MLL_HTTP2_KEEPALIVE_H_
#define MLL_HTTP2_KEEPALIVE_H_

#include "grpc/grpc.h"

namespace mll {

// How often a client pings a connection, and how long it waits for the ack.
inline constexpr int kKeepaliveTimeMs = 20000;
inline constexpr int kKeepaliveTimeoutMs = 10000;
// The shortest interval between a client's pings the server accepts.
inline constexpr int kKeepaliveMinReceivedPingIntervalMs = 10000;
static_assert(kKeepaliveMinReceivedPingIntervalMs <= kKeepaliveTimeMs / 2,
              "the server must accept the clients' pings with room to spare");

// Calls set(name, value) for each channel argument of a client channel
// (grpc::ChannelArguments::SetInt).
template <typename SetIntArgument>
void SetClientKeepalive(SetIntArgument set) {
  set(GRPC_ARG_KEEPALIVE_TIME_MS, kKeepaliveTimeMs);
  set(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, kKeepaliveTimeoutMs);
  // Idle connections too: they are the ones nothing else checks.
  set(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  // No limit on pings without data in between (gRPC's default stops at 2).
  set(GRPC_ARG_HTTP2_MAX_PINGS_WITHOUT_DATA, 0);
}

// Calls set(name, value) for each channel argument of the server
// (grpc::ServerBuilder::AddChannelArgument).
template <typename SetIntArgument>
void SetServerKeepalivePolicy(SetIntArgument set) {
  set(GRPC_ARG_KEEPALIVE_PERMIT_WITHOUT_CALLS, 1);
  set(GRPC_ARG_HTTP2_MIN_RECV_PING_INTERVAL_WITHOUT_DATA_MS,
      kKeepaliveMinReceivedPingIntervalMs);
  set(GRPC_ARG_HTTP2_MAX_PINGS_WITHOUT_DATA, 0);
}

}  // namespace mll

#endif  // MLL_HTTP2_KEEPALIVE_H_

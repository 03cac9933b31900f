// HTTP/2 keepalive of every client channel, and the server's policy for the
// clients' pings, chosen together. A connection that carries nothing (an idle
// trainer, a lease renewer between renewals) is pinged by the client every
// kKeepaliveTimeMs, so middleboxes do not drop it and a dead peer ends it
// (TCP gives up on unacknowledged data; it never does on an idle socket).
// grpcio (the Python PettingZoo envs) reads its connections on a thread of
// its own and closes one whose ping is not acknowledged within
// kKeepaliveTimeoutMs (its server's host lost power or network), so the next
// call opens a new one instead of waiting on a dead socket. The C++ client
// (and the native library under the Python vector env) reads its connections
// only in the calling thread, while the caller waits for an answer: an ack
// can sit unread for as long as a trainer computes between StepAsync and
// StepWait, or between two steps, so its wait for the ack is
// kCallerReadKeepaliveTimeoutMs, in effect none, and a dead server is found by
// the next request's deadline (ClientOptions::step_timeout) instead. With a
// 10 s wait, two vector envs stepped in turn beside other work lost their
// connections with "keepalive watchdog timeout" about 40 s into a run. The
// server accepts pings up to twice as often as clients send them, with or
// without calls in flight, so it never answers GOAWAY "too_many_pings". A
// stalled server with a request in flight is found sooner by the request's
// deadline (ClientOptions::step_timeout, step_timeout_s in Python).
//
// The Python client sets the same values on its grpcio channels
// (multi_lunar_lander/_channel.py, CHANNEL_OPTIONS).
#ifndef MLL_HTTP2_KEEPALIVE_H_
#define MLL_HTTP2_KEEPALIVE_H_

#include "grpc/grpc.h"

namespace mll {

// How often a client pings a connection, and how long it waits for the ack.
inline constexpr int kKeepaliveTimeMs = 20000;
inline constexpr int kKeepaliveTimeoutMs = 10000;  // grpcio's channels.
inline constexpr int kCallerReadKeepaliveTimeoutMs =
    24 * 3600 * 1000;  // The C++ client's.

// The shortest interval between a client's pings the server accepts.
inline constexpr int kKeepaliveMinReceivedPingIntervalMs = 10000;
static_assert(kKeepaliveMinReceivedPingIntervalMs <= kKeepaliveTimeMs / 2,
              "the server must accept the clients' pings with room to spare");

// Calls set(name, value) for each channel argument of a C++ client channel
// (grpc::ChannelArguments::SetInt).
template <typename SetIntArgument>
void SetClientKeepalive(SetIntArgument set) {
  set(GRPC_ARG_KEEPALIVE_TIME_MS, kKeepaliveTimeMs);
  set(GRPC_ARG_KEEPALIVE_TIMEOUT_MS, kCallerReadKeepaliveTimeoutMs);
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

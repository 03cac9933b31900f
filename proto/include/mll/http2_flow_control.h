// HTTP/2 flow control of every channel of the server and the C++ clients.
// Async clients keep many large requests in flight over links with latency;
// a stream's window must then cover the link's bandwidth-delay product, or
// the sender stalls waiting for window updates. BDP probing (gRPC's default,
// set here on purpose) grows the windows to the measured product; the
// lookahead gives each stream a large window from its first message, before
// the first probe has measured anything.
#ifndef MLL_HTTP2_FLOW_CONTROL_H_
#define MLL_HTTP2_FLOW_CONTROL_H_

#include "grpc/grpc.h"

namespace mll {

// A stream's initial flow-control window: 8 MiB, a 64-env packed batch
// several hundred times over.
inline constexpr int kHttp2StreamLookaheadBytes = 8 << 20;

// Calls set(name, value) for each channel argument of the policy above
// (grpc::ChannelArguments::SetInt or grpc::ServerBuilder::AddChannelArgument).
template <typename SetIntArgument>
void SetHttp2FlowControl(SetIntArgument set) {
  set(GRPC_ARG_HTTP2_BDP_PROBE, 1);
  set(GRPC_ARG_HTTP2_STREAM_LOOKAHEAD_BYTES, kHttp2StreamLookaheadBytes);
}

}  // namespace mll

#endif  // MLL_HTTP2_FLOW_CONTROL_H_

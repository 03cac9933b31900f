// The RPCs of mll.v1.MultiLunarLander (proto/mll/v1/multi_lunar_lander.proto)
// as C++ sees them, one row each in the service's order: the one list that
// the server's metrics (the Method enum and kMethodCount, metrics.h), the
// server's Session dispatch (server/service/src/service.cc) and the C++
// client's unary transport (client_cpp/src/transport.cc) expand, so that a
// new RPC is one row here and they all follow.
//
//   MLL_RPCS(SESSION_OP, SESSION_BATCH_OP, NOT_A_SESSION_OP), whose rows are
//   SESSION_OP(method, request_member, rpc, response_member)   also a Session
//       operation, completed in the call
//   SESSION_BATCH_OP(method, request_member, rpc, response_member)
//       also a Session operation, completed on the worker pool (StepBatch)
//   NOT_A_SESSION_OP(method, rpc)   unary only, or the Session stream itself
//
// method           the enumerator: metrics' Method::kStepEnv, and the
//                  SessionRequest::OpCase of a Session operation (kStepEnv)
// request_member   the SessionRequest oneof member (step_env), whose message
//                  is the RPC's request
// rpc              the service method (StepEnv): the generated stub's method
//                  and the server's Dispatch method of that name
// response_member  the SessionResponse oneof member that carries the RPC's
//                  response message (step_env)
//
// A Session's attach_shared_memory is the Session's own (no RPC) and is not
// listed. tests/service/rpc_table_test.cc checks the rows against the proto's
// descriptors (names in order, field numbers, request and response types) and
// that every other SessionRequest member has a row.
#ifndef MLL_SESSION_OPS_H_
#define MLL_SESSION_OPS_H_

#define MLL_RPCS(SESSION_OP, SESSION_BATCH_OP, NOT_A_SESSION_OP)       \
  SESSION_OP(kCreateEnv, create_env, CreateEnv, env)                   \
  SESSION_OP(kGetEnv, get_env, GetEnv, env)                            \
  NOT_A_SESSION_OP(kListEnvs, ListEnvs)                                \
  SESSION_OP(kDeleteEnv, delete_env, DeleteEnv, delete_env)            \
  SESSION_OP(kResetEnv, reset_env, ResetEnv, reset_env)                \
  SESSION_OP(kStepEnv, step_env, StepEnv, step_env)                    \
  SESSION_OP(kStepAgent, step_agent, StepAgent, step_agent)            \
  SESSION_BATCH_OP(kStepBatch, step_batch, StepBatch, step_batch)      \
  SESSION_OP(kRenderEnv, render_env, RenderEnv, frame)                 \
  /* Each request of a Session stream counts as one call (metrics). */ \
  NOT_A_SESSION_OP(kSession, Session)                                  \
  NOT_A_SESSION_OP(kKeepAlive, KeepAlive)                              \
  NOT_A_SESSION_OP(kGetServerInfo, GetServerInfo)

// Expands to nothing: the rows a view of MLL_RPCS leaves out.
#define MLL_RPC_SKIP(...)

// X(method, request_member, rpc, response_member) for each Session operation
// that completes in the call, and for every Session operation.
#define MLL_SESSION_SYNC_OPS(X) MLL_RPCS(X, MLL_RPC_SKIP, MLL_RPC_SKIP)
#define MLL_SESSION_OPS(X) MLL_RPCS(X, X, MLL_RPC_SKIP)

#endif  // MLL_SESSION_OPS_H_

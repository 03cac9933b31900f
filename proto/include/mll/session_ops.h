// The Session operations that are also unary RPCs of mll.v1.MultiLunarLander
// (proto/mll/v1/multi_lunar_lander.proto), one row each: the one table that
// the server's Session dispatch (server/service/src/service.cc) and the C++
// client's unary transport (client_cpp/src/transport.cc) expand, so that both
// map a SessionRequest to its RPC the same way.
//
//   X(op_case, request_member, rpc, response_member)
//
// op_case          the SessionRequest::OpCase enumerator (kStepEnv)
// request_member   the SessionRequest oneof member (step_env), whose message
//                  is the RPC's request
// rpc              the service method (StepEnv): the generated stub's method
//                  and the server's Dispatch method of that name
// response_member  the SessionResponse oneof member that carries the RPC's
//                  response message (step_env)
//
// attach_shared_memory is the Session's own (no RPC) and is not listed.
// StepBatch completes on the worker pool; MLL_SESSION_SYNC_OPS are the rest,
// which complete in the call. tests/service/rpc_table_test.cc checks the rows
// against the proto's descriptors and that every other oneof member has one.
#ifndef MLL_SESSION_OPS_H_
#define MLL_SESSION_OPS_H_

#define MLL_SESSION_SYNC_OPS(X)                    \
  X(kCreateEnv, create_env, CreateEnv, env)        \
  X(kGetEnv, get_env, GetEnv, env)                 \
  X(kDeleteEnv, delete_env, DeleteEnv, delete_env) \
  X(kResetEnv, reset_env, ResetEnv, reset_env)     \
  X(kStepEnv, step_env, StepEnv, step_env)         \
  X(kStepAgent, step_agent, StepAgent, step_agent) \
  X(kRenderEnv, render_env, RenderEnv, frame)

#define MLL_SESSION_OPS(X) \
  MLL_SESSION_SYNC_OPS(X)  \
  X(kStepBatch, step_batch, StepBatch, step_batch)

#endif  // MLL_SESSION_OPS_H_

/* The C interface of the C++ client's VectorEnv (mll/vector_env.h), for the
 * Python client's vector env (client_py/multi_lunar_lander/vector.py loads it
 * with ctypes). Placement, the Session streams, batch handles, pipelined
 * send/recv, failover by replay and the snapshot format are the C++ client's
 * code: Python keeps only its conventions (spaces, infos, exceptions).
 *
 * A handle is used by one thread at a time. Return codes are gRPC status
 * codes (0 is OK); after a failure, mll_vector_env_message says why (the
 * server's message, or the client's naming the argument and what is allowed).
 *
 * Results: every call that produces results (reset, step, step_wait, recv)
 * keeps them in the handle until the next such call, and writes them in place
 * into the caller's buffers bound for its row count
 * (mll_vector_env_bind_results) before it returns; mll_vector_env_results
 * copies them on demand. The columns, their element types and shapes are
 * described by mll_vector_env_column_*: the caller derives its arrays from
 * that table instead of declaring them again. */
#ifndef MLL_CLIENT_NATIVE_VECTOR_C_API_H_
#define MLL_CLIENT_NATIVE_VECTOR_C_API_H_

#include <stddef.h>
#include <stdint.h>

#define MLL_NATIVE_API __attribute__((visibility("default")))

/* Values of `transport` (mll::client::SessionTransport): shared memory with a
 * server on this host where it grants it, else gRPC's stream; shared memory
 * or fail saying why not; gRPC's stream. */
#define MLL_NATIVE_TRANSPORT_AUTO 0
#define MLL_NATIVE_TRANSPORT_SHARED_MEMORY 1
#define MLL_NATIVE_TRANSPORT_NATIVE 2

/* Returned by mll_vector_env_step_wait and mll_vector_env_recv when their
 * timeout passed first. */
#define MLL_NATIVE_STREAM_PENDING (-1)

#ifdef __cplusplus
extern "C" {
#endif

typedef struct mll_vector_env mll_vector_env;

/* ------------------------------------------------------------ result columns
 * Column i (0 <= i < mll_vector_env_column_count()) is an array of
 * [rows] + (per_agent ? [n_landers] : []) + (width > 1 ? [width] : []) items
 * of the column's element type, C order. rows is the call's: num_envs after
 * reset and step_wait, batch_size after recv. */
MLL_NATIVE_API int mll_vector_env_column_count(void);
/* "observations", "rewards", "terminations", "truncations", "active",
 * "outcomes", "episode_returns", "episode_lengths", "auto_reset",
 * "episode_over", "env_ids": the names Python's results use. */
MLL_NATIVE_API const char* mll_vector_env_column_name(int column);
/* mll.v1.DType's values (proto/mll/v1): DTYPE_FLOAT32, DTYPE_UINT8,
 * DTYPE_INT32. */
MLL_NATIVE_API int mll_vector_env_column_dtype(int column);
/* 1: one entry per lander; 0: one per row. */
MLL_NATIVE_API int mll_vector_env_column_per_agent(int column);
/* Items per entry: the observation size (12) for observations, else 1. */
MLL_NATIVE_API int mll_vector_env_column_width(int column);

/* --------------------------------------------------------- life of a handle
 * `num_envs` new environments on the servers of `addresses` (comma-separated
 * host:port or unix:PATH; a host name stands for every address it resolves
 * to; placed by the servers' load, VectorEnv::Create), created on Session
 * streams of the handle's own (they die with it), with the options of
 * `config` (`config_size` bytes of a serialized mll.v1.EnvConfig; auto_reset
 * is forced on). `root_cert_pem` (`root_cert_size` bytes) turns TLS on with
 * those root certificates; NULL is plaintext. `server_name` (NULL or "": the
 * address's host) is the name the servers' certificates must carry. `token`
 * (NULL or "": none) is sent as `authorization: Bearer <token>`. `transport`:
 * MLL_NATIVE_TRANSPORT_*. `batch_size`: how many
 * envs recv returns (0: num_envs). `failover`: -1 unset (on with several
 * servers or a host name, off with one address), 0 off, 1 on.
 * `step_timeout_s`: how long a request in flight may wait for its answer
 * before its server counts as down (< 0: the C++ client's default; 0: no
 * deadline). `rediscover_interval_s`: how
 * often the host names in `addresses` are resolved again to find servers
 * that joined or left them (< 0: the C++ client's default, 10 s; 0: never;
 * ClientOptions::rediscover_interval).
 *
 * Never NULL: mll_vector_env_create_status says whether the envs were
 * created (0) or why not (the handle then holds nothing but the message, and
 * is freed as any other). */
MLL_NATIVE_API mll_vector_env* mll_vector_env_new(
    const char* addresses, const char* root_cert_pem, size_t root_cert_size,
    const char* server_name, const char* token, int transport,
    const char* config, size_t config_size, int num_envs, int batch_size,
    int failover, double step_timeout_s, double rediscover_interval_s);
MLL_NATIVE_API int mll_vector_env_create_status(const mll_vector_env* env);
/* The message of the last failed call (or of the failed creation). */
MLL_NATIVE_API const char* mll_vector_env_message(const mll_vector_env* env);
/* Deletes the envs (closing the streams) and frees the handle. */
MLL_NATIVE_API void mll_vector_env_free(mll_vector_env* env);

/* ------------------------------------------------------------- what it is */
MLL_NATIVE_API int mll_vector_env_num_envs(const mll_vector_env* env);
MLL_NATIVE_API int mll_vector_env_n_landers(const mll_vector_env* env);
MLL_NATIVE_API int mll_vector_env_continuous(const mll_vector_env* env);
MLL_NATIVE_API int mll_vector_env_batch_size(const mll_vector_env* env);
MLL_NATIVE_API int mll_vector_env_failover(const mll_vector_env* env);
MLL_NATIVE_API int mll_vector_env_failovers(const mll_vector_env* env);
/* Rebalancing events so far (VectorEnv::rebalances: envs moved onto a server
 * that joined). */
MLL_NATIVE_API int mll_vector_env_rebalances(const mll_vector_env* env);
/* The serialized mll.v1.Env of env 0 as its server created it (the config
 * with the server's defaults filled in, the spaces, possible_agents,
 * idle_timeout_s); valid while the handle lives. */
MLL_NATIVE_API int mll_vector_env_spec(const mll_vector_env* env,
                                       const char** data, size_t* size);
/* `envs/{id}` of env `index`, and the address of its server (valid until the
 * next call on the handle). NULL for an index out of range. */
MLL_NATIVE_API const char* mll_vector_env_name(const mll_vector_env* env,
                                               int index);
MLL_NATIVE_API const char* mll_vector_env_env_address(const mll_vector_env* env,
                                                      int index);
/* The servers the handle knows (those of `addresses`, a name's resolved, and
 * those that joined a name since), in server order: their count, each address,
 * and each one's mll.v1.ServerInfo (GetServerInfo's answer), serialized
 * (valid until the next call on the handle). */
MLL_NATIVE_API int mll_vector_env_server_count(const mll_vector_env* env);
MLL_NATIVE_API const char* mll_vector_env_server_address(
    const mll_vector_env* env, int server);
MLL_NATIVE_API int mll_vector_env_server_info(const mll_vector_env* env,
                                              int server, const char** data,
                                              size_t* size);
/* "shared_memory" or "native" (opening the streams if none is open). */
MLL_NATIVE_API const char* mll_vector_env_transport(mll_vector_env* env);
/* The failover events logged since the last call, one line each, joined by
 * '\n' ("" when none); valid until the next call on the handle. The handle
 * writes none of them to stderr: the caller logs them. */
MLL_NATIVE_API const char* mll_vector_env_take_events(mll_vector_env* env);
/* Binds `flag` (the caller's; NULL unbinds): the handle sets it to 1 when it
 * logs an event and take_events sets it to 0, so that a caller looks at it
 * instead of calling take_events after every call. */
MLL_NATIVE_API void mll_vector_env_bind_event_flag(mll_vector_env* env,
                                                   int32_t* flag);

/* ------------------------------------------------------------- operations
 * Actions: `count` items of int32 (discrete, [rows, n_landers]) or float32
 * (continuous, [rows, n_landers, 2]), `continuous` saying which.
 *
 * Waits: step_wait and recv wait at most `timeout_ms` (< 0: until done) and
 * return MLL_NATIVE_STREAM_PENDING when it passed first; the caller calls
 * them again (a caller that waits in slices handles its signals between
 * them). Nothing is lost or repeated by a PENDING return. */

/* Reset of every env; has_seed: seed s gives env i the seed s + i. */
MLL_NATIVE_API int mll_vector_env_reset(mll_vector_env* env, int has_seed,
                                        uint64_t seed);
/* One step of every env, sent at once; step_wait's results are its. */
MLL_NATIVE_API int mll_vector_env_step_async(mll_vector_env* env,
                                             const void* actions, size_t count,
                                             int continuous);
/* step_async then step_wait in one call: a step of every env and its
 * results. A PENDING return leaves the step in flight, for step_wait. */
MLL_NATIVE_API int mll_vector_env_step(mll_vector_env* env, const void* actions,
                                       size_t count, int continuous,
                                       int timeout_ms);
MLL_NATIVE_API int mll_vector_env_step_wait(mll_vector_env* env,
                                            int timeout_ms);
/* EnvPool's async API (VectorEnv::AsyncReset, Send, Recv). send's env_ids
 * are int64 (NumPy's and torch's index type, as recv's callers get them). */
MLL_NATIVE_API int mll_vector_env_async_reset(mll_vector_env* env, int has_seed,
                                              uint64_t seed);
MLL_NATIVE_API int mll_vector_env_send(mll_vector_env* env, const void* actions,
                                       size_t count, int continuous,
                                       const int64_t* env_ids,
                                       size_t env_count);
MLL_NATIVE_API int mll_vector_env_recv(mll_vector_env* env, int timeout_ms);
/* Envs with a step (or async_reset) in flight whose results recv has not
 * returned. */
MLL_NATIVE_API int mll_vector_env_in_flight(const mll_vector_env* env);

/* The latest results' row count, and copies of their columns into
 * `buffers` (one pointer per column, in column order, each large enough for
 * that many rows; a NULL pointer skips its column). */
MLL_NATIVE_API int mll_vector_env_rows(const mll_vector_env* env);
MLL_NATIVE_API void mll_vector_env_results(const mll_vector_env* env,
                                           void* const* buffers);
/* Binds `buffers` (as mll_vector_env_results takes them; the handle copies
 * the pointers, the memory stays the caller's and must outlive the binding)
 * to results of `rows` rows: from now on every call that completes with
 * results of that many rows (reset, step, step_wait: num_envs; recv:
 * batch_size) writes them there before it returns, so that the caller reads
 * them in place with no further call. NULL unbinds. A failed call writes
 * nothing. INVALID_ARGUMENT for rows other than num_envs and batch_size. */
MLL_NATIVE_API int mll_vector_env_bind_results(mll_vector_env* env, int rows,
                                               void* const* buffers);
/* Makes the results of `rows` rows go `*offset` bytes past each bound buffer,
 * `*offset` read afresh by every call that writes them (NULL: no offset, as
 * at first). A caller that hands out every call's results as arrays of their
 * own binds one large block once and moves the offset to a fresh slot of it
 * before each call: no copy and no call to rebind. The caller keeps each
 * buffer plus offset within its memory. INVALID_ARGUMENT for rows other than
 * num_envs and batch_size. */
MLL_NATIVE_API int mll_vector_env_bind_results_offset(mll_vector_env* env,
                                                      int rows,
                                                      const int64_t* offset);

/* ---------------------------------------------------------------- snapshots
 * Env `index`'s snapshot (VectorEnv::EnvSnapshot), valid until the next call
 * on the handle; and RestoreEnv, writing the env's observations (float32
 * [n_landers, 12]) into `observations`. */
MLL_NATIVE_API int mll_vector_env_snapshot(mll_vector_env* env, int index,
                                           const char** data, size_t* size);
MLL_NATIVE_API int mll_vector_env_restore(mll_vector_env* env, int index,
                                          const char* snapshot, size_t size,
                                          float* observations);

#ifdef __cplusplus
}
#endif

#endif /* MLL_CLIENT_NATIVE_VECTOR_C_API_H_ */

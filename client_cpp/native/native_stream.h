/* A C interface to one Session stream of mll_server, for the Python client's
 * vector environments (loaded with ctypes). It carries serialized
 * SessionRequest and SessionResponse messages, so it needs no protobuf: the
 * caller encodes and decodes them.
 *
 * One operation at a time: mll_native_stream_write starts sending a request
 * and returns without waiting for the server; mll_native_stream_read waits for
 * the answer. The stream opens on the first write; when it breaks, the read
 * returns the gRPC status and the next write opens a new stream. All waiting
 * happens in the calling thread (no thread is made), and a handle is used by
 * one thread at a time. */
#ifndef MLL_CLIENT_NATIVE_NATIVE_STREAM_H_
#define MLL_CLIENT_NATIVE_NATIVE_STREAM_H_

#include <stddef.h>
#include <stdint.h>

#define MLL_NATIVE_API __attribute__((visibility("default")))

#ifdef __cplusplus
extern "C" {
#endif

typedef struct mll_native_stream mll_native_stream;

/* A stream handle for the server at `address` (host:port or unix:PATH).
 * `root_cert_pem` (`root_cert_size` bytes) turns TLS on with those root
 * certificates; NULL is plaintext. `server_name` (NULL or "": the address's
 * host) is the name the server's certificate must carry. `token` (NULL or "":
 * none) is sent as `authorization: Bearer <token>`. Never NULL; bad settings
 * make the first write fail with INVALID_ARGUMENT. */
MLL_NATIVE_API mll_native_stream* mll_native_stream_open(
    const char* address, const char* root_cert_pem, size_t root_cert_size,
    const char* server_name, const char* token);

/* Starts sending `size` bytes of a serialized SessionRequest (copied).
 * Returns 0, or the gRPC status code of a stream that could not be opened
 * (then mll_native_stream_message says why, and no read is due). */
MLL_NATIVE_API int mll_native_stream_write(mll_native_stream* stream,
                                           const char* data, size_t size);

/* Returned by mll_native_stream_read when `timeout_ms` passed first. */
#define MLL_NATIVE_STREAM_PENDING (-1)

/* Waits for the answer to the last write, for at most `timeout_ms` (< 0:
 * until it comes): 0 with `*data` and `*size` set to the serialized
 * SessionResponse (valid until the next call on the handle), the gRPC status
 * code of the broken stream (the server's code and message; UNAVAILABLE when
 * the server ended the stream cleanly), or MLL_NATIVE_STREAM_PENDING, after
 * which the caller reads again (or closes the handle): a caller that waits in
 * slices can handle its signals between them. */
MLL_NATIVE_API int mll_native_stream_read(mll_native_stream* stream,
                                          const char** data, size_t* size,
                                          int timeout_ms);

/* The message of the last failed write or read. */
MLL_NATIVE_API const char* mll_native_stream_message(
    const mll_native_stream* stream);

/* Whether a stream is open (a write opens one; a broken one is forgotten). */
MLL_NATIVE_API int mll_native_stream_is_open(const mll_native_stream* stream);

/* Shared memory (mll/shared_memory_pipe.h), for a server on this host: once
 * the caller's attach_shared_memory request was answered on the open stream,
 * this maps the region of the answer (`path`, `size`, `nonce`), and from then
 * on writes and reads go through it (a read still returns the stream's
 * status if the session ends). Returns 0, or NOT_FOUND when the path is not
 * this session's region here (the server is on another host or in another
 * container: close the handle and use a new one without); the stream stays
 * as it was. A broken stream drops the region: the next stream starts
 * without. */
MLL_NATIVE_API int mll_native_stream_attach_shared_memory(
    mll_native_stream* stream, const char* path, uint64_t size, uint64_t nonce);

/* Cancels the open stream, if any, and frees the handle. */
MLL_NATIVE_API void mll_native_stream_close(mll_native_stream* stream);

#ifdef __cplusplus
}
#endif

#endif /* MLL_CLIENT_NATIVE_NATIVE_STREAM_H_ */

/* The C interface of the C++ client's Session stream (client_cpp/src/
 * session_stream.h), for the Python client, which loads it with ctypes
 * (client_py/multi_lunar_lander/_native.py). It carries serialized
 * SessionRequest and SessionResponse messages, so the caller needs no C++
 * types: the protocol itself (opening, shared memory, pipelining, a broken
 * stream's status) is the C++ client's code, the same in both languages.
 *
 * A handle is used by one thread at a time; all waiting happens in the
 * calling thread. Return codes are gRPC status codes (0 is OK); after a
 * failure, mll_native_stream_message says why. */
#ifndef MLL_CLIENT_NATIVE_SESSION_C_API_H_
#define MLL_CLIENT_NATIVE_SESSION_C_API_H_

#include <stddef.h>
#include <stdint.h>

#define MLL_NATIVE_API __attribute__((visibility("default")))

#ifdef __cplusplus
extern "C" {
#endif

typedef struct mll_native_stream mll_native_stream;

/* Values of `transport` (mll::client::SessionTransport). */
#define MLL_NATIVE_TRANSPORT_AUTO 0
#define MLL_NATIVE_TRANSPORT_SHARED_MEMORY 1
#define MLL_NATIVE_TRANSPORT_NATIVE 2

/* A stream handle for the server at `address` (host:port or unix:PATH).
 * `root_cert_pem` (`root_cert_size` bytes) turns TLS on with those root
 * certificates; NULL is plaintext. `server_name` (NULL or "": the address's
 * host) is the name the server's certificate must carry. `token` (NULL or "":
 * none) is sent as `authorization: Bearer <token>`. `transport` says whether
 * each stream asks for shared memory. Never NULL; bad settings make the first
 * open or write fail with INVALID_ARGUMENT. Nothing is opened yet. */
MLL_NATIVE_API mll_native_stream* mll_native_stream_new(
    const char* address, const char* root_cert_pem, size_t root_cert_size,
    const char* server_name, const char* token, int transport);

/* Opens a stream now if none is open (asking for shared memory as
 * `transport` says). Returns 0 or the code of the failure (with
 * MLL_NATIVE_TRANSPORT_SHARED_MEMORY, FAILED_PRECONDITION when shared memory
 * was refused or cannot be mapped here). */
MLL_NATIVE_API int mll_native_stream_open(mll_native_stream* stream);

/* Starts sending `size` bytes of a serialized SessionRequest (copied) and
 * returns without waiting for the server; several may be in flight. Opens a
 * stream when none is open. Returns 0, or the code of a stream that could not
 * be opened or broke (then no answer is due for this request). */
MLL_NATIVE_API int mll_native_stream_write(mll_native_stream* stream,
                                           const char* data, size_t size);

/* Returned by mll_native_stream_read when `timeout_ms` passed first. */
#define MLL_NATIVE_STREAM_PENDING (-1)

/* Waits, at most `timeout_ms` (< 0: until it comes), for the answer to the
 * oldest request in flight: 0 with `*data` and `*size` set to the serialized
 * SessionResponse (valid until the next call on the handle), the code of the
 * broken stream (the server's code and message; UNAVAILABLE when the server
 * ended the stream cleanly), or MLL_NATIVE_STREAM_PENDING, after which the
 * caller reads again (a caller that waits in slices can handle its signals
 * between them). */
MLL_NATIVE_API int mll_native_stream_read(mll_native_stream* stream,
                                          const char** data, size_t* size,
                                          int timeout_ms);

/* The message of the last failed call. */
MLL_NATIVE_API const char* mll_native_stream_message(
    const mll_native_stream* stream);

/* Whether a stream is open (a broken one is forgotten). */
MLL_NATIVE_API int mll_native_stream_is_open(const mll_native_stream* stream);

/* Whether the open stream passes its messages through shared memory. */
MLL_NATIVE_API int mll_native_stream_shared_memory_in_use(
    const mll_native_stream* stream);

/* Requests sent and not yet answered on the open stream. */
MLL_NATIVE_API int mll_native_stream_in_flight(const mll_native_stream* stream);

/* Cancels the open stream, if any, and frees the handle. */
MLL_NATIVE_API void mll_native_stream_free(mll_native_stream* stream);

#ifdef __cplusplus
}
#endif

#endif /* MLL_CLIENT_NATIVE_SESSION_C_API_H_ */

// What the C interface (vector_c_api.cc) needs beside the client: gRPC kept
// initialised, and the client options made from its C arguments.
#ifndef MLL_CLIENT_NATIVE_NATIVE_OPTIONS_H_
#define MLL_CLIENT_NATIVE_NATIVE_OPTIONS_H_

#include <stddef.h>

#include "absl/status/status.h"
#include "mll/client.h"

namespace mll::client::internal {

// Keeps gRPC initialised for the life of the process: without a reference
// of its own, freeing the last handle would shut gRPC down (joining its
// threads, a few hundred milliseconds) and the next would start it again.
void KeepGrpcInitialised();

// The options of mll_vector_env_new's arguments: `root_cert_pem`
// (`root_cert_size` bytes; NULL: plaintext) turns TLS on, `server_name` and
// `token` (NULL or "": none), `transport` (MLL_NATIVE_TRANSPORT_*), and the
// Python client's largest message.
ClientOptions NativeClientOptions(const char* root_cert_pem,
                                  size_t root_cert_size,
                                  const char* server_name, const char* token,
                                  int transport);

// The C interfaces' return code of `status`: its gRPC code.
inline int CodeOf(const absl::Status& status) {
  return static_cast<int>(status.code());
}

}  // namespace mll::client::internal

#endif  // MLL_CLIENT_NATIVE_NATIVE_OPTIONS_H_

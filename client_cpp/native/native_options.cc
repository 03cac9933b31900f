#include "native_options.h"

#include "grpc/grpc.h"
#include "vector_c_api.h"

namespace mll::client::internal {
namespace {

// The largest message either way, as the Python client's own channels.
constexpr int kMaxMessageBytes = 64 << 20;

}  // namespace

void KeepGrpcInitialised() {
  static const bool initialised = (grpc_init(), true);
  (void)initialised;
}

ClientOptions NativeClientOptions(const char* root_cert_pem,
                                  size_t root_cert_size,
                                  const char* server_name, const char* token,
                                  int transport) {
  ClientOptions options;
  options.use_tls = root_cert_pem != nullptr;
  if (options.use_tls) {
    options.tls_root_certificates.assign(root_cert_pem, root_cert_size);
  }
  if (server_name != nullptr) options.tls_target_name_override = server_name;
  if (token != nullptr) options.token = token;
  options.max_receive_message_bytes = kMaxMessageBytes;
  options.session_transport = SessionTransport::kNative;
  if (transport == MLL_NATIVE_TRANSPORT_AUTO) {
    options.session_transport = SessionTransport::kAuto;
  }
  if (transport == MLL_NATIVE_TRANSPORT_SHARED_MEMORY) {
    options.session_transport = SessionTransport::kSharedMemory;
  }
  return options;
}

}  // namespace mll::client::internal

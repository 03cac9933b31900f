#include "session_c_api.h"

#include <memory>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/time/time.h"
#include "channel.h"
#include "mll/client.h"
#include "native_options.h"
#include "session_stream.h"

namespace {

using ::mll::client::ClientOptions;
using ::mll::client::internal::CodeOf;
using ::mll::client::internal::SessionStream;

}  // namespace

struct mll_native_stream {
  std::unique_ptr<SessionStream> session;
};

extern "C" {

mll_native_stream* mll_native_stream_new(const char* address,
                                         const char* root_cert_pem,
                                         size_t root_cert_size,
                                         const char* server_name,
                                         const char* token, int transport) {
  mll::client::internal::KeepGrpcInitialised();
  const ClientOptions options = mll::client::internal::NativeClientOptions(
      root_cert_pem, root_cert_size, server_name, token, transport);
  return new mll_native_stream{std::make_unique<SessionStream>(
      mll::client::internal::OpenChannel(address, options), options.token,
      absl::StrCat("server ", address), options.session_transport)};
}

int mll_native_stream_open(mll_native_stream* stream) {
  return CodeOf(stream->session->Open());
}

int mll_native_stream_write(mll_native_stream* stream, const char* data,
                            size_t size) {
  return CodeOf(stream->session->SendBytes(absl::string_view(data, size)));
}

int mll_native_stream_read(mll_native_stream* stream, const char** data,
                           size_t* size, int timeout_ms) {
  absl::string_view response;
  const std::optional<absl::Status> status = stream->session->ReceiveBytes(
      &response, timeout_ms < 0 ? absl::InfiniteDuration()
                                : absl::Milliseconds(timeout_ms));
  if (!status.has_value()) return MLL_NATIVE_STREAM_PENDING;
  if (!status->ok()) return CodeOf(*status);
  *data = response.data();
  *size = response.size();
  return 0;
}

const char* mll_native_stream_message(const mll_native_stream* stream) {
  return stream->session->last_message().c_str();
}

int mll_native_stream_is_open(const mll_native_stream* stream) {
  return stream->session->is_open() ? 1 : 0;
}

int mll_native_stream_shared_memory_in_use(const mll_native_stream* stream) {
  return stream->session->shared_memory_in_use() ? 1 : 0;
}

int mll_native_stream_in_flight(const mll_native_stream* stream) {
  return stream->session->in_flight();
}

void mll_native_stream_free(mll_native_stream* stream) { delete stream; }

}  // extern "C"

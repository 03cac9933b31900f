// Shared helpers of the service tests: servers reachable in-process, action
// arrays, decoded result columns.
#ifndef MLL_TESTS_SERVICE_TEST_UTIL_H_
#define MLL_TESTS_SERVICE_TEST_UTIL_H_

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "grpcpp/grpcpp.h"
#include "mll/service/server.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"

namespace mll::service::testing {

// A server listening nowhere, with a stub on an in-process channel.
struct InProcess {
  explicit InProcess(ServiceOptions options = ServiceOptions(),
                     int max_message_mb = 64);
  // `options` as given, but listening on no gRPC address.
  explicit InProcess(ServerOptions options);
  std::unique_ptr<Server> server;
  std::unique_ptr<v1::MultiLunarLander::Stub> stub;
};

// A Session attached to shared memory, as a client on the server's host uses
// it (mll/shared_memory_pipe.h): Attach() sends attach_shared_memory on the
// stream and maps the answer's region; Call() then passes a request through
// the region and waits for the answer.
class SharedMemorySession {
 public:
  explicit SharedMemorySession(v1::MultiLunarLander::Stub& stub);
  ~SharedMemorySession();
  SharedMemorySession(const SharedMemorySession&) = delete;
  SharedMemorySession& operator=(const SharedMemorySession&) = delete;

  // The attach answer (its error when refused); maps the region on success.
  v1::SessionResponse Attach();
  // `request` (sequence set here) through the region; its answer, whose
  // sequence is checked. Waits at most 20 s (an empty, sequence-0 response
  // with a failed expectation when the server does not answer).
  v1::SessionResponse Call(v1::SessionRequest request);
  // Passes `size` raw bytes (not necessarily a SessionRequest, and `size` may
  // exceed what the region holds: only the first bytes that fit are copied).
  v1::SessionResponse CallRaw(const std::string& bytes, uint64_t size);
  // Cancels the stream: the session ends.
  void Cancel() { context_.TryCancel(); }
  grpc::ClientReaderWriter<v1::SessionRequest, v1::SessionResponse>& stream() {
    return *stream_;
  }

 private:
  grpc::ClientContext context_;
  std::unique_ptr<
      grpc::ClientReaderWriter<v1::SessionRequest, v1::SessionResponse>>
      stream_;
  void* region_ = nullptr;
  uint64_t bytes_ = 0;
  uint64_t sequence_ = 0;
};

// Adds `authorization: Bearer <token>` to the call's metadata.
void AddToken(const std::string& token, grpc::ClientContext* context);

v1::Array DiscreteActions(const std::vector<int32_t>& actions);
v1::Array ContinuousActions(const std::vector<float>& actions);

// A config with the given lander count and the other fields unset.
v1::CreateEnvRequest CreateRequest(int n_landers);

// Creates an env (asserting success) and returns its name.
std::string CreateEnv(v1::MultiLunarLander::Stub& stub,
                      const v1::CreateEnvRequest& request);

// Decoded columns of StepData, asserting their dtype and shape.
std::vector<float> Observations(const v1::StepData& data, int n);
std::vector<float> Rewards(const v1::StepData& data, int n);

// The columns that must be bit-identical across transports, as one string.
std::string ResultBits(const v1::StepData& data);

// A deterministic table of discrete actions: [cycle][agent], biased towards
// the main engine so that episodes last a while.
std::vector<std::vector<int32_t>> ActionTable(int cycles, int n_landers,
                                              uint32_t seed);

// Checks an HTTP listener of Server::Start (its address in options.*address,
// its bound port from server.*port, its flag `flag`): malformed addresses
// are INVALID_ARGUMENT naming the flag and the value, and a port in use is
// UNAVAILABLE naming the flag.
void ExpectListenerRefusesBadAndBusyAddresses(
    const std::string& flag, std::string ServerOptions::*address,
    int (Server::*port)() const);

}  // namespace mll::service::testing

#endif  // MLL_TESTS_SERVICE_TEST_UTIL_H_

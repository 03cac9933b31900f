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

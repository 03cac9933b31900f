// The real mll_server binary on 127.0.0.1:0 with --port_file, driven over
// TCP (and a Unix-domain socket): the service, the health service, and a
// clean exit on SIGTERM.
#include <signal.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <string>
#include <tuple>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/service/server_info.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

TEST(ServerBinaryTest, ServesOverTcpAndExitsCleanlyOnSigterm) {
  ServerProcess process({"--threads=2", "--idle_timeout_s=60"});
  const int port = process.WaitForPort();
  ASSERT_GT(port, 0);
  auto channel = grpc::CreateChannel("127.0.0.1:" + std::to_string(port),
                                     grpc::InsecureChannelCredentials());
  ASSERT_TRUE(channel->WaitForConnected(std::chrono::system_clock::now() +
                                        std::chrono::seconds(10)));
  auto stub = v1::MultiLunarLander::NewStub(channel);

  grpc::Status health_status;
  EXPECT_EQ(HealthCheck(channel, &health_status), std::string("\x08\x01", 2))
      << "want status SERVING";
  EXPECT_TRUE(health_status.ok()) << health_status.error_message();

  const std::string name = CreateEnv(*stub, CreateRequest(2));
  grpc::ClientContext reset_context;
  v1::ResetEnvRequest reset;
  reset.set_name(name);
  reset.set_seed(11);
  v1::ResetEnvResponse reset_response;
  ASSERT_TRUE(stub->ResetEnv(&reset_context, reset, &reset_response).ok());
  for (int i = 0; i < 10; ++i) {
    grpc::ClientContext context;
    v1::StepBatchRequest batch;
    batch.add_steps()->set_name(name);
    *batch.mutable_steps(0)->mutable_actions() = DiscreteActions({2, 2});
    v1::StepBatchResponse response;
    ASSERT_TRUE(stub->StepBatch(&context, batch, &response).ok());
    ASSERT_TRUE(response.results(0).has_data());
    EXPECT_EQ(response.results(0).data().cycles(), i + 1);
  }
  {
    grpc::ClientContext context;
    v1::StepEnvRequest step;
    step.set_name(name);
    *step.mutable_actions() = DiscreteActions({0});
    v1::StepEnvResponse response;
    const grpc::Status status = stub->StepEnv(&context, step, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
    EXPECT_THAT(status.error_message(),
                HasSubstr("actions: shape [1] does not match [2]"));
  }
  // An idle C++ client answers the server's GOAWAY only when its backup
  // poller runs (every 5 s), which would hold the shutdown until its grace
  // period ends; a client that is done closes its channel.
  stub.reset();
  channel.reset();
  EXPECT_EQ(process.SignalAndWait(SIGTERM), 0);
}

TEST(ServerBinaryTest, RejectsBadFlagsNamingThem) {
  auto [code, output] = RunServer("--address=127.0.0.1:0 --threads=0");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--threads: 0 is out of range"));
  std::tie(code, output) = RunServer("--address=127.0.0.1:0 --max_envs=-5");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--max_envs: -5"));
  std::tie(code, output) =
      RunServer("--address=127.0.0.1:0 --shutdown_grace_s=0");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--shutdown_grace_s: 0 is out of range"));
  std::tie(code, output) = RunServer("--address=127.0.0.1:0 --parent_pid=-3");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--parent_pid: -3 is out of range"));
#ifdef __linux__
  // Pid 1 is not the parent of the shell that RunServer starts the server in.
  std::tie(code, output) = RunServer("--address=127.0.0.1:0 --parent_pid=1");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--parent_pid=1 has already exited"));
#endif
  std::tie(code, output) = RunServer("--address=not-an-address");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output,
              HasSubstr("--address: \"not-an-address\" is not host:port"));
}

// Exit code 1 and exactly one line, which names `flag` and `address`.
void ExpectOneLineRefusal(const std::string& flags, const std::string& flag,
                          const std::string& address) {
  auto [code, output] = RunServer(flags);
  EXPECT_EQ(code, 1) << flags;
  EXPECT_EQ(std::count(output.begin(), output.end(), '\n'), 1)
      << flags << ": " << output;
  EXPECT_THAT(output, HasSubstr(flag + ": ")) << flags;
  EXPECT_THAT(output, HasSubstr(address)) << flags;
}

TEST(ServerBinaryTest, RefusesABusyPortInsteadOfSharingIt) {
  ServerProcess first({});
  const int port = first.WaitForPort();
  ASSERT_GT(port, 0);
  const std::string busy = "127.0.0.1:" + std::to_string(port);
  ExpectOneLineRefusal("--address=" + busy, "--address",
                       "cannot listen on " + busy);
  // The metrics listener refuses it as well.
  ExpectOneLineRefusal("--address=127.0.0.1:0 --metrics_address=" + busy,
                       "--metrics_address", "cannot listen on " + busy);
  EXPECT_EQ(first.SignalAndWait(SIGTERM), 0);
}

TEST(ServerBinaryTest, RefusesMalformedAndOutOfRangePorts) {
  for (const std::string address :
       {"127.0.0.1:99999", "127.0.0.1:65536", "abc", "127.0.0.1",
        "127.0.0.1:", ":50051", "127.0.0.1:-1", "127.0.0.1:5x", "::1:50051"}) {
    ExpectOneLineRefusal("--address=" + address, "--address",
                         "\"" + address + "\" is not host:port");
    ExpectOneLineRefusal("--address=127.0.0.1:0 --metrics_address=" + address,
                         "--metrics_address",
                         "\"" + address + "\" is not host:port");
  }
}

// --address=unix:PATH: the service over a Unix-domain socket (what an
// embedded server listens on), a second server refused on the same socket
// rather than taking its path, and malformed unix: addresses refused.
TEST(ServerBinaryTest, ServesOnAUnixSocketAndRefusesABusyOne) {
  const std::string dir =
      ::testing::TempDir() + "mll_unix_" + std::to_string(getpid());
  ASSERT_EQ(mkdir(dir.c_str(), 0700), 0) << dir;
  const std::string address = "unix:" + dir + "/mll.sock";
  {
    ServerProcess process({"--address=" + address, "--threads=2"});
    auto channel =
        grpc::CreateChannel(address, grpc::InsecureChannelCredentials());
    ASSERT_TRUE(channel->WaitForConnected(std::chrono::system_clock::now() +
                                          std::chrono::seconds(20)));
    grpc::Status health_status;
    EXPECT_EQ(HealthCheck(channel, &health_status), std::string("\x08\x01", 2))
        << "want status SERVING";
    auto stub = v1::MultiLunarLander::NewStub(channel);
    const std::string name = CreateEnv(*stub, CreateRequest(2));
    grpc::ClientContext reset_context;
    v1::ResetEnvRequest reset;
    reset.set_name(name);
    v1::ResetEnvResponse reset_response;
    ASSERT_TRUE(stub->ResetEnv(&reset_context, reset, &reset_response).ok());
    grpc::ClientContext context;
    v1::StepBatchRequest batch;
    batch.add_steps()->set_name(name);
    *batch.mutable_steps(0)->mutable_actions() = DiscreteActions({2, 2});
    v1::StepBatchResponse response;
    ASSERT_TRUE(stub->StepBatch(&context, batch, &response).ok());
    EXPECT_EQ(response.results(0).data().cycles(), 1);

    ExpectOneLineRefusal("--address=" + address, "--address",
                         "cannot listen on " + address + " (in use");
    // The socket is still the first server's: a new connection reaches it.
    auto again =
        grpc::CreateChannel(address, grpc::InsecureChannelCredentials());
    EXPECT_EQ(HealthCheck(again, &health_status), std::string("\x08\x01", 2));
    again.reset();
    stub.reset();
    channel.reset();
    EXPECT_EQ(process.SignalAndWait(SIGTERM), 0);
  }
  ExpectOneLineRefusal("--address=unix:" + dir + "/missing/mll.sock",
                       "--address", "its directory is missing");
  ExpectOneLineRefusal("--address=unix:", "--address",
                       "\"unix:\" has a socket path of 0 bytes");
  const std::string too_long = "unix:/" + std::string(107, 'x');
  ExpectOneLineRefusal("--address=" + too_long, "--address",
                       "socket path of 108 bytes (allowed: unix:PATH with "
                       "1..107 bytes");
  // The HTTP listeners take host:port only.
  ExpectOneLineRefusal("--address=127.0.0.1:0 --metrics_address=" + address,
                       "--metrics_address",
                       "\"" + address + "\" is not host:port");
  std::remove((dir + "/mll.sock").c_str());
  rmdir(dir.c_str());
}

TEST(ServerBinaryTest, PositionalArgumentsAreAUsageError) {
  for (const std::string argument : {"extra", "127.0.0.1:50051"}) {
    auto [code, output] = RunServer("--address=127.0.0.1:0 " + argument);
    EXPECT_EQ(code, 2) << argument;
    EXPECT_EQ(std::count(output.begin(), output.end(), '\n'), 1) << output;
    EXPECT_THAT(output, HasSubstr("takes flags only"));
    EXPECT_THAT(output, HasSubstr("\"" + argument + "\""));
  }
}

TEST(ServerBinaryTest, HelpListsEveryFlagAndExitsZero) {
  const auto [code, output] = RunServer("--help");
  EXPECT_EQ(code, 0);
  // No build paths: flags are listed by name, not by the file defining them.
  EXPECT_THAT(output, Not(HasSubstr(".cc")));
  for (const char* flag :
       {"--address", "--port_file", "--threads", "--max_envs",
        "--max_envs_per_token", "--idle_timeout_s", "--max_message_mb",
        "--tls_cert", "--tls_key", "--auth_token_file", "--metrics_address",
        "--shutdown_grace_s", "--parent_pid"}) {
    EXPECT_THAT(output, HasSubstr(flag));
  }
}

// The project's version, as GetServerInfo's server_version (and the Python
// package's: scripts/wheel_smoke.py checks the installed wheel).
TEST(ServerBinaryTest, VersionIsGetServerInfosAndExitsZero) {
  const auto [code, output] = RunServer("--version");
  EXPECT_EQ(code, 0);
  EXPECT_EQ(output, "mll_server " + std::string(ServerVersion()) + "\n");
}

}  // namespace
}  // namespace mll::service::testing

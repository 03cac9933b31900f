// The real mll_server binary on 127.0.0.1:0 with --port_file, driven over
// TCP: the service, the health service, and a clean exit on SIGTERM.
#include <signal.h>
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <fstream>
#include <string>
#include <thread>
#include <tuple>
#include <utility>
#include <vector>

#include "gmock/gmock.h"
#include "grpcpp/generic/generic_stub.h"
#include "gtest/gtest.h"
#include "test_util.h"

extern char** environ;

namespace mll::testing {
namespace {

using ::testing::HasSubstr;

constexpr char kServerPath[] = MLL_SERVER_PATH;

class ServerProcess {
 public:
  explicit ServerProcess(std::vector<std::string> flags) {
    port_file_ = ::testing::TempDir() + "mll_server_port_" +
                 std::to_string(getpid());
    std::remove(port_file_.c_str());
    std::vector<std::string> args = {kServerPath, "--address=127.0.0.1:0",
                                     "--port_file=" + port_file_};
    args.insert(args.end(), flags.begin(), flags.end());
    std::vector<char*> argv;
    for (std::string& arg : args) argv.push_back(arg.data());
    argv.push_back(nullptr);
    EXPECT_EQ(posix_spawn(&pid_, kServerPath, nullptr, nullptr, argv.data(),
                          environ),
              0);
  }

  ~ServerProcess() {
    if (pid_ > 0) {
      kill(pid_, SIGKILL);
      waitpid(pid_, nullptr, 0);
    }
    std::remove(port_file_.c_str());
  }

  // The port from --port_file, polled for at most 20 s; 0 on timeout.
  int WaitForPort() {
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (std::chrono::steady_clock::now() < end) {
      std::ifstream in(port_file_);
      int port = 0;
      if (in >> port && port > 0) return port;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return 0;
  }

  // Sends `signal` and returns the exit status, or -1 if the process did not
  // exit within 15 s.
  int SignalAndWait(int signal) {
    kill(pid_, signal);
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(15);
    while (std::chrono::steady_clock::now() < end) {
      int status = 0;
      if (waitpid(pid_, &status, WNOHANG) == pid_) {
        pid_ = -1;
        return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
      }
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    return -1;
  }

 private:
  pid_t pid_ = -1;
  std::string port_file_;
};

// grpc.health.v1.Health/Check for the whole server, as raw protobuf bytes
// (the health proto's C++ stubs are not part of Debian's gRPC).
std::string HealthCheck(const std::shared_ptr<grpc::Channel>& channel,
                        grpc::Status* status) {
  grpc::GenericStub generic(channel);
  grpc::CompletionQueue queue;
  grpc::ClientContext context;
  context.set_deadline(std::chrono::system_clock::now() +
                       std::chrono::seconds(10));
  grpc::Slice empty("");
  grpc::ByteBuffer request(&empty, 1);  // HealthCheckRequest{service: ""}.
  auto call = generic.PrepareUnaryCall(&context, "/grpc.health.v1.Health/Check",
                                       request, &queue);
  call->StartCall();
  grpc::ByteBuffer response;
  call->Finish(&response, status, reinterpret_cast<void*>(1));
  void* tag = nullptr;
  bool ok = false;
  EXPECT_TRUE(queue.Next(&tag, &ok));
  std::vector<grpc::Slice> slices;
  std::string bytes;
  if (status->ok() && response.Dump(&slices).ok()) {
    for (const grpc::Slice& slice : slices) {
      bytes.append(reinterpret_cast<const char*>(slice.begin()), slice.size());
    }
  }
  queue.Shutdown();
  while (queue.Next(&tag, &ok)) {
  }
  return bytes;
}

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

// Runs the binary with `flags` to completion; its exit code and output.
std::pair<int, std::string> RunServer(const std::string& flags) {
  FILE* pipe =
      popen((std::string(kServerPath) + " " + flags + " 2>&1").c_str(), "r");
  EXPECT_NE(pipe, nullptr);
  std::string output;
  char buffer[4096];
  size_t read = 0;
  while ((read = fread(buffer, 1, sizeof(buffer), pipe)) > 0) {
    output.append(buffer, read);
  }
  const int status = pclose(pipe);
  return {WIFEXITED(status) ? WEXITSTATUS(status) : -1, output};
}

TEST(ServerBinaryTest, RejectsBadFlagsNamingThem) {
  auto [code, output] = RunServer("--address=127.0.0.1:0 --threads=0");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--threads: 0 is out of range"));
  std::tie(code, output) = RunServer("--address=127.0.0.1:0 --max_envs=-5");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--max_envs: -5"));
  std::tie(code, output) = RunServer("--address=not-an-address");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr("--address: cannot listen on not-an-address"));
}

TEST(ServerBinaryTest, HelpListsEveryFlag) {
  const std::string output = RunServer("--help").second;
  for (const char* flag : {"--address", "--port_file", "--threads",
                           "--max_envs", "--idle_timeout_s",
                           "--max_message_mb"}) {
    EXPECT_THAT(output, HasSubstr(flag));
  }
}

}  // namespace
}  // namespace mll::testing

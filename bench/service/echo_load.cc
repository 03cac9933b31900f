// The transport floor of bench/service/bench_server_cpu.py: a bare gRPC
// stream carrying the bytes of a Session's StepBatch, request and answer, with
// the same callback-API reactor shape as the Session.
//
//   mll_echo_load --serve --port_file=F [--work_us=U]
//     serves echo.proto's Echo on 127.0.0.1 (an OS-chosen port, written to
//     F); each answer first spins for U us (the physics a real call would
//     run). Each line read on stdin is answered with the stream messages
//     answered so far and the CPU seconds their spins took; it stops at the
//     end of stdin.
//   mll_echo_load --load=ADDRESS --clients=C --seconds=S --request_bytes=Q
//       --response_bytes=R [--client_work_us=W]
//     C clients, each on a connection of its own, each a ping-pong stream of
//     Q-byte requests asking for R-byte answers, for S seconds, spinning for
//     W us after each answer (what a client does with it);
//     prints one JSON line with the calls made.
#include <atomic>
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iostream>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "echo.grpc.pb.h"
#include "echo_service.h"
#include "grpcpp/grpcpp.h"

ABSL_FLAG(bool, serve, false, "Serve the echo stream (see the file's header).");
ABSL_FLAG(std::string, port_file, "", "With --serve: where the port goes.");
ABSL_FLAG(int64_t, work_us, 0,
          "With --serve: how long each answer spins first, >= 0.");
ABSL_FLAG(std::string, load, "", "host:port of an echo server to load.");
ABSL_FLAG(int, clients, 8, "With --load: concurrent streams, >= 1.");
ABSL_FLAG(double, seconds, 8.0, "With --load: how long, > 0.");
ABSL_FLAG(int, request_bytes, 300, "With --load: payload of each request.");
ABSL_FLAG(int, response_bytes, 4000, "With --load: payload of each answer.");
ABSL_FLAG(int64_t, client_work_us, 0,
          "With --load: how long each client spins after each answer, >= 0.");

namespace mll::bench {
namespace {

int Serve() {
  const int64_t work_us = absl::GetFlag(FLAGS_work_us);
  if (work_us < 0 || absl::GetFlag(FLAGS_port_file).empty()) {
    std::fprintf(stderr, "--serve needs --port_file and --work_us >= 0\n");
    return 2;
  }
  EchoService service(work_us);
  int port = 0;
  grpc::ServerBuilder builder;
  builder.AddListeningPort("127.0.0.1:0", grpc::InsecureServerCredentials(),
                           &port);
  builder.RegisterService(&service);
  std::unique_ptr<grpc::Server> server = builder.BuildAndStart();
  if (server == nullptr || port == 0) {
    std::fprintf(stderr, "cannot listen on 127.0.0.1\n");
    return 1;
  }
  std::ofstream(absl::GetFlag(FLAGS_port_file)) << port << "\n";
  for (std::string line; std::getline(std::cin, line);) {
    std::cout << service.answered() << " " << service.work_cpu_ns() * 1e-9
              << std::endl;
  }
  server->Shutdown(std::chrono::system_clock::now() + std::chrono::seconds(1));
  return 0;
}

int Load() {
  const int clients = absl::GetFlag(FLAGS_clients);
  const double seconds = absl::GetFlag(FLAGS_seconds);
  const int64_t client_work_us = absl::GetFlag(FLAGS_client_work_us);
  const int request_bytes = absl::GetFlag(FLAGS_request_bytes);
  const int response_bytes = absl::GetFlag(FLAGS_response_bytes);
  if (clients < 1 || !(seconds > 0) || client_work_us < 0 ||
      request_bytes < 0 || response_bytes < 0) {
    std::fprintf(stderr,
                 "--load needs --clients >= 1, --seconds > 0, and "
                 "--client_work_us, --request_bytes and --response_bytes "
                 ">= 0\n");
    return 2;
  }
  EchoRequest request;
  request.mutable_payload()->assign(request_bytes, 'r');
  request.set_response_size(response_bytes);
  const auto deadline =
      std::chrono::steady_clock::now() +
      std::chrono::duration_cast<std::chrono::steady_clock::duration>(
          std::chrono::duration<double>(seconds));
  std::atomic<int64_t> calls{0};
  std::atomic<bool> failed{false};
  std::vector<std::thread> threads;
  for (int c = 0; c < clients; ++c) {
    threads.emplace_back([&, c] {
      grpc::ChannelArguments arguments;
      arguments.SetInt("mll.bench.client", c);  // A connection of its own.
      std::unique_ptr<Echo::Stub> stub =
          Echo::NewStub(grpc::CreateCustomChannel(
              absl::GetFlag(FLAGS_load), grpc::InsecureChannelCredentials(),
              arguments));
      grpc::ClientContext context;
      context.set_deadline(
          std::chrono::system_clock::now() +
          std::chrono::seconds(static_cast<int>(seconds) + 10));
      auto stream = stub->Stream(&context);
      EchoResponse response;
      int64_t made = 0;
      while (std::chrono::steady_clock::now() < deadline) {
        if (!stream->Write(request) || !stream->Read(&response)) {
          failed = true;
          break;
        }
        ++made;
        SpinFor(client_work_us);
      }
      stream->WritesDone();
      stream->Finish().IgnoreError();
      calls += made;
    });
  }
  for (std::thread& thread : threads) thread.join();
  if (failed) {
    std::fprintf(stderr, "an echo stream failed\n");
    return 1;
  }
  std::printf("{\"calls\": %lld}\n", static_cast<long long>(calls.load()));
  return 0;
}

}  // namespace
}  // namespace mll::bench

int main(int argc, char** argv) {
  absl::ParseCommandLine(argc, argv);
  if (absl::GetFlag(FLAGS_serve)) return mll::bench::Serve();
  if (!absl::GetFlag(FLAGS_load).empty()) return mll::bench::Load();
  std::fprintf(stderr, "mll_echo_load: --serve or --load=ADDRESS\n");
  return 2;
}

// The web dashboard (--http_address) through a real server and cpp-httplib's
// client on loopback: the page, the env list (and what each token sees), the
// frame stream, its errors, and that viewers neither change a trajectory nor
// leave work behind.
#include "mll/service/dashboard.h"

#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <set>
#include <string>
#include <thread>
#include <tuple>
#include <vector>

#include "absl/strings/escaping.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "httplib.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::HasSubstr;
using ::testing::Not;

constexpr char kPngSignature[] = "\x89PNG\r\n\x1a\n";

ServerOptions Options(std::vector<std::string> tokens = {}) {
  ServerOptions options;
  options.http_address = "127.0.0.1:0";
  options.service.threads = 2;
  options.service.auth_tokens = std::move(tokens);
  return options;
}

httplib::Client Client(const InProcess& s) {
  httplib::Client http("127.0.0.1", s.server->http_port());
  http.set_connection_timeout(5);
  http.set_read_timeout(5);
  return http;
}

void Reset(InProcess& s, const std::string& name, uint64_t seed,
           const std::string& token = "") {
  grpc::ClientContext context;
  if (!token.empty()) AddToken(token, &context);
  v1::ResetEnvRequest request;
  request.set_name(name);
  request.set_seed(seed);
  v1::ResetEnvResponse response;
  ASSERT_TRUE(s.stub->ResetEnv(&context, request, &response).ok());
}

v1::StepData Step(InProcess& s, const std::string& name,
                  const std::vector<int32_t>& actions) {
  grpc::ClientContext context;
  v1::StepEnvRequest request;
  request.set_name(name);
  *request.mutable_actions() = DiscreteActions(actions);
  v1::StepEnvResponse response;
  const grpc::Status status = s.stub->StepEnv(&context, request, &response);
  EXPECT_TRUE(status.ok()) << status.error_message();
  return response.data();
}

// The frames of one stream: each event's id and PNG, as a viewer sees them.
struct Viewer {
  std::vector<std::string> ids;
  std::vector<std::string> pngs;
  bool gone = false;
  std::string buffer;

  // Parses complete events out of `data`.
  void Feed(const char* data, size_t size) {
    buffer.append(data, size);
    size_t end;
    while ((end = buffer.find("\n\n")) != std::string::npos) {
      const std::string event = buffer.substr(0, end);
      buffer.erase(0, end + 2);
      if (event.rfind("event: gone", 0) == 0) gone = true;
      if (event.rfind("event: frame", 0) != 0) continue;
      const size_t id = event.find("\nid: ");
      const size_t payload = event.find("\ndata: ");
      ids.push_back(event.substr(id + 5, payload - id - 5));
      std::string png;
      EXPECT_TRUE(absl::Base64Unescape(event.substr(payload + 7), &png));
      pngs.push_back(png);
    }
  }
};

// Watches `name` until `stop` returns true (checked after every chunk), then
// closes the connection.
httplib::Result Watch(const InProcess& s, const std::string& name,
                      Viewer* viewer, const std::function<bool()>& stop,
                      const httplib::Headers& headers = {}) {
  httplib::Client http = Client(s);
  return http.Get(absl::StrCat("/api/frames?name=", name).c_str(), headers,
                  [viewer, &stop](const char* data, size_t size) {
                    viewer->Feed(data, size);
                    return !stop();
                  });
}

bool WaitFor(const std::function<bool()>& condition,
             std::chrono::seconds timeout = std::chrono::seconds(10)) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  while (!condition()) {
    if (std::chrono::steady_clock::now() > deadline) return false;
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return true;
}

TEST(DashboardTest, ServesThePageAndListsTheHostedEnvs) {
  InProcess s(Options());
  ASSERT_GT(s.server->http_port(), 0);
  httplib::Client http = Client(s);
  httplib::Result page = http.Get("/");
  ASSERT_TRUE(page) << httplib::to_string(page.error());
  EXPECT_EQ(page->status, 200);
  EXPECT_THAT(page->get_header_value("Content-Type"), HasSubstr("text/html"));
  EXPECT_THAT(page->body, HasSubstr("EventSource"));

  httplib::Result empty = http.Get("/api/envs");
  ASSERT_TRUE(empty);
  EXPECT_EQ(empty->body, "{\"envs\":[],\"auth\":false}");

  const std::string name = CreateEnv(*s.stub, CreateRequest(2));
  const std::string fresh = CreateEnv(*s.stub, CreateRequest(3));
  Reset(s, name, 1);
  for (int i = 0; i < 5; ++i) Step(s, name, {0, 0});
  httplib::Result list = http.Get("/api/envs");
  ASSERT_TRUE(list);
  EXPECT_EQ(list->status, 200);
  EXPECT_THAT(list->body,
              HasSubstr(absl::StrCat("{\"name\":\"", name,
                                     "\",\"landers\":2,\"continuous\":false,"
                                     "\"episode\":1,\"step\":5,\"active\":2,"
                                     "\"returns\":[")));
  EXPECT_THAT(list->body, HasSubstr("\"outcomes\":[\"none\",\"none\"]"));
  EXPECT_THAT(list->body,
              HasSubstr(absl::StrCat("{\"name\":\"", fresh,
                                     "\",\"landers\":3,\"continuous\":false,"
                                     "\"episode\":0,\"step\":0")));
}

TEST(DashboardTest, WithAuthEachTokenSeesOnlyItsEnvs) {
  InProcess s(Options({"alpha-token", "beta-token"}));
  v1::CreateEnvRequest request = CreateRequest(2);
  grpc::ClientContext context;
  AddToken("alpha-token", &context);
  v1::Env env;
  ASSERT_TRUE(s.stub->CreateEnv(&context, request, &env).ok());
  Reset(s, env.name(), 3, "alpha-token");

  httplib::Client http = Client(s);
  httplib::Result anonymous = http.Get("/api/envs");
  ASSERT_TRUE(anonymous);
  EXPECT_EQ(anonymous->status, 401);
  EXPECT_THAT(anonymous->body, Not(HasSubstr(env.name())));
  httplib::Result wrong =
      http.Get("/api/envs", {{"Authorization", "Bearer nope"}});
  ASSERT_TRUE(wrong);
  EXPECT_EQ(wrong->status, 401);
  httplib::Result beta =
      http.Get("/api/envs", {{"Authorization", "Bearer beta-token"}});
  ASSERT_TRUE(beta);
  EXPECT_EQ(beta->status, 200);
  EXPECT_EQ(beta->body, "{\"envs\":[],\"auth\":true}");
  // The page's way: the token in a cookie, URI-encoded.
  httplib::Result alpha = http.Get(
      "/api/envs", {{"Cookie", "theme=dark; mll_token=alpha%2Dtoken"}});
  ASSERT_TRUE(alpha);
  EXPECT_EQ(alpha->status, 200);
  EXPECT_THAT(alpha->body, HasSubstr(env.name()));

  // Another token cannot watch it: the name is as unknown as any.
  httplib::Result stream =
      http.Get(absl::StrCat("/api/frames?name=", env.name()).c_str(),
               {{"Authorization", "Bearer beta-token"}});
  ASSERT_TRUE(stream);
  EXPECT_EQ(stream->status, 404);
  Viewer viewer;
  httplib::Result watched =
      Watch(s, env.name(), &viewer, [&] { return !viewer.pngs.empty(); },
            {{"Authorization", "Bearer alpha-token"}});
  ASSERT_EQ(viewer.pngs.size(), 1u);
  EXPECT_EQ(viewer.pngs[0].substr(0, 8), std::string(kPngSignature, 8));
}

TEST(DashboardTest, StreamErrorsNameTheParameter) {
  InProcess s(Options());
  const std::string name = CreateEnv(*s.stub, CreateRequest(1));
  httplib::Client http = Client(s);
  httplib::Result unknown = http.Get("/api/frames?name=envs/nothing");
  ASSERT_TRUE(unknown);
  EXPECT_EQ(unknown->status, 404);
  EXPECT_THAT(unknown->body, HasSubstr("name: no env"));
  for (const char* fps : {"0", "31", "x"}) {
    httplib::Result bad =
        http.Get(absl::StrCat("/api/frames?fps=", fps, "&name=", name).c_str());
    ASSERT_TRUE(bad);
    EXPECT_EQ(bad->status, 400) << fps;
    EXPECT_THAT(bad->body, HasSubstr("fps: \\\"")) << fps;
    EXPECT_THAT(bad->body, HasSubstr("1..30")) << fps;
  }
  EXPECT_EQ(s.server->dashboard()->viewers(), 0);
}

TEST(DashboardTest, FramesFollowTheEnvAndAViewerThatLeavesLeavesNoWork) {
  InProcess s(Options());
  const std::string name = CreateEnv(*s.stub, CreateRequest(3));
  Reset(s, name, 7);
  std::atomic<bool> stepping{true};
  std::thread stepper([&] {
    for (int i = 0; i < 200 && stepping; ++i) {
      Step(s, name, {2, 2, 2});
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
  });
  Viewer viewer;
  Watch(s, name, &viewer, [&] { return viewer.pngs.size() >= 5; });
  stepping = false;
  stepper.join();
  ASSERT_EQ(viewer.pngs.size(), 5u);
  // Each frame is a new step with a new picture.
  EXPECT_EQ(std::set<std::string>(viewer.ids.begin(), viewer.ids.end()).size(),
            5u);
  EXPECT_EQ(
      std::set<std::string>(viewer.pngs.begin(), viewer.pngs.end()).size(), 5u);
  for (const std::string& id : viewer.ids) EXPECT_THAT(id, HasSubstr("1."));

  // The connection is closed: the stream's thread notices at its next
  // write and ends, and nothing draws any more.
  DashboardServer& dashboard = *s.server->dashboard();
  ASSERT_TRUE(WaitFor([&] { return dashboard.viewers() == 0; }))
      << dashboard.viewers() << " viewers left";
  const int64_t drawn = dashboard.frames_rendered();
  for (int i = 0; i < 10; ++i) {
    Step(s, name, {0, 0, 0});
    std::this_thread::sleep_for(std::chrono::milliseconds(40));
  }
  EXPECT_EQ(dashboard.frames_rendered(), drawn);
}

TEST(DashboardTest, AnIdleEnvIsDrawnOnceAndItsViewerStillLeaves) {
  InProcess s(Options());
  const std::string name = CreateEnv(*s.stub, CreateRequest(2));
  Reset(s, name, 1);
  DashboardServer& dashboard = *s.server->dashboard();
  Viewer viewer;
  const auto start = std::chrono::steady_clock::now();
  // Two keep-alive periods: the frame, then comments only.
  Watch(s, name, &viewer, [&] {
    return std::chrono::steady_clock::now() - start > std::chrono::seconds(2);
  });
  EXPECT_EQ(viewer.pngs.size(), 1u);
  EXPECT_EQ(dashboard.frames_rendered(), 1);
  EXPECT_TRUE(WaitFor([&] { return dashboard.viewers() == 0; }));
}

TEST(DashboardTest, ADeletedEnvEndsItsStreams) {
  InProcess s(Options());
  const std::string name = CreateEnv(*s.stub, CreateRequest(1));
  Reset(s, name, 1);
  Viewer viewer;
  std::atomic<bool> deleted{false};
  httplib::Result result = Watch(s, name, &viewer, [&] {
    if (!viewer.pngs.empty() && !deleted.exchange(true)) {
      grpc::ClientContext context;
      v1::DeleteEnvRequest request;
      request.set_name(name);
      v1::DeleteEnvResponse response;
      EXPECT_TRUE(s.stub->DeleteEnv(&context, request, &response).ok());
    }
    return false;  // Until the server ends the stream.
  });
  EXPECT_TRUE(result) << httplib::to_string(result.error());
  EXPECT_TRUE(viewer.gone);
  EXPECT_TRUE(WaitFor([&] { return s.server->dashboard()->viewers() == 0; }));
}

TEST(DashboardTest, ViewersNeverChangeATrajectoryAndShareFrames) {
  InProcess s(Options());
  const std::string watched = CreateEnv(*s.stub, CreateRequest(3));
  const std::string alone = CreateEnv(*s.stub, CreateRequest(3));
  Reset(s, watched, 11);
  Reset(s, alone, 11);
  constexpr int kViewers = 3;
  std::atomic<bool> done{false};
  std::vector<Viewer> viewers(kViewers);
  std::vector<std::thread> threads;
  for (Viewer& viewer : viewers) {
    threads.emplace_back([&s, &watched, &viewer, &done] {
      Watch(s, watched, &viewer, [&done] { return done.load(); });
    });
  }
  ASSERT_TRUE(
      WaitFor([&] { return s.server->dashboard()->viewers() == kViewers; }));
  const std::vector<std::vector<int32_t>> actions = ActionTable(150, 3, 5);
  for (const std::vector<int32_t>& row : actions) {
    const v1::StepData a = Step(s, watched, row);
    const v1::StepData b = Step(s, alone, row);
    ASSERT_EQ(ResultBits(a), ResultBits(b));
    if (a.episode_over()) {
      Reset(s, watched, 12);
      Reset(s, alone, 12);
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  done = true;
  // A viewer's callback runs only when data arrives: keep the env moving
  // until every stream has noticed.
  for (int i = 0; i < 50 && s.server->dashboard()->viewers() > 0; ++i) {
    Reset(s, watched, 13);
    std::this_thread::sleep_for(std::chrono::milliseconds(40));
  }
  for (std::thread& t : threads) t.join();
  int64_t received = 0;
  for (const Viewer& viewer : viewers) {
    EXPECT_GT(viewer.pngs.size(), 5u);
    received += viewer.pngs.size();
  }
  // Viewers of one env share its frames: fewer drawn than received.
  EXPECT_LT(s.server->dashboard()->frames_rendered(), received);
  EXPECT_TRUE(WaitFor([&] { return s.server->dashboard()->viewers() == 0; }));
}

TEST(DashboardAddressTest, BadOrBusyAddressIsAnErrorNamingTheFlag) {
  ExpectListenerRefusesBadAndBusyAddresses(
      "--http_address", &ServerOptions::http_address, &Server::http_port);
}

TEST(DashboardBinaryTest, BadOrBusyHttpAddressExitsWithOneLine) {
  auto [code, output] =
      RunServer("--address=127.0.0.1:0 --http_address=127.0.0.1:http");
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output,
              HasSubstr("--http_address: \"127.0.0.1:http\" is not host:port"));
  EXPECT_EQ(std::count(output.begin(), output.end(), '\n'), 1) << output;

  // A port some other socket listens on.
  const int busy = socket(AF_INET, SOCK_STREAM, 0);
  ASSERT_GE(busy, 0);
  sockaddr_in address{};
  address.sin_family = AF_INET;
  address.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  ASSERT_EQ(bind(busy, reinterpret_cast<sockaddr*>(&address), sizeof(address)),
            0);
  ASSERT_EQ(listen(busy, 1), 0);
  socklen_t length = sizeof(address);
  getsockname(busy, reinterpret_cast<sockaddr*>(&address), &length);
  const std::string taken = absl::StrCat("127.0.0.1:", ntohs(address.sin_port));
  std::tie(code, output) =
      RunServer(absl::StrCat("--address=127.0.0.1:0 --http_address=", taken));
  close(busy);
  EXPECT_EQ(code, 1);
  EXPECT_THAT(output, HasSubstr(absl::StrCat(
                          "--http_address: cannot listen on ", taken)));
  EXPECT_EQ(std::count(output.begin(), output.end(), '\n'), 1) << output;

  EXPECT_THAT(RunServer("--help").second, HasSubstr("--http_address"));
}

}  // namespace
}  // namespace mll::service::testing

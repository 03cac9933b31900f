// mll::client against the real mll_server on a free loopback port: every call
// in both transports (unary and session), error codes and messages as the
// server sends them, and the handles' RAII deletion.
#include "mll/client.h"

#include <algorithm>
#include <chrono>
#include <memory>
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::Not;
using ::testing::StartsWith;

// One server for the whole suite: tests use their own environments.
class ServerEnvironment : public ::testing::Environment {
 public:
  void SetUp() override {
    absl::StatusOr<std::unique_ptr<ServerProcess>> server =
        ServerProcess::Start(MLL_SERVER_PATH);
    ASSERT_TRUE(server.ok()) << server.status();
    server_ = *std::move(server);
  }
  void TearDown() override { server_.reset(); }
  static const std::string& address() { return server_->address(); }

 private:
  static inline std::unique_ptr<ServerProcess> server_;
};

Client Connect() {
  absl::StatusOr<Client> client = Client::Create(ServerEnvironment::address());
  EXPECT_TRUE(client.ok()) << client.status();
  return *std::move(client);
}

std::vector<std::string> ListedNames(const Client& client) {
  absl::StatusOr<std::vector<EnvInfo>> envs = client.ListEnvs();
  EXPECT_TRUE(envs.ok()) << envs.status();
  std::vector<std::string> names;
  if (envs.ok()) {
    for (const EnvInfo& env : *envs) names.push_back(env.name);
  }
  return names;
}

bool Listed(const Client& client, const std::string& name) {
  const std::vector<std::string> names = ListedNames(client);
  return std::find(names.begin(), names.end(), name) != names.end();
}

RemoteEnvConfig Landers(int n) {
  RemoteEnvConfig config;
  config.n_landers = n;
  return config;
}

// Runs each test with a unary client and with a session client.
class ClientTest : public ::testing::TestWithParam<bool> {
 protected:
  ClientTest() : unary_(Connect()) {
    if (GetParam()) {
      absl::StatusOr<Client> session = unary_.OpenSession();
      EXPECT_TRUE(session.ok()) << session.status();
      client_ = std::make_unique<Client>(*std::move(session));
    } else {
      client_ = std::make_unique<Client>(Connect());
    }
  }
  Client& client() { return *client_; }

  RemoteEnv MakeEnv(const RemoteEnvConfig& config) {
    absl::StatusOr<RemoteEnv> env = client().CreateEnv(config);
    EXPECT_TRUE(env.ok()) << env.status();
    return *std::move(env);
  }

  Client unary_;
  std::unique_ptr<Client> client_;
};

TEST_P(ClientTest, HealthIsServing) {
  EXPECT_EQ(client().is_session(), GetParam());
  EXPECT_TRUE(client().CheckHealth().ok());
}

TEST_P(ClientTest, CreateReportsConfigAndSpaces) {
  RemoteEnvConfig config = Landers(4);
  config.continuous = true;
  config.gravity = -5.5;
  RemoteEnv env = MakeEnv(config);
  EXPECT_THAT(env.name(), StartsWith("envs/"));
  EXPECT_EQ(env.n_landers(), 4);
  EXPECT_TRUE(env.continuous());
  const EnvInfo& info = env.info();
  EXPECT_EQ(info.config.gravity, -5.5);
  EXPECT_EQ(info.config.max_cycles, 500);  // The server's default, filled in.
  EXPECT_EQ(info.config.shared_reward, true);
  EXPECT_THAT(info.possible_agents,
              ElementsAre("lander_0", "lander_1", "lander_2", "lander_3"));
  EXPECT_EQ(info.observation_space.kind, SpaceSpec::Kind::kBox);
  EXPECT_EQ(info.observation_space.dtype, ElementType::kFloat32);
  EXPECT_THAT(info.observation_space.shape, ElementsAre(12));
  EXPECT_EQ(info.action_space.kind, SpaceSpec::Kind::kBox);
  EXPECT_THAT(info.action_space.shape, ElementsAre(2));
  EXPECT_THAT(info.action_space.low, ElementsAre(-1.0, -1.0));
  EXPECT_THAT(info.action_space.high, ElementsAre(1.0, 1.0));
  EXPECT_EQ(info.render_fps, 50);
  EXPECT_FALSE(info.episode_started);
  EXPECT_EQ(info.session_bound, GetParam());
  EXPECT_THAT(info.json, HasSubstr("\"name\":\"" + env.name() + "\""));

  RemoteEnv discrete = MakeEnv(Landers(1));
  EXPECT_EQ(discrete.info().action_space.kind, SpaceSpec::Kind::kDiscrete);
  EXPECT_EQ(discrete.info().action_space.n, 4);
}

TEST_P(ClientTest, GetListAttachAndDelete) {
  RemoteEnv env = MakeEnv(Landers(2));
  absl::StatusOr<EnvInfo> info = client().GetEnv(env.name());
  ASSERT_TRUE(info.ok()) << info.status();
  EXPECT_EQ(info->name, env.name());
  EXPECT_EQ(info->n_landers(), 2);
  EXPECT_TRUE(Listed(unary_, env.name()));

  absl::StatusOr<RemoteEnv> attached = client().Attach(env.name());
  ASSERT_TRUE(attached.ok()) << attached.status();
  EXPECT_FALSE(attached->owned());
  ASSERT_TRUE(attached->Reset(1).ok());
  absl::StatusOr<EnvInfo> refreshed = env.Refresh();
  ASSERT_TRUE(refreshed.ok()) << refreshed.status();
  EXPECT_TRUE(refreshed->episode_started);
  EXPECT_EQ(refreshed->episodes, 1);
  { RemoteEnv gone = *std::move(attached); }  // Not owned: nothing deleted.
  EXPECT_TRUE(Listed(unary_, env.name()));
  const std::string name = env.name();
  ASSERT_TRUE(env.Delete().ok());
  EXPECT_FALSE(Listed(unary_, name));
  EXPECT_EQ(client().DeleteEnv(name).code(), absl::StatusCode::kNotFound);
}

TEST_P(ClientTest, ResetAndParallelStep) {
  RemoteEnv env = MakeEnv(Landers(3));
  absl::StatusOr<StepData> reset = env.Reset(42);
  ASSERT_TRUE(reset.ok()) << reset.status();
  EXPECT_EQ(reset->n_landers, 3);
  EXPECT_EQ(reset->observations.size(), 36u);
  EXPECT_THAT(reset->stepped, ElementsAre(1, 1, 1));
  EXPECT_THAT(reset->rewards, ElementsAre(0.0f, 0.0f, 0.0f));
  EXPECT_EQ(reset->seed, 42u);
  EXPECT_EQ(reset->cycles, 0);
  EXPECT_FALSE(reset->episode_over);

  const std::vector<int32_t> actions = {2, 0, 3};
  absl::StatusOr<StepData> step = env.Step(Actions::Discrete(actions));
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->cycles, 1);
  EXPECT_NE(step->observations, reset->observations);
  for (LanderOutcome outcome : step->outcomes) {
    EXPECT_EQ(outcome, LanderOutcome::kNone);
  }
  EXPECT_THAT(step->episode_lengths, ElementsAre(1, 1, 1));

  // Fly to the end with the main engine off: every lander ends the episode.
  int steps = 1;
  const std::vector<int32_t> idle = {0, 0, 0};
  while (!step->episode_over && steps < 1000) {
    step = env.Step(Actions::Discrete(idle));
    ASSERT_TRUE(step.ok()) << step.status();
    ++steps;
  }
  EXPECT_TRUE(step->episode_over);
  absl::StatusOr<StepData> after = env.Step(Actions::Discrete(idle));
  EXPECT_EQ(after.status().code(), absl::StatusCode::kFailedPrecondition);
}

TEST_P(ClientTest, ContinuousStep) {
  RemoteEnvConfig config = Landers(2);
  config.continuous = true;
  RemoteEnv env = MakeEnv(config);
  ASSERT_TRUE(env.Reset(3).ok());
  const std::vector<float> actions = {1.0f, 0.0f, -1.0f, 0.7f};
  absl::StatusOr<StepData> step = env.Step(Actions::Continuous(actions));
  ASSERT_TRUE(step.ok()) << step.status();
  EXPECT_EQ(step->cycles, 1);
}

TEST_P(ClientTest, AecTurnsAndDeadSteps) {
  RemoteEnvConfig config = Landers(2);
  config.max_cycles = 3;
  RemoteEnv env = MakeEnv(config);
  EXPECT_EQ(env.Last().status().code(), absl::StatusCode::kFailedPrecondition);
  ASSERT_TRUE(env.Reset(5).ok());
  EXPECT_THAT(env.aec().agents, ElementsAre(0, 1));
  absl::StatusOr<AecTurn> turn = env.Last();
  ASSERT_TRUE(turn.ok()) << turn.status();
  EXPECT_EQ(turn->agent, 0);
  EXPECT_EQ(turn->observation.size(), 12u);
  EXPECT_FALSE(turn->done());

  ASSERT_TRUE(env.StepAgent(2).ok());
  EXPECT_FALSE(env.aec().world_stepped);
  EXPECT_EQ(env.aec().agent_selection, 1);
  ASSERT_TRUE(env.StepAgent(0).ok());
  EXPECT_TRUE(env.aec().world_stepped);
  EXPECT_EQ(env.aec().agent_selection, 0);

  // A dead step for a live agent is refused and changes nothing.
  absl::Status dead = env.StepAgentDead();
  EXPECT_EQ(dead.code(), absl::StatusCode::kFailedPrecondition) << dead;
  EXPECT_EQ(env.aec().agent_selection, 0);

  // Play the PettingZoo loop until every agent has taken its dead step.
  int calls = 0;
  while (env.aec().agent_selection >= 0 && calls < 100) {
    absl::StatusOr<AecTurn> last = env.Last();
    ASSERT_TRUE(last.ok()) << last.status();
    absl::Status status = last->done() ? env.StepAgentDead() : env.StepAgent(0);
    ASSERT_TRUE(status.ok()) << status;
    ++calls;
  }
  EXPECT_TRUE(env.aec().agents.empty());
  EXPECT_EQ(env.Last().status().code(), absl::StatusCode::kFailedPrecondition);
  absl::StatusOr<EnvInfo> info = env.Refresh();
  ASSERT_TRUE(info.ok());
  EXPECT_TRUE(info->episode_over);
  EXPECT_EQ(info->cycles, 3);
}

TEST_P(ClientTest, AecContinuousAction) {
  RemoteEnvConfig config = Landers(1);
  config.continuous = true;
  RemoteEnv env = MakeEnv(config);
  ASSERT_TRUE(env.Reset(0).ok());
  ASSERT_TRUE(env.StepAgent({0.5f, -0.9f}).ok());
  EXPECT_TRUE(env.aec().world_stepped);
  EXPECT_EQ(env.aec().episode_lengths[0], 1);
}

TEST_P(ClientTest, AecStaleViewIsRefused) {
  RemoteEnv env = MakeEnv(Landers(2));
  ASSERT_TRUE(env.Reset(0).ok());
  // Another handle acts for lander_0 behind this handle's back.
  absl::StatusOr<RemoteEnv> other = client().Attach(env.name());
  ASSERT_TRUE(other.ok());
  ASSERT_TRUE(other->Reset(0).ok());
  ASSERT_TRUE(other->StepAgent(0).ok());
  absl::Status stale = env.StepAgent(0);  // Believes lander_0 is selected.
  EXPECT_EQ(stale.code(), absl::StatusCode::kFailedPrecondition) << stale;
}

TEST_P(ClientTest, RenderRgbAndPng) {
  RemoteEnvConfig config = Landers(2);
  config.render_rgb_array = true;
  RemoteEnv env = MakeEnv(config);
  ASSERT_TRUE(env.Reset(0).ok());
  absl::StatusOr<RenderedFrame> rgb = env.Render(FrameFormat::kRgb);
  ASSERT_TRUE(rgb.ok()) << rgb.status();
  EXPECT_EQ(rgb->width, 600);
  EXPECT_EQ(rgb->height, 400);
  EXPECT_EQ(rgb->format, FrameFormat::kRgb);
  EXPECT_EQ(rgb->data.size(), 600u * 400u * 3u);
  absl::StatusOr<RenderedFrame> png = env.Render(FrameFormat::kPng);
  ASSERT_TRUE(png.ok()) << png.status();
  EXPECT_EQ(png->format, FrameFormat::kPng);
  EXPECT_THAT(png->data, StartsWith("\x89PNG\r\n\x1a\n"));

  RemoteEnv no_render = MakeEnv(Landers(1));
  ASSERT_TRUE(no_render.Reset(0).ok());
  EXPECT_EQ(no_render.Render().status().code(),
            absl::StatusCode::kFailedPrecondition);
}

TEST_P(ClientTest, StepBatchReportsErrorsPerItem) {
  RemoteEnv a = MakeEnv(Landers(2));
  RemoteEnv b = MakeEnv(Landers(3));
  RemoteEnv c = MakeEnv(Landers(1));
  ASSERT_TRUE(a.Reset(1).ok());
  ASSERT_TRUE(b.Reset(2).ok());  // c is never reset.
  const std::vector<int32_t> two = {2, 2};
  const std::vector<int32_t> three = {1, 9, 3};  // 9 is not an action.
  const std::vector<int32_t> one = {0};
  const std::vector<BatchStep> steps = {{&a, Actions::Discrete(two)},
                                        {&b, Actions::Discrete(three)},
                                        {&c, Actions::Discrete(one)}};
  absl::StatusOr<std::vector<absl::StatusOr<StepData>>> results =
      client().StepBatch(steps);
  ASSERT_TRUE(results.ok()) << results.status();
  ASSERT_EQ(results->size(), 3u);
  ASSERT_TRUE((*results)[0].ok()) << (*results)[0].status();
  EXPECT_EQ((*results)[0]->n_landers, 2);
  EXPECT_EQ((*results)[0]->cycles, 1);
  EXPECT_EQ((*results)[1].status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT((*results)[1].status().message(), HasSubstr("9"));
  EXPECT_EQ((*results)[2].status().code(),
            absl::StatusCode::kFailedPrecondition);

  const std::vector<BatchStep> empty_handle = {
      {nullptr, Actions::Discrete(one)}};
  EXPECT_EQ(client().StepBatch(empty_handle).status().code(),
            absl::StatusCode::kInvalidArgument);
}

TEST_P(ClientTest, ServerErrorsKeepCodeAndMessage) {
  const std::string missing = "envs/does-not-exist";
  absl::Status status = client().GetEnv(missing).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kNotFound) << status;
  EXPECT_THAT(status.message(), HasSubstr(missing));
  EXPECT_EQ(client().Attach(missing).status().code(),
            absl::StatusCode::kNotFound);

  absl::StatusOr<RemoteEnv> bad = client().CreateEnv(Landers(99));
  EXPECT_EQ(bad.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(bad.status().message(), HasSubstr("n_landers"));
  EXPECT_THAT(bad.status().message(), HasSubstr("99"));

  RemoteEnv env = MakeEnv(Landers(2));
  const std::vector<int32_t> actions = {0, 0};
  EXPECT_EQ(env.Step(Actions::Discrete(actions)).status().code(),
            absl::StatusCode::kFailedPrecondition);  // Before Reset.
  ASSERT_TRUE(env.Reset(0).ok());
  const std::vector<int32_t> out_of_range = {0, 7};
  absl::Status step = env.Step(Actions::Discrete(out_of_range)).status();
  EXPECT_EQ(step.code(), absl::StatusCode::kInvalidArgument) << step;
  EXPECT_THAT(step.message(), HasSubstr("7"));
  const std::vector<int32_t> too_few = {0};
  EXPECT_EQ(env.Step(Actions::Discrete(too_few)).status().code(),
            absl::StatusCode::kInvalidArgument);
  const std::vector<float> wrong_kind = {0.0f, 0.0f, 0.0f, 0.0f};
  EXPECT_EQ(env.Step(Actions::Continuous(wrong_kind)).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(env.StepAgent(5).code(), absl::StatusCode::kInvalidArgument);
  // Neither member set: refused by the client before any call.
  absl::Status none = env.Step(Actions()).status();
  EXPECT_EQ(none.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(none.message(), HasSubstr("exactly one"));
  // The session survives errors: the env is still usable.
  EXPECT_TRUE(env.Step(Actions::Discrete(actions)).ok());
}

TEST_P(ClientTest, HandleDeletesItsEnvOnDestruction) {
  std::string name;
  {
    RemoteEnv env = MakeEnv(Landers(1));
    name = env.name();
    EXPECT_TRUE(Listed(unary_, name));
    RemoteEnv moved = std::move(env);  // Ownership moves; one deletion.
    EXPECT_FALSE(env.owned());
    EXPECT_TRUE(moved.owned());
  }
  EXPECT_FALSE(Listed(unary_, name));

  // Assigning over an owning handle deletes its env.
  RemoteEnv first = MakeEnv(Landers(1));
  const std::string first_name = first.name();
  first = MakeEnv(Landers(1));
  EXPECT_FALSE(Listed(unary_, first_name));
  EXPECT_TRUE(Listed(unary_, first.name()));
}

TEST_P(ClientTest, ReleasedHandleLeavesItsEnv) {
  std::string name;
  {
    RemoteEnv env = MakeEnv(Landers(1));
    name = env.Release();
    EXPECT_FALSE(env.owned());
  }
  EXPECT_TRUE(Listed(unary_, name));
  EXPECT_TRUE(unary_.DeleteEnv(name).ok());
}

INSTANTIATE_TEST_SUITE_P(Transports, ClientTest, ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& info) {
                           return info.param ? "Session" : "Unary";
                         });

TEST(SessionTest, EnvsDieWithTheSessionUnlessDetached) {
  Client unary = Connect();
  std::string bound;
  std::string detached;
  {
    absl::StatusOr<Client> session = unary.OpenSession();
    ASSERT_TRUE(session.ok()) << session.status();
    absl::StatusOr<RemoteEnv> a = session->CreateEnv(Landers(1));
    absl::StatusOr<RemoteEnv> b =
        session->CreateEnv(Landers(1), /*detached=*/true);
    ASSERT_TRUE(a.ok() && b.ok());
    bound = a->Release();  // Not deleted by the handle: by the session's end.
    detached = b->Release();
    EXPECT_TRUE(a->info().session_bound);
    EXPECT_FALSE(b->info().session_bound);
    EXPECT_TRUE(Listed(unary, bound));
  }  // The last user of the stream is gone: it ends.
  EXPECT_TRUE(Eventually([&] { return !Listed(unary, bound); }));
  EXPECT_TRUE(Listed(unary, detached));
  EXPECT_TRUE(unary.DeleteEnv(detached).ok());
}

TEST(SessionTest, HandlesKeepTheStreamAlive) {
  Client unary = Connect();
  absl::StatusOr<RemoteEnv> env;
  {
    absl::StatusOr<Client> session = unary.OpenSession();
    ASSERT_TRUE(session.ok());
    env = session->CreateEnv(Landers(2));
    ASSERT_TRUE(env.ok());
  }  // The session client is gone, its handle is not.
  EXPECT_TRUE(env->Reset(0).ok());
  EXPECT_TRUE(Listed(unary, env->name()));
}

TEST(ClientOptionsTest, BadAddressAndOptions) {
  EXPECT_EQ(Client::Create("").status().code(),
            absl::StatusCode::kInvalidArgument);
  ClientOptions options;
  options.max_receive_message_bytes = 0;
  absl::Status status = Client::Create("127.0.0.1:1", options).status();
  EXPECT_EQ(status.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(status.message(), HasSubstr("max_receive_message_bytes"));
}

// A private server, killed mid-use: every call then fails UNAVAILABLE.
TEST(ServerGoneTest, CallsFailUnavailable) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server =
      ServerProcess::Start(MLL_SERVER_PATH);
  ASSERT_TRUE(server.ok()) << server.status();
  ClientOptions options;
  options.call_timeout = std::chrono::seconds(20);
  absl::StatusOr<Client> client = Client::Create((*server)->address(), options);
  ASSERT_TRUE(client.ok());
  absl::StatusOr<Client> session = client->OpenSession();
  ASSERT_TRUE(session.ok());
  absl::StatusOr<RemoteEnv> env = client->CreateEnv(Landers(1));
  ASSERT_TRUE(env.ok()) << env.status();
  absl::StatusOr<RemoteEnv> session_env = session->CreateEnv(Landers(1));
  ASSERT_TRUE(session_env.ok()) << session_env.status();
  ASSERT_TRUE(env->Reset(0).ok());

  (*server)->Kill();
  EXPECT_EQ(client->CheckHealth().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(env->Reset(0).status().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(client->ListEnvs().status().code(), absl::StatusCode::kUnavailable);
  absl::Status on_session = session_env->Reset(0).status();
  EXPECT_EQ(on_session.code(), absl::StatusCode::kUnavailable) << on_session;
  // The stream stays failed; later calls say the same at once.
  EXPECT_EQ(session->GetEnv(session_env->name()).status().code(),
            absl::StatusCode::kUnavailable);
  EXPECT_EQ(env->Delete().code(), absl::StatusCode::kUnavailable);
}

// Leases follow the handles: a paused program keeps its environments for
// many idle timeouts; once the handle is gone, the server reclaims the env
// after the timeout and its NOT_FOUND says so.
TEST(LeaseTest, HandlesKeepTheirEnvsThroughPausesLongerThanTheTimeout) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server =
      ServerProcess::Start(MLL_SERVER_PATH, {"--idle_timeout_s=0.6"});
  ASSERT_TRUE(server.ok()) << server.status();
  absl::StatusOr<Client> client = Client::Create((*server)->address());
  ASSERT_TRUE(client.ok()) << client.status();
  absl::StatusOr<Client> session = client->OpenSession();
  ASSERT_TRUE(session.ok()) << session.status();
  absl::StatusOr<RemoteEnv> env = client->CreateEnv(Landers(1));
  ASSERT_TRUE(env.ok()) << env.status();
  EXPECT_DOUBLE_EQ(env->info().idle_timeout_s, 0.6);
  absl::StatusOr<RemoteEnv> bound = session->CreateEnv(Landers(1));
  ASSERT_TRUE(bound.ok()) << bound.status();
  absl::StatusOr<RemoteEnv> released = client->CreateEnv(Landers(1));
  ASSERT_TRUE(released.ok()) << released.status();
  const std::string name = released->Release();
  released = absl::CancelledError("dropped");  // Destroys the handle.

  std::this_thread::sleep_for(std::chrono::milliseconds(2000));  // The pause.
  EXPECT_TRUE(env->Reset(1).ok());
  EXPECT_TRUE(bound->Reset(1).ok());
  absl::Status gone = client->GetEnv(name).status();
  EXPECT_EQ(gone.code(), absl::StatusCode::kNotFound);
  EXPECT_THAT(gone.message(),
              HasSubstr("was reclaimed after being idle 0.6 s"));
}

TEST(ServerGoneTest, NoServerAtAll) {
  // Port 1 on loopback: nothing listens there for an unprivileged test.
  absl::StatusOr<Client> client = Client::Create("127.0.0.1:1");
  ASSERT_TRUE(client.ok());
  EXPECT_EQ(client->CheckHealth().code(), absl::StatusCode::kUnavailable);
  EXPECT_EQ(client->CreateEnv().status().code(),
            absl::StatusCode::kUnavailable);
}

}  // namespace
}  // namespace mll::client

int main(int argc, char** argv) {
  ::testing::InitGoogleTest(&argc, argv);
  ::testing::AddGlobalTestEnvironment(new mll::client::ServerEnvironment);
  return RUN_ALL_TESTS();
}

// The server gives the same bits as the core in-process: for the same config,
// seed and actions, every observation, reward, flag and outcome of a remote
// episode equals the core's, whatever the transport (unary, session stream,
// batched).
#include <cstring>
#include <memory>
#include <string>
#include <vector>

#include "core_bridge.h"
#include "gtest/gtest.h"
#include "mll/client.h"
#include "mll/core/aec_env.h"
#include "mll/core/env.h"
#include "mll/core/heuristic.h"
#include "server_process.h"
#include "suite_server.h"

namespace mll::client {
namespace {

enum class Transport { kUnary, kSession, kBatch };

struct Case {
  std::string label;
  Transport transport;
  core::EnvConfig config;
  uint64_t seed;
};

void PrintTo(const Case& c, std::ostream* os) { *os << c.label; }

template <typename T>
bool SameBits(const std::vector<T>& a, const std::vector<T>& b) {
  return a.size() == b.size() &&
         std::memcmp(a.data(), b.data(), a.size() * sizeof(T)) == 0;
}

// Every column of a remote result equals the core's, bit for bit.
void ExpectSameBits(const core::StepResult& core, const StepData& remote,
                    int step) {
  SCOPED_TRACE(testing::Message() << "step " << step);
  EXPECT_TRUE(SameBits(core.observations, remote.observations));
  EXPECT_TRUE(SameBits(core.rewards, remote.rewards));
  EXPECT_EQ(core.terminations, remote.terminations);
  EXPECT_EQ(core.truncations, remote.truncations);
  EXPECT_EQ(core.stepped, remote.stepped);
  ASSERT_EQ(core.outcomes.size(), remote.outcomes.size());
  for (size_t i = 0; i < core.outcomes.size(); ++i) {
    EXPECT_EQ(static_cast<int>(core.outcomes[i]),
              static_cast<int>(remote.outcomes[i]));
  }
  EXPECT_EQ(core.episode_over, remote.episode_over);
}

class EquivalenceTest : public ::testing::TestWithParam<Case> {
 protected:
  static void SetUpTestSuite() { server_ = StartSuiteServer({"--threads=2"}); }
  static void TearDownTestSuite() {
    delete server_;
    server_ = nullptr;
  }
  // A unary client, or a session client for Transport::kSession.
  static absl::StatusOr<Client> ClientFor(Transport transport) {
    absl::StatusOr<Client> unary = Client::Create(server_->address());
    if (!unary.ok() || transport != Transport::kSession) return unary;
    return unary->OpenSession();
  }

  static inline ServerProcess* server_ = nullptr;
};

TEST_P(EquivalenceTest, HeuristicEpisodeIsBitIdentical) {
  const Case& c = GetParam();
  absl::StatusOr<std::unique_ptr<core::Env>> core = core::Env::Create(c.config);
  ASSERT_TRUE(core.ok()) << core.status();
  absl::StatusOr<Client> client = ClientFor(c.transport);
  ASSERT_TRUE(client.ok()) << client.status();
  absl::StatusOr<RemoteEnv> remote =
      client->CreateEnv(RemoteConfigFrom(c.config));
  ASSERT_TRUE(remote.ok()) << remote.status();

  core::StepResult core_result;
  (*core)->Reset(c.seed, &core_result);
  absl::StatusOr<StepData> remote_result = remote->Reset(c.seed);
  ASSERT_TRUE(remote_result.ok()) << remote_result.status();
  ExpectSameBits(core_result, *remote_result, 0);

  // Actions come from the core's observations; the remote env must follow
  // the same trajectory for them to keep fitting.
  RemotePilot pilot(PilotPolicy::kHeuristic, c.config.n_landers,
                    c.config.continuous, 0);
  int step = 0;
  while (!core_result.episode_over && step < c.config.max_cycles) {
    StepData core_view;
    core_view.n_landers = c.config.n_landers;
    core_view.observations = core_result.observations;
    core_view.terminations = core_result.terminations;
    core_view.truncations = core_result.truncations;
    core_view.stepped = core_result.stepped;
    const Actions actions = pilot.Act(core_view);
    core::ActionsView view{actions.discrete, actions.continuous};
    ASSERT_TRUE((*core)->Step(view, &core_result).ok());
    if (c.transport == Transport::kBatch) {
      const std::vector<BatchStep> batch = {{&*remote, actions}};
      absl::StatusOr<std::vector<absl::StatusOr<StepData>>> results =
          client->StepBatch(batch);
      ASSERT_TRUE(results.ok()) << results.status();
      remote_result = (*results)[0];
    } else {
      remote_result = remote->Step(actions);
    }
    ASSERT_TRUE(remote_result.ok()) << remote_result.status();
    ++step;
    ExpectSameBits(core_result, *remote_result, step);
    if (HasFailure()) return;
  }
  EXPECT_TRUE(core_result.episode_over);
  EXPECT_GT(step, 50);  // A real flight, not a crash at the first step.
  for (int agent = 0; agent < c.config.n_landers; ++agent) {
    EXPECT_EQ(static_cast<float>((*core)->episode_return(agent)),
              remote_result->episode_returns[agent]);
    EXPECT_EQ((*core)->episode_length(agent),
              remote_result->episode_lengths[agent]);
  }
}

// The AEC path: the core's AecEnv and the server's StepAgent agree on every
// turn's observation and cumulative reward (no batch form exists).
using AecEquivalenceTest = EquivalenceTest;

TEST_P(AecEquivalenceTest, AecEpisodeIsBitIdentical) {
  const Case& c = GetParam();
  absl::StatusOr<std::unique_ptr<core::Env>> core = core::Env::Create(c.config);
  ASSERT_TRUE(core.ok());
  core::AecEnv core_aec(core->get());
  absl::StatusOr<Client> client = ClientFor(c.transport);
  ASSERT_TRUE(client.ok()) << client.status();
  absl::StatusOr<RemoteEnv> remote =
      client->CreateEnv(RemoteConfigFrom(c.config));
  ASSERT_TRUE(remote.ok()) << remote.status();

  core_aec.Reset(c.seed);
  ASSERT_TRUE(remote->Reset(c.seed).ok());
  int turns = 0;
  while (core_aec.agent_selection() >= 0 && turns < 5000) {
    const int agent = core_aec.agent_selection();
    ASSERT_EQ(remote->aec().agent_selection, agent) << "turn " << turns;
    const AecTurn last = remote->aec().Last();
    const absl::Span<const float> core_obs = core_aec.observe(agent);
    ASSERT_EQ(std::memcmp(core_obs.data(), last.observation.data(),
                          core_obs.size() * sizeof(float)),
              0)
        << "turn " << turns;
    ASSERT_EQ(core_aec.cumulative_reward(agent), last.cumulative_reward);
    ASSERT_EQ(core_aec.terminated(agent), last.termination);
    ASSERT_EQ(core_aec.truncated(agent), last.truncation);
    if (last.done()) {
      ASSERT_TRUE(core_aec.Step(std::nullopt).ok());
      ASSERT_TRUE(remote->StepAgentDead().ok());
    } else {
      const core::AgentAction action =
          core::HeuristicAction(core_obs, c.config.continuous);
      ASSERT_TRUE(core_aec.Step(action).ok());
      ASSERT_TRUE((c.config.continuous ? remote->StepAgent(action.continuous)
                                       : remote->StepAgent(action.discrete))
                      .ok());
    }
    ++turns;
  }
  EXPECT_EQ(remote->aec().agent_selection, -1);
  EXPECT_GT(turns, 50);
}

core::EnvConfig Config(int n, bool continuous, bool wind) {
  core::EnvConfig config;
  config.n_landers = n;
  config.continuous = continuous;
  config.enable_wind = wind;
  config.max_cycles = 400;
  // One crash must not end everyone's flight at once: longer episodes.
  config.terminate_on_damage = false;
  return config;
}

const Case kUnaryDiscrete3{"UnaryDiscrete3", Transport::kUnary,
                           Config(3, false, false), 7};
const Case kUnaryContinuousWind4{"UnaryContinuousWind4", Transport::kUnary,
                                 Config(4, true, true), 11};
const Case kSessionDiscrete3{"SessionDiscrete3", Transport::kSession,
                             Config(3, false, false), 7};
const Case kSessionContinuous2{"SessionContinuous2", Transport::kSession,
                               Config(2, true, false), 3};
const Case kBatchDiscreteWind9{"BatchDiscreteWind9", Transport::kBatch,
                               Config(9, false, true), 5};

std::string Label(const ::testing::TestParamInfo<Case>& info) {
  return info.param.label;
}

INSTANTIATE_TEST_SUITE_P(
    Transports, EquivalenceTest,
    ::testing::Values(kUnaryDiscrete3, kUnaryContinuousWind4, kSessionDiscrete3,
                      kSessionContinuous2, kBatchDiscreteWind9),
    Label);
INSTANTIATE_TEST_SUITE_P(Transports, AecEquivalenceTest,
                         ::testing::Values(kUnaryDiscrete3,
                                           kUnaryContinuousWind4,
                                           kSessionDiscrete3,
                                           kSessionContinuous2),
                         Label);

}  // namespace
}  // namespace mll::client

// Same seed and same actions give bit-identical observations, rewards and
// outcomes whether the env is stepped in-process (mll::core::Env), by StepEnv,
// by StepAgent (AEC, once every agent acted), by StepBatch, or on a Session
// stream, and whatever the server's thread count.
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"
#include "mll/service/convert.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

constexpr int kLanders = 3;
constexpr int kCycles = 300;

// Long episodes in which landers finish at different times, so that dead
// agents, dead steps and partial rows are exercised.
v1::CreateEnvRequest Request() {
  v1::CreateEnvRequest request = CreateRequest(kLanders);
  request.mutable_config()->set_terminate_on_damage(false);
  request.mutable_config()->set_shared_reward(false);
  request.mutable_config()->set_max_cycles(kCycles);
  return request;
}

using Trajectory = std::vector<std::string>;  // ResultBits per step.

// The reference: the core stepped directly, the reset's result first.
std::vector<v1::StepData> CoreTrajectory(
    uint64_t seed, const std::vector<std::vector<int32_t>>& actions) {
  absl::StatusOr<core::EnvConfig> config =
      EnvConfigFromProto(Request().config());
  EXPECT_TRUE(config.ok());
  absl::StatusOr<std::unique_ptr<core::Env>> env = core::Env::Create(*config);
  EXPECT_TRUE(env.ok());
  core::StepResult result;
  v1::StepData data;
  (*env)->Reset(seed, &result);
  FillStepData(result, **env, false, &data);
  std::vector<v1::StepData> trajectory = {data};
  for (const std::vector<int32_t>& row : actions) {
    if (result.episode_over) break;
    EXPECT_TRUE((*env)->Step(core::ActionsView{row, {}}, &result).ok());
    FillStepData(result, **env, false, &data);
    trajectory.push_back(data);
  }
  return trajectory;
}

v1::ResetEnvRequest ResetRequest(const std::string& name, uint64_t seed) {
  v1::ResetEnvRequest request;
  request.set_name(name);
  request.set_seed(seed);
  return request;
}

v1::StepEnvRequest StepRequest(const std::string& name,
                               const std::vector<int32_t>& actions) {
  v1::StepEnvRequest request;
  request.set_name(name);
  *request.mutable_actions() = DiscreteActions(actions);
  return request;
}

class EquivalenceTest : public ::testing::Test {
 protected:
  void SetUp() override {
    for (uint64_t seed : kSeeds) {
      actions_.push_back(ActionTable(kCycles, kLanders, seed + 100));
      reference_.push_back(CoreTrajectory(seed, actions_.back()));
      expected_.emplace_back();
      for (const v1::StepData& data : reference_.back()) {
        expected_.back().push_back(ResultBits(data));
      }
    }
  }

  // StepBatch over every seed's env at once, each dropped when its episode
  // is over.
  void ExpectBatchMatches(v1::MultiLunarLander::Stub& stub) {
    std::vector<std::string> names;
    std::vector<Trajectory> got(kSeeds.size());
    for (size_t e = 0; e < kSeeds.size(); ++e) {
      names.push_back(CreateEnv(stub, Request()));
      grpc::ClientContext context;
      v1::ResetEnvResponse reset;
      ASSERT_TRUE(
          stub.ResetEnv(&context, ResetRequest(names[e], kSeeds[e]), &reset)
              .ok());
      got[e].push_back(ResultBits(reset.data()));
    }
    for (int cycle = 0; cycle < kCycles; ++cycle) {
      v1::StepBatchRequest request;
      std::vector<size_t> in_batch;
      for (size_t e = 0; e < kSeeds.size(); ++e) {
        if (got[e].size() < expected_[e].size()) {
          *request.add_steps() = StepRequest(names[e], actions_[e][cycle]);
          in_batch.push_back(e);
        }
      }
      if (in_batch.empty()) break;
      grpc::ClientContext context;
      v1::StepBatchResponse response;
      ASSERT_TRUE(stub.StepBatch(&context, request, &response).ok());
      ASSERT_EQ(response.results_size(), static_cast<int>(in_batch.size()));
      for (size_t i = 0; i < in_batch.size(); ++i) {
        ASSERT_TRUE(response.results(i).has_data())
            << response.results(i).error().message();
        got[in_batch[i]].push_back(ResultBits(response.results(i).data()));
      }
    }
    for (size_t e = 0; e < kSeeds.size(); ++e) {
      EXPECT_EQ(got[e], expected_[e]) << "seed " << kSeeds[e];
    }
  }

  const std::vector<uint64_t> kSeeds = {0, 1, 7, 12345, 99};
  std::vector<std::vector<std::vector<int32_t>>> actions_;
  std::vector<std::vector<v1::StepData>> reference_;
  std::vector<Trajectory> expected_;  // ResultBits of reference_.
};

TEST_F(EquivalenceTest, ReferenceEpisodesAreNontrivial) {
  for (const Trajectory& trajectory : expected_) {
    EXPECT_GT(trajectory.size(), 20u);
  }
}

TEST_F(EquivalenceTest, StepEnvMatchesTheCore) {
  InProcess s;
  for (size_t e = 0; e < kSeeds.size(); ++e) {
    const std::string name = CreateEnv(*s.stub, Request());
    grpc::ClientContext context;
    v1::ResetEnvResponse reset;
    ASSERT_TRUE(
        s.stub->ResetEnv(&context, ResetRequest(name, kSeeds[e]), &reset).ok());
    Trajectory got = {ResultBits(reset.data())};
    for (size_t c = 0; got.size() < expected_[e].size(); ++c) {
      grpc::ClientContext step_context;
      v1::StepEnvResponse response;
      ASSERT_TRUE(s.stub
                      ->StepEnv(&step_context,
                                StepRequest(name, actions_[e][c]), &response)
                      .ok());
      got.push_back(ResultBits(response.data()));
    }
    EXPECT_EQ(got, expected_[e]) << "seed " << kSeeds[e];
  }
}

TEST_F(EquivalenceTest, StepBatchMatchesTheCoreOnOneAndTwoThreads) {
  for (int threads : {1, 2}) {
    SCOPED_TRACE(threads);
    ServiceOptions options;
    options.threads = threads;
    InProcess s(options);
    ExpectBatchMatches(*s.stub);
  }
}

TEST_F(EquivalenceTest, SessionMatchesTheCore) {
  InProcess s;
  for (size_t e = 0; e < kSeeds.size(); ++e) {
    grpc::ClientContext context;
    auto stream = s.stub->Session(&context);
    uint64_t sequence = 0;
    auto call = [&](v1::SessionRequest request) {
      request.set_sequence(++sequence);
      EXPECT_TRUE(stream->Write(request));
      v1::SessionResponse response;
      EXPECT_TRUE(stream->Read(&response));
      EXPECT_EQ(response.sequence(), sequence);
      EXPECT_FALSE(response.has_error()) << response.error().message();
      return response;
    };
    v1::SessionRequest create;
    *create.mutable_create_env() = Request();
    const std::string name = call(create).env().name();
    v1::SessionRequest reset;
    *reset.mutable_reset_env() = ResetRequest(name, kSeeds[e]);
    Trajectory got = {ResultBits(call(reset).reset_env().data())};
    // Alternates plain steps and one-env batches on the stream.
    for (size_t c = 0; got.size() < expected_[e].size(); ++c) {
      v1::SessionRequest step;
      if (c % 2 == 0) {
        *step.mutable_step_env() = StepRequest(name, actions_[e][c]);
        got.push_back(ResultBits(call(step).step_env().data()));
      } else {
        *step.mutable_step_batch()->add_steps() =
            StepRequest(name, actions_[e][c]);
        v1::SessionResponse response = call(step);
        ASSERT_EQ(response.step_batch().results_size(), 1);
        got.push_back(ResultBits(response.step_batch().results(0).data()));
      }
    }
    stream->WritesDone();
    EXPECT_TRUE(stream->Finish().ok());
    EXPECT_EQ(got, expected_[e]) << "seed " << kSeeds[e];
  }
}

// A client whose writer runs ahead of its reader (the server runs a stream's
// requests one at a time, reading the next and writing earlier answers
// meanwhile): the steps of one env, each batch on the worker pool, still run
// in request order, every answer comes in order, and a half-close ends the
// stream only once all of them are written.
TEST_F(EquivalenceTest,
       PipelinedSessionMatchesTheCoreAndAnswersAllBeforeEnding) {
  ServiceOptions options;
  options.threads = 2;
  InProcess s(options);
  for (size_t e = 0; e < kSeeds.size(); ++e) {
    const std::string name = CreateEnv(*s.stub, Request());
    grpc::ClientContext context;
    auto stream = s.stub->Session(&context);
    std::thread writer([&] {
      uint64_t sequence = 0;
      v1::SessionRequest reset;
      reset.set_sequence(++sequence);
      *reset.mutable_reset_env() = ResetRequest(name, kSeeds[e]);
      EXPECT_TRUE(stream->Write(reset));
      for (size_t c = 0; c + 1 < expected_[e].size(); ++c) {
        v1::SessionRequest step;
        step.set_sequence(++sequence);
        *step.mutable_step_batch()->add_steps() =
            StepRequest(name, actions_[e][c]);
        EXPECT_TRUE(stream->Write(step));
      }
      stream->WritesDone();
    });
    Trajectory got;
    v1::SessionResponse response;
    for (uint64_t expected = 1; stream->Read(&response); ++expected) {
      EXPECT_EQ(response.sequence(), expected);
      EXPECT_FALSE(response.has_error()) << response.error().message();
      const v1::StepData& data = response.has_reset_env()
                                     ? response.reset_env().data()
                                     : response.step_batch().results(0).data();
      got.push_back(ResultBits(data));
    }
    writer.join();
    EXPECT_TRUE(stream->Finish().ok());
    EXPECT_EQ(got, expected_[e]) << "seed " << kSeeds[e];
  }
}

// AEC: after the last live agent of a cycle acted, the world stepped once;
// the rows of the agents stepped equal the parallel step's.
TEST_F(EquivalenceTest, StepAgentMatchesTheCoreOnceEveryAgentActed) {
  InProcess s;
  for (size_t e = 0; e < kSeeds.size(); ++e) {
    SCOPED_TRACE(kSeeds[e]);
    const std::string name = CreateEnv(*s.stub, Request());
    grpc::ClientContext context;
    v1::ResetEnvResponse reset;
    ASSERT_TRUE(
        s.stub->ResetEnv(&context, ResetRequest(name, kSeeds[e]), &reset).ok());
    v1::AecState state = reset.aec();
    size_t cycle = 0;
    int dead_steps = 0;
    while (!state.agents().empty()) {
      const int agent = state.agent_selection();
      v1::StepAgentRequest request;
      request.set_name(name);
      request.set_agent(agent);
      const bool done = state.terminations().data()[agent] != 0 ||
                        state.truncations().data()[agent] != 0;
      if (done) {
        ++dead_steps;
      } else {
        request.mutable_action()->set_discrete(actions_[e][cycle][agent]);
      }
      grpc::ClientContext step_context;
      v1::StepAgentResponse response;
      ASSERT_TRUE(s.stub->StepAgent(&step_context, request, &response).ok());
      state = response.aec();
      if (!state.world_stepped()) continue;
      ++cycle;
      ASSERT_LT(cycle, expected_[e].size());
      const v1::StepData& reference = reference_[e][cycle];
      for (int i = 0; i < kLanders; ++i) {
        if (reference.stepped().data()[i] == 0) continue;
        SCOPED_TRACE(::testing::Message()
                     << "cycle " << cycle << " agent " << i);
        const size_t row = static_cast<size_t>(i) * core::kObservationSize * 4;
        EXPECT_EQ(state.observations().data().substr(row, 48),
                  reference.observations().data().substr(row, 48));
        EXPECT_EQ(state.rewards().data().substr(i * 4, 4),
                  reference.rewards().data().substr(i * 4, 4));
        EXPECT_EQ(state.terminations().data()[i],
                  reference.terminations().data()[i]);
        EXPECT_EQ(state.truncations().data()[i],
                  reference.truncations().data()[i]);
        EXPECT_EQ(state.outcomes().data()[i], reference.outcomes().data()[i]);
        EXPECT_EQ(state.episode_returns().data().substr(i * 4, 4),
                  reference.episode_returns().data().substr(i * 4, 4));
      }
    }
    EXPECT_EQ(cycle + 1, expected_[e].size());
    EXPECT_GT(dead_steps, 0);
  }
}

}  // namespace
}  // namespace mll::service::testing

// Golden trajectories: fixed seeds and fixed action sequences must give the
// same bits, forever. Each scenario's observations, rewards, terminations,
// truncations, stepped flags, outcomes, episode returns and lengths, step by
// step, are hashed (FNV-1a 64 over their little-endian bytes) and compared
// with a hash recorded from the code as it was before the one-source-of-truth
// redesign. The core is checked directly, then the same trajectories through
// the server's unary StepEnv, StepBatch (steps and packed forms) and Session
// stream: one changed bit anywhere fails the test.
//
// A deliberate change of the simulation changes these hashes; the failure
// prints the new ones, to be pasted here in the same commit that explains why.
#include <cstdint>
#include <cstring>
#include <functional>
#include <memory>
#include <ostream>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/types/span.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

constexpr int kMaxCycles = 300;

struct Scenario {
  const char* label;
  uint64_t seed;
  int n_landers;
  bool continuous;
  bool enable_wind;
  bool terminate_on_damage;
  bool shared_reward;
  bool remove_on_damage;
  // Recorded before the redesign.
  uint64_t golden;
};

const Scenario kScenarios[] = {
    {"one_discrete", 0, 1, false, false, true, true, true,
     0xd8ac2a1caca23329ull},
    {"three_discrete_wind", 7, 3, false, true, false, false, true,
     0x2bb52ba537abe9adull},
    {"eight_continuous_wind", 12345, 8, true, true, false, true, true,
     0x0325211660fcdb88ull},
    {"two_continuous_wrecks", 3, 2, true, false, false, false, false,
     0x62a57bf923f3c9f1ull},
    {"thirty_two_discrete_wind", 99, 32, false, true, false, true, true,
     0x99750890fa4b7052ull},
};

// splitmix64: a fixed generator of actions, independent of the library.
void PrintTo(const Scenario& s, std::ostream* os) { *os << s.label; }

class Actions {
 public:
  explicit Actions(uint64_t seed) : state_(seed) {}
  uint64_t Next() {
    uint64_t z = (state_ += 0x9E3779B97F4A7C15ull);
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
    return z ^ (z >> 31);
  }
  // Biased towards the main engine so that episodes last a while.
  std::vector<int32_t> Discrete(int n) {
    constexpr int32_t kChoices[] = {0, 1, 2, 2, 2, 3, 2, 0};
    std::vector<int32_t> row(n);
    for (int32_t& action : row) action = kChoices[Next() % 8];
    return row;
  }
  // Values in [-1.2, 1.2): some outside the box, to exercise clipping.
  std::vector<float> Continuous(int n) {
    std::vector<float> row(2 * n);
    for (float& action : row) {
      action = static_cast<float>(Next() >> 40) / 16777216.0f * 2.4f - 1.2f;
    }
    return row;
  }

 private:
  uint64_t state_;
};

class Hash {
 public:
  void Add(const void* data, size_t size) {
    const auto* bytes = static_cast<const unsigned char*>(data);
    for (size_t i = 0; i < size; ++i) {
      value_ = (value_ ^ bytes[i]) * 0x100000001B3ull;
    }
  }
  void Add(const std::string& bytes) { Add(bytes.data(), bytes.size()); }
  template <typename T>
  void AddValues(const std::vector<T>& values) {
    Add(values.data(), values.size() * sizeof(T));
  }
  uint64_t value() const { return value_; }

 private:
  uint64_t value_ = 0xCBF29CE484222325ull;
};

core::EnvConfig CoreConfig(const Scenario& s) {
  core::EnvConfig config;
  config.n_landers = s.n_landers;
  config.continuous = s.continuous;
  config.enable_wind = s.enable_wind;
  config.terminate_on_damage = s.terminate_on_damage;
  config.shared_reward = s.shared_reward;
  config.remove_on_damage = s.remove_on_damage;
  config.max_cycles = kMaxCycles;
  return config;
}

v1::CreateEnvRequest WireConfig(const Scenario& s) {
  v1::CreateEnvRequest request = CreateRequest(s.n_landers);
  v1::EnvConfig* config = request.mutable_config();
  config->set_continuous(s.continuous);
  config->set_enable_wind(s.enable_wind);
  config->set_terminate_on_damage(s.terminate_on_damage);
  config->set_shared_reward(s.shared_reward);
  config->set_remove_on_damage(s.remove_on_damage);
  config->set_max_cycles(kMaxCycles);
  return request;
}

// The hash of one step's columns, in StepData's wire layout.
void HashCore(const core::StepResult& result, const core::Env& env,
              Hash* hash) {
  const int n = env.n_landers();
  hash->AddValues(result.observations);
  hash->AddValues(result.rewards);
  hash->AddValues(result.terminations);
  hash->AddValues(result.truncations);
  hash->AddValues(result.stepped);
  std::vector<uint8_t> outcomes;
  std::vector<float> returns;
  std::vector<int32_t> lengths;
  for (int i = 0; i < n; ++i) {
    outcomes.push_back(static_cast<uint8_t>(result.outcomes[i]));
    returns.push_back(static_cast<float>(env.episode_return(i)));
    lengths.push_back(static_cast<int32_t>(env.episode_length(i)));
  }
  hash->AddValues(outcomes);
  hash->AddValues(returns);
  hash->AddValues(lengths);
  const uint8_t over = result.episode_over ? 1 : 0;
  hash->Add(&over, 1);
}

// The per-agent columns StepData and PackedStepData share; with one env in
// a packed batch they have the same bytes.
template <typename Columns>
void HashAgentColumns(const Columns& data, Hash* hash) {
  for (const v1::Array* column :
       {&data.observations(), &data.rewards(), &data.terminations(),
        &data.truncations(), &data.stepped(), &data.outcomes(),
        &data.episode_returns(), &data.episode_lengths()}) {
    hash->Add(column->data());
  }
}

void HashWire(const v1::StepData& data, Hash* hash) {
  HashAgentColumns(data, hash);
  const uint8_t over = data.episode_over() ? 1 : 0;
  hash->Add(&over, 1);
}

// episode_over travels as a uint8 column in a packed batch.
void HashPacked(const v1::PackedStepData& data, Hash* hash) {
  HashAgentColumns(data, hash);
  hash->Add(data.episode_over().data());
}

struct Trajectory {
  uint64_t hash = 0;
  int steps = 0;
  std::vector<int> final_outcomes;
};

Trajectory CoreTrajectory(const Scenario& s) {
  absl::StatusOr<std::unique_ptr<core::Env>> env =
      core::Env::Create(CoreConfig(s));
  EXPECT_TRUE(env.ok()) << env.status();
  if (!env.ok()) return {};
  Actions actions(s.seed + 1000);
  core::StepResult result;
  Hash hash;
  (*env)->Reset(s.seed, &result);
  HashCore(result, **env, &hash);
  Trajectory trajectory;
  while (!result.episode_over) {
    absl::Status status;
    if (s.continuous) {
      const std::vector<float> row = actions.Continuous(s.n_landers);
      status = (*env)->Step(core::ActionsView{{}, row}, &result);
    } else {
      const std::vector<int32_t> row = actions.Discrete(s.n_landers);
      status = (*env)->Step(core::ActionsView{row, {}}, &result);
    }
    EXPECT_TRUE(status.ok()) << status;
    if (!status.ok()) break;
    HashCore(result, **env, &hash);
    ++trajectory.steps;
  }
  for (core::Outcome outcome : result.outcomes) {
    trajectory.final_outcomes.push_back(static_cast<int>(outcome));
  }
  trajectory.hash = hash.value();
  return trajectory;
}

v1::Array ActionArray(const Scenario& s, Actions* actions) {
  return s.continuous ? ContinuousActions(actions->Continuous(s.n_landers))
                      : DiscreteActions(actions->Discrete(s.n_landers));
}

// How one transport performs a reset and a step of the env `name`; each
// hashes the result's columns and says whether the episode is over.
struct Transport {
  std::function<bool(const std::string& name, uint64_t seed, Hash*)> reset;
  std::function<bool(const std::string& name, v1::Array actions, Hash*)> step;
};

uint64_t WireTrajectory(const Scenario& s, v1::MultiLunarLander::Stub& stub,
                        const Transport& transport) {
  const std::string name = CreateEnv(stub, WireConfig(s));
  Actions actions(s.seed + 1000);
  Hash hash;
  bool over = transport.reset(name, s.seed, &hash);
  for (int step = 0; !over && step <= kMaxCycles; ++step) {
    over = transport.step(name, ActionArray(s, &actions), &hash);
  }
  return hash.value();
}

bool ResetUnary(v1::MultiLunarLander::Stub& stub, const std::string& name,
                uint64_t seed, Hash* hash) {
  grpc::ClientContext context;
  v1::ResetEnvRequest request;
  request.set_name(name);
  request.set_seed(seed);
  v1::ResetEnvResponse response;
  const grpc::Status status = stub.ResetEnv(&context, request, &response);
  EXPECT_TRUE(status.ok()) << status.error_message();
  HashWire(response.data(), hash);
  return !status.ok() || response.data().episode_over();
}

class GoldenTrajectoryTest : public ::testing::TestWithParam<Scenario> {};

TEST_P(GoldenTrajectoryTest, CoreMatchesTheRecordedBits) {
  const Scenario& s = GetParam();
  const Trajectory trajectory = CoreTrajectory(s);
  EXPECT_GT(trajectory.steps, 20) << "the episode is too short to mean much";
  EXPECT_EQ(trajectory.hash, s.golden)
      << s.label << ": got " << absl::StrCat(absl::Hex(trajectory.hash))
      << " after " << trajectory.steps << " steps";
}

TEST_P(GoldenTrajectoryTest, EveryTransportMatchesTheRecordedBits) {
  const Scenario& s = GetParam();
  InProcess server;
  v1::MultiLunarLander::Stub& stub = *server.stub;

  const Transport unary = {
      [&](const std::string& name, uint64_t seed, Hash* hash) {
        return ResetUnary(stub, name, seed, hash);
      },
      [&](const std::string& name, v1::Array actions, Hash* hash) {
        grpc::ClientContext context;
        v1::StepEnvRequest request;
        request.set_name(name);
        *request.mutable_actions() = std::move(actions);
        v1::StepEnvResponse response;
        const grpc::Status status = stub.StepEnv(&context, request, &response);
        EXPECT_TRUE(status.ok()) << status.error_message();
        HashWire(response.data(), hash);
        return !status.ok() || response.data().episode_over();
      }};
  const Transport batch = {
      unary.reset, [&](const std::string& name, v1::Array actions, Hash* hash) {
        grpc::ClientContext context;
        v1::StepBatchRequest request;
        v1::StepEnvRequest* step = request.add_steps();
        step->set_name(name);
        *step->mutable_actions() = std::move(actions);
        v1::StepBatchResponse response;
        const grpc::Status status =
            stub.StepBatch(&context, request, &response);
        EXPECT_TRUE(status.ok()) << status.error_message();
        if (!status.ok() || response.results_size() != 1) return true;
        EXPECT_TRUE(response.results(0).has_data());
        HashWire(response.results(0).data(), hash);
        return response.results(0).data().episode_over();
      }};
  // The packed form hashes the packed columns' bytes: with one env they are
  // StepData's, except episode_over which travels as a uint8 column there.
  const Transport packed = {
      unary.reset, [&](const std::string& name, v1::Array actions, Hash* hash) {
        grpc::ClientContext context;
        v1::StepBatchRequest request;
        v1::PackedSteps* steps = request.mutable_packed();
        steps->add_names(name);
        *steps->mutable_actions() = std::move(actions);
        steps->mutable_actions()->mutable_shape()->Add(0);
        // Shape [1, n] or [1, n, 2]: a leading env dimension.
        auto* shape = steps->mutable_actions()->mutable_shape();
        for (int i = shape->size() - 1; i > 0; --i) {
          shape->Set(i, shape->Get(i - 1));
        }
        shape->Set(0, 1);
        v1::StepBatchResponse response;
        const grpc::Status status =
            stub.StepBatch(&context, request, &response);
        EXPECT_TRUE(status.ok()) << status.error_message();
        EXPECT_EQ(response.packed().errors_size(), 0);
        if (!status.ok() || response.packed().errors_size() != 0) return true;
        HashPacked(response.packed(), hash);
        return response.packed().episode_over().data() == std::string(1, '\1');
      }};

  // Every result of the stream is checked; the stream stays open over the
  // whole trajectory.
  grpc::ClientContext stream_context;
  auto stream = stub.Session(&stream_context);
  auto call = [&stream](const v1::SessionRequest& request) {
    v1::SessionResponse response;
    const bool answered = stream->Write(request) && stream->Read(&response);
    EXPECT_TRUE(answered && !response.has_error())
        << response.error().message();
    return response;
  };
  const Transport session = {
      [&](const std::string& name, uint64_t seed, Hash* hash) {
        v1::SessionRequest request;
        request.mutable_reset_env()->set_name(name);
        request.mutable_reset_env()->set_seed(seed);
        const v1::SessionResponse response = call(request);
        HashWire(response.reset_env().data(), hash);
        return response.has_error() ||
               response.reset_env().data().episode_over();
      },
      [&](const std::string& name, v1::Array actions, Hash* hash) {
        v1::SessionRequest request;
        request.mutable_step_env()->set_name(name);
        *request.mutable_step_env()->mutable_actions() = std::move(actions);
        const v1::SessionResponse response = call(request);
        HashWire(response.step_env().data(), hash);
        return response.has_error() ||
               response.step_env().data().episode_over();
      }};

  const std::pair<const char*, const Transport*> transports[] = {
      {"StepEnv", &unary},
      {"StepBatch.steps", &batch},
      {"StepBatch.packed", &packed},
      {"Session", &session}};
  for (const auto& [label, transport] : transports) {
    const uint64_t got = WireTrajectory(s, stub, *transport);
    EXPECT_EQ(got, s.golden) << s.label << " through " << label << ": got "
                             << absl::StrCat(absl::Hex(got));
  }
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());
}

INSTANTIATE_TEST_SUITE_P(Scenarios, GoldenTrajectoryTest,
                         ::testing::ValuesIn(kScenarios),
                         [](const ::testing::TestParamInfo<Scenario>& info) {
                           return std::string(info.param.label);
                         });

}  // namespace
}  // namespace mll::service::testing

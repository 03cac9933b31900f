// The packed (columnar) form of StepBatch: bit-identical to the `steps` form
// and to the in-process core (discrete and continuous, across auto-resets),
// the same on 1 and 2 threads, every request-level error and every per-env
// error with the code and message a StepEnv would give, failing envs leaving
// the other rows intact, and the form carried by a Session stream (which
// keeps its recent batches' envs: leases renewed, gone envs not found), and
// batches stepped by a handle (PackedSteps.handle): the same bits as by
// names, bad handles refused naming the field, gone envs not found.
#include <algorithm>
#include <chrono>
#include <cstring>
#include <random>
#include <string>
#include <thread>
#include <vector>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"
#include "mll/service/convert.h"
#include "mll/service/registry.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::HasSubstr;

constexpr int kLanders = 3;

// Env e's row of a packed response as the StepData a StepEnv would return,
// cut out of the columns byte for byte, so results of the two forms compare
// as serialized messages.
v1::StepData RowAsStepData(const v1::PackedStepData& packed, int e, int n) {
  auto cut = [](const v1::Array& column, size_t row_bytes, int e,
                std::vector<int> shape, v1::Array* out) {
    out->set_dtype(column.dtype());
    out->mutable_shape()->Assign(shape.begin(), shape.end());
    out->set_data(column.data().substr(e * row_bytes, row_bytes));
  };
  v1::StepData data;
  const size_t agents = static_cast<size_t>(n);
  cut(packed.observations(), agents * core::kObservationSize * 4, e,
      {n, core::kObservationSize}, data.mutable_observations());
  cut(packed.rewards(), agents * 4, e, {n}, data.mutable_rewards());
  cut(packed.terminations(), agents, e, {n}, data.mutable_terminations());
  cut(packed.truncations(), agents, e, {n}, data.mutable_truncations());
  cut(packed.stepped(), agents, e, {n}, data.mutable_stepped());
  cut(packed.outcomes(), agents, e, {n}, data.mutable_outcomes());
  cut(packed.episode_returns(), agents * 4, e, {n},
      data.mutable_episode_returns());
  cut(packed.episode_lengths(), agents * 4, e, {n},
      data.mutable_episode_lengths());
  data.set_episode_over(packed.episode_over().data().at(e) != 0);
  data.set_auto_reset(packed.auto_reset().data().at(e) != 0);
  int32_t cycles = 0;
  std::memcpy(&cycles, packed.cycles().data().data() + 4 * e, 4);
  data.set_cycles(cycles);
  return data;
}

// Every byte of env e's rows in every column is zero.
bool RowIsZero(const v1::PackedStepData& packed, int e, int n) {
  const std::string bits = RowAsStepData(packed, e, n).SerializeAsString();
  v1::StepData zero = RowAsStepData(packed, e, n);
  for (v1::Array* column :
       {zero.mutable_observations(), zero.mutable_rewards(),
        zero.mutable_terminations(), zero.mutable_truncations(),
        zero.mutable_stepped(), zero.mutable_outcomes(),
        zero.mutable_episode_returns(), zero.mutable_episode_lengths()}) {
    column->set_data(std::string(column->data().size(), '\0'));
  }
  zero.set_episode_over(false);
  zero.set_auto_reset(false);
  zero.set_cycles(0);
  return bits == zero.SerializeAsString();
}

v1::CreateEnvRequest Config(bool continuous, int n_landers = kLanders) {
  v1::CreateEnvRequest request = CreateRequest(n_landers);
  request.mutable_config()->set_continuous(continuous);
  request.mutable_config()->set_auto_reset(true);
  // Short episodes: the run crosses several auto-resets.
  request.mutable_config()->set_max_cycles(40);
  request.mutable_config()->set_terminate_on_damage(false);
  request.mutable_config()->set_shared_reward(false);
  return request;
}

grpc::Status Reset(v1::MultiLunarLander::Stub& stub, const std::string& name,
                   uint64_t seed) {
  grpc::ClientContext context;
  v1::ResetEnvRequest request;
  request.set_name(name);
  request.set_seed(seed);
  v1::ResetEnvResponse response;
  return stub.ResetEnv(&context, request, &response);
}

// Actions of env e at a cycle: int32 [n] or float32 [n, 2] values, drawn
// from a fixed generator (continuous values partly outside [-1, 1], which
// the core clips).
class ActionSource {
 public:
  ActionSource(bool continuous, int n) : continuous_(continuous), n_(n) {}
  std::vector<int32_t> Discrete() {
    std::vector<int32_t> row(n_);
    for (int32_t& a : row) a = std::uniform_int_distribution<int>(0, 3)(rng_);
    return row;
  }
  std::vector<float> Continuous() {
    std::vector<float> row(2 * n_);
    for (float& a : row) {
      a = std::uniform_real_distribution<float>(-1.2f, 1.2f)(rng_);
    }
    return row;
  }
  bool continuous() const { return continuous_; }

 private:
  bool continuous_;
  int n_;
  std::mt19937 rng_{42};
};

// One cycle's actions for `num_envs` envs, in both forms.
struct CycleActions {
  std::vector<std::vector<int32_t>> discrete;
  std::vector<std::vector<float>> continuous;

  v1::Array Row(int e) const {
    return continuous.empty() ? DiscreteActions(discrete[e])
                              : ContinuousActions(continuous[e]);
  }
  core::ActionsView View(int e) const {
    return continuous.empty() ? core::ActionsView{discrete[e], {}}
                              : core::ActionsView{{}, continuous[e]};
  }
  v1::Array Packed(int n) const {
    v1::Array array;
    const int num_envs = static_cast<int>(
        continuous.empty() ? discrete.size() : continuous.size());
    if (continuous.empty()) {
      std::vector<int32_t> all;
      for (const auto& row : discrete) {
        all.insert(all.end(), row.begin(), row.end());
      }
      const int shape[] = {num_envs, n};
      FillArray<int32_t>(all, shape, &array);
    } else {
      std::vector<float> all;
      for (const auto& row : continuous) {
        all.insert(all.end(), row.begin(), row.end());
      }
      const int shape[] = {num_envs, n, 2};
      FillArray<float>(all, shape, &array);
    }
    return array;
  }
};

CycleActions Draw(ActionSource& source, int num_envs) {
  CycleActions actions;
  for (int e = 0; e < num_envs; ++e) {
    if (source.continuous()) {
      actions.continuous.push_back(source.Continuous());
    } else {
      actions.discrete.push_back(source.Discrete());
    }
  }
  return actions;
}

v1::StepBatchRequest PackedRequest(const std::vector<std::string>& names,
                                   const v1::Array& actions) {
  v1::StepBatchRequest request;
  request.mutable_packed()->mutable_names()->Assign(names.begin(), names.end());
  *request.mutable_packed()->mutable_actions() = actions;
  return request;
}

class PackedEquivalenceTest : public ::testing::TestWithParam<bool> {};

// Per cycle: the core (with the service's auto-reset rule), the `steps` form
// and the packed form, each on its own envs with the same seeds; every row
// must serialize to the same bytes. The packed responses of the 1- and
// 2-thread servers must be equal too: 12 envs of 3 landers are enough for the
// 2-thread server to split a batch in two (a runner gets at least 16
// agent-steps).
TEST_P(PackedEquivalenceTest, MatchesStepsFormAndCoreOnOneAndTwoThreads) {
  const bool continuous = GetParam();
  const std::vector<uint64_t> seeds = {0,  3,  7,  11, 19, 12345,
                                       23, 29, 31, 37, 41, 43};
  const int num_envs = static_cast<int>(seeds.size());
  constexpr int kCycles = 130;

  absl::StatusOr<core::EnvConfig> config =
      EnvConfigFromProto(Config(continuous).config());
  ASSERT_TRUE(config.ok());
  std::vector<std::unique_ptr<core::Env>> core;
  core::StepResult result;
  for (uint64_t seed : seeds) {
    core.push_back(*core::Env::Create(*config));
    core.back()->Reset(seed, &result);
  }

  ActionSource source(continuous, kLanders);
  std::vector<CycleActions> cycles;
  for (int c = 0; c < kCycles; ++c) cycles.push_back(Draw(source, num_envs));

  // reference[c][e]: the serialized StepData of env e at cycle c.
  std::vector<std::vector<std::string>> reference(kCycles);
  int auto_resets = 0;
  for (int c = 0; c < kCycles; ++c) {
    for (int e = 0; e < num_envs; ++e) {
      v1::StepData data;
      if (core[e]->episode_over()) {
        core[e]->Reset(std::nullopt, &result);
        FillStepData(result, *core[e], /*auto_reset=*/true, &data);
        ++auto_resets;
      } else {
        ASSERT_TRUE(core[e]->Step(cycles[c].View(e), &result).ok());
        FillStepData(result, *core[e], /*auto_reset=*/false, &data);
      }
      reference[c].push_back(data.SerializeAsString());
    }
  }
  EXPECT_GE(auto_resets, num_envs) << "the run must cross auto-resets";

  std::vector<std::string> packed_bits[2];
  for (int threads : {1, 2}) {
    SCOPED_TRACE(threads);
    ServiceOptions options;
    options.threads = threads;
    InProcess s(options);
    std::vector<std::string> steps_envs, packed_envs;
    for (int e = 0; e < num_envs; ++e) {
      steps_envs.push_back(CreateEnv(*s.stub, Config(continuous)));
      packed_envs.push_back(CreateEnv(*s.stub, Config(continuous)));
      ASSERT_TRUE(Reset(*s.stub, steps_envs[e], seeds[e]).ok());
      ASSERT_TRUE(Reset(*s.stub, packed_envs[e], seeds[e]).ok());
    }
    for (int c = 0; c < kCycles; ++c) {
      SCOPED_TRACE(c);
      v1::StepBatchRequest steps;
      for (int e = 0; e < num_envs; ++e) {
        v1::StepEnvRequest* step = steps.add_steps();
        step->set_name(steps_envs[e]);
        *step->mutable_actions() = cycles[c].Row(e);
      }
      grpc::ClientContext steps_context;
      v1::StepBatchResponse steps_response;
      ASSERT_TRUE(
          s.stub->StepBatch(&steps_context, steps, &steps_response).ok());
      EXPECT_FALSE(steps_response.has_packed());

      grpc::ClientContext packed_context;
      v1::StepBatchResponse packed_response;
      ASSERT_TRUE(s.stub
                      ->StepBatch(&packed_context,
                                  PackedRequest(packed_envs,
                                                cycles[c].Packed(kLanders)),
                                  &packed_response)
                      .ok());
      ASSERT_EQ(packed_response.results_size(), 0);
      const v1::PackedStepData& packed = packed_response.packed();
      ASSERT_EQ(packed.errors_size(), 0) << packed.errors(0).error().message();
      EXPECT_THAT(
          packed.observations().shape(),
          ::testing::ElementsAre(num_envs, kLanders, core::kObservationSize));
      EXPECT_THAT(packed.cycles().shape(), ::testing::ElementsAre(num_envs));
      for (int e = 0; e < num_envs; ++e) {
        ASSERT_TRUE(steps_response.results(e).has_data());
        EXPECT_EQ(steps_response.results(e).data().SerializeAsString(),
                  reference[c][e])
            << "steps form, env " << e;
        EXPECT_EQ(RowAsStepData(packed, e, kLanders).SerializeAsString(),
                  reference[c][e])
            << "packed form, env " << e;
      }
      packed_bits[threads - 1].push_back(packed.SerializeAsString());
    }
  }
  EXPECT_EQ(packed_bits[0], packed_bits[1]);
}

INSTANTIATE_TEST_SUITE_P(DiscreteAndContinuous, PackedEquivalenceTest,
                         ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& info) {
                           return info.param ? "Continuous" : "Discrete";
                         });

class PackedErrorsTest : public ::testing::Test {
 protected:
  grpc::Status Batch(const v1::StepBatchRequest& request,
                     v1::StepBatchResponse* response) {
    grpc::ClientContext context;
    return s_.stub->StepBatch(&context, request, response);
  }
  // StepEnv's error for `name` with `actions`, as (code, message).
  grpc::Status StepEnvError(const std::string& name, const v1::Array& actions) {
    grpc::ClientContext context;
    v1::StepEnvRequest request;
    request.set_name(name);
    *request.mutable_actions() = actions;
    v1::StepEnvResponse response;
    return s_.stub->StepEnv(&context, request, &response);
  }
  void ExpectRejected(const v1::StepBatchRequest& request,
                      const std::string& message) {
    v1::StepBatchResponse response;
    const grpc::Status status = Batch(request, &response);
    EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT)
        << status.error_message();
    EXPECT_THAT(status.error_message(), HasSubstr(message));
  }

  InProcess s_;
};

v1::Array Int32Array(std::vector<int> shape, size_t count) {
  v1::Array array;
  FillArray<int32_t>(std::vector<int32_t>(count, 0), shape, &array);
  return array;
}

TEST_F(PackedErrorsTest, RequestLevelErrorsStepNothing) {
  const std::string a = CreateEnv(*s_.stub, Config(false));
  const std::string b = CreateEnv(*s_.stub, Config(false));
  ASSERT_TRUE(Reset(*s_.stub, a, 1).ok());
  ASSERT_TRUE(Reset(*s_.stub, b, 2).ok());
  const std::vector<std::string> names = {a, b};

  v1::StepBatchRequest both = PackedRequest(names, Int32Array({2, 3}, 6));
  v1::StepEnvRequest* step = both.add_steps();
  step->set_name(a);
  *step->mutable_actions() = DiscreteActions({0, 0, 0});
  ExpectRejected(both,
                 "steps, packed: both set (1 steps and a packed batch "
                 "of 2 envs)");

  v1::Array bytes;
  const int byte_shape[] = {2, 3};
  FillArray<uint8_t>(std::vector<uint8_t>(6, 0), byte_shape, &bytes);
  ExpectRejected(PackedRequest(names, bytes),
                 "packed.actions: dtype DTYPE_UINT8 is not allowed (expected "
                 "int32 [2, n_landers] for discrete actions or float32 [2, "
                 "n_landers, 2] for continuous ones");
  ExpectRejected(PackedRequest(names, v1::Array()),
                 "packed.actions: dtype DTYPE_UNSPECIFIED is not allowed");
  ExpectRejected(PackedRequest(names, Int32Array({3, 3}, 9)),
                 "packed.actions: shape [3, 3] of DTYPE_INT32 does not fit "
                 "(expected int32 [2, n_landers]");
  ExpectRejected(PackedRequest(names, Int32Array({6}, 6)),
                 "packed.actions: shape [6] of DTYPE_INT32 does not fit");
  ExpectRejected(PackedRequest(names, Int32Array({2, 33}, 66)),
                 "n_landers 1..32");
  ExpectRejected(PackedRequest(names, Int32Array({2, 0}, 0)),
                 "packed.actions: shape [2, 0] of DTYPE_INT32 does not fit");
  v1::Array floats;
  const int float_shape[] = {2, 3, 3};
  FillArray<float>(std::vector<float>(18, 0.0f), float_shape, &floats);
  ExpectRejected(PackedRequest(names, floats),
                 "packed.actions: shape [2, 3, 3] of DTYPE_FLOAT32 does not "
                 "fit");
  v1::Array short_data = Int32Array({2, 3}, 6);
  short_data.mutable_data()->resize(20);
  ExpectRejected(PackedRequest(names, short_data),
                 "packed.actions: data has 20 bytes but shape [2, 3] of "
                 "DTYPE_INT32 needs 24");
  ExpectRejected(PackedRequest({a, b, a}, Int32Array({3, 3}, 9)),
                 "packed.names[2]: " + a +
                     " also appears at packed.names[0]; the envs of one batch "
                     "must be distinct");

  // Nothing was stepped by any of the above.
  v1::Env env;
  grpc::ClientContext context;
  v1::GetEnvRequest get;
  get.set_name(a);
  ASSERT_TRUE(s_.stub->GetEnv(&context, get, &env).ok());
  EXPECT_EQ(env.cycles(), 0);

  // An empty packed batch is a valid batch of nothing.
  v1::StepBatchResponse response;
  ASSERT_TRUE(Batch(PackedRequest({}, Int32Array({0, 3}, 0)), &response).ok());
  EXPECT_TRUE(response.has_packed());
  EXPECT_THAT(response.packed().observations().shape(),
              ::testing::ElementsAre(0, 3, core::kObservationSize));
}

// Each failing env gets StepEnv's code and message (its field names moved
// under `packed.`), its rows stay zero, and the other envs step as if alone.
TEST_F(PackedErrorsTest, FailingEnvsGetStepEnvsErrorAndLeaveOthersIntact) {
  const std::string good0 = CreateEnv(*s_.stub, Config(false));
  const std::string other_n = CreateEnv(*s_.stub, Config(false, 2));
  const std::string other_type = CreateEnv(*s_.stub, Config(true));
  const std::string unreset = CreateEnv(*s_.stub, Config(false));
  v1::CreateEnvRequest short_config = CreateRequest(kLanders);
  short_config.mutable_config()->set_max_cycles(1);
  const std::string over = CreateEnv(*s_.stub, short_config);
  const std::string bad_value = CreateEnv(*s_.stub, Config(false));
  const std::string good1 = CreateEnv(*s_.stub, Config(false));
  // Twins of the good envs, stepped by StepEnv for the expected rows.
  const std::string twin0 = CreateEnv(*s_.stub, Config(false));
  const std::string twin1 = CreateEnv(*s_.stub, Config(false));
  for (const auto& [name, seed] :
       std::vector<std::pair<std::string, uint64_t>>{{good0, 5},
                                                     {twin0, 5},
                                                     {good1, 6},
                                                     {twin1, 6},
                                                     {other_n, 1},
                                                     {other_type, 1},
                                                     {over, 1},
                                                     {bad_value, 1}}) {
    ASSERT_TRUE(Reset(*s_.stub, name, seed).ok());
  }
  ASSERT_TRUE(
      StepEnvError(over, DiscreteActions({0, 0, 0})).ok());  // Now over.

  const std::vector<std::string> names = {good0,          other_n,   other_type,
                                          "envs/missing", "bogus",   unreset,
                                          over,           bad_value, good1};
  std::vector<std::vector<int32_t>> rows = {{2, 1, 3}, {0, 0, 0}, {0, 0, 0},
                                            {0, 0, 0}, {0, 0, 0}, {0, 0, 0},
                                            {0, 0, 0}, {0, 7, 0}, {3, 2, 2}};
  CycleActions actions;
  actions.discrete = rows;

  v1::StepBatchResponse response;
  ASSERT_TRUE(
      Batch(PackedRequest(names, actions.Packed(kLanders)), &response).ok());
  const v1::PackedStepData& packed = response.packed();

  // What StepEnv says for each failing env with its row of actions.
  struct Expected {
    int index;
    grpc::StatusCode code;
    std::string message;
  };
  auto step_env = [&](int e) { return StepEnvError(names[e], actions.Row(e)); };
  auto renamed = [](const std::string& message, const std::string& from,
                    const std::string& to) {
    EXPECT_EQ(message.rfind(from, 0), 0u) << message;
    return to + message.substr(from.size());
  };
  std::vector<Expected> expected;
  for (int e : {1, 2}) {  // Layout mismatch: StepEnv's `actions` check.
    const grpc::Status status = step_env(e);
    expected.push_back({e, status.error_code(),
                        renamed(status.error_message(), "actions",
                                "packed.actions[" + std::to_string(e) + "]")});
  }
  for (int e : {3, 4}) {  // Unknown, malformed name: StepEnv's `name` check.
    const grpc::Status status = step_env(e);
    expected.push_back({e, status.error_code(),
                        renamed(status.error_message(), "name",
                                "packed.names[" + std::to_string(e) + "]")});
  }
  for (int e : {5, 6, 7}) {  // Not reset, over, bad value: the env's word.
    const grpc::Status status = step_env(e);
    expected.push_back({e, status.error_code(), status.error_message()});
  }
  ASSERT_EQ(packed.errors_size(), static_cast<int>(expected.size()));
  const grpc::StatusCode codes[] = {grpc::StatusCode::INVALID_ARGUMENT,
                                    grpc::StatusCode::INVALID_ARGUMENT,
                                    grpc::StatusCode::NOT_FOUND,
                                    grpc::StatusCode::INVALID_ARGUMENT,
                                    grpc::StatusCode::FAILED_PRECONDITION,
                                    grpc::StatusCode::FAILED_PRECONDITION,
                                    grpc::StatusCode::INVALID_ARGUMENT};
  for (size_t i = 0; i < expected.size(); ++i) {
    SCOPED_TRACE(names[expected[i].index]);
    EXPECT_EQ(expected[i].code, codes[i]);
    EXPECT_EQ(packed.errors(i).index(), expected[i].index);
    EXPECT_EQ(packed.errors(i).error().code(), expected[i].code);
    EXPECT_EQ(packed.errors(i).error().message(), expected[i].message);
    EXPECT_TRUE(RowIsZero(packed, expected[i].index, kLanders));
  }
  EXPECT_THAT(packed.errors(0).error().message(),
              HasSubstr("packed.actions[1]: shape [3] does not match [2]"));
  EXPECT_THAT(packed.errors(1).error().message(),
              HasSubstr("packed.actions[2]: dtype DTYPE_INT32 does not match "
                        "DTYPE_FLOAT32"));

  for (const auto& [e, twin] :
       std::vector<std::pair<int, std::string>>{{0, twin0}, {8, twin1}}) {
    grpc::ClientContext context;
    v1::StepEnvRequest request;
    request.set_name(twin);
    *request.mutable_actions() = actions.Row(e);
    v1::StepEnvResponse alone;
    ASSERT_TRUE(s_.stub->StepEnv(&context, request, &alone).ok());
    EXPECT_EQ(RowAsStepData(packed, e, kLanders).SerializeAsString(),
              alone.data().SerializeAsString());
    EXPECT_FALSE(RowIsZero(packed, e, kLanders));
  }
}

TEST(PackedSessionTest, SessionCarriesAPackedBatch) {
  InProcess s;
  const std::string twin = CreateEnv(*s.stub, Config(true));
  ASSERT_TRUE(Reset(*s.stub, twin, 9).ok());

  grpc::ClientContext context;
  auto stream = s.stub->Session(&context);
  v1::SessionRequest create;
  create.set_sequence(1);
  *create.mutable_create_env() = Config(true);
  v1::SessionResponse response;
  ASSERT_TRUE(stream->Write(create) && stream->Read(&response));
  const std::string name = response.env().name();
  v1::SessionRequest reset;
  reset.set_sequence(2);
  reset.mutable_reset_env()->set_name(name);
  reset.mutable_reset_env()->set_seed(9);
  ASSERT_TRUE(stream->Write(reset) && stream->Read(&response));

  CycleActions actions;
  actions.continuous = {{0.9f, -0.7f, 0.3f, 1.0f, -1.0f, 0.6f}};
  v1::SessionRequest step;
  step.set_sequence(3);
  *step.mutable_step_batch() = PackedRequest({name}, actions.Packed(kLanders));
  ASSERT_TRUE(stream->Write(step) && stream->Read(&response));
  EXPECT_EQ(response.sequence(), 3u);
  ASSERT_FALSE(response.has_error()) << response.error().message();
  ASSERT_TRUE(response.step_batch().has_packed());
  EXPECT_EQ(response.step_batch().packed().errors_size(), 0);

  grpc::ClientContext twin_context;
  v1::StepEnvRequest request;
  request.set_name(twin);
  *request.mutable_actions() = actions.Row(0);
  v1::StepEnvResponse alone;
  ASSERT_TRUE(s.stub->StepEnv(&twin_context, request, &alone).ok());
  EXPECT_EQ(RowAsStepData(response.step_batch().packed(), 0, kLanders)
                .SerializeAsString(),
            alone.data().SerializeAsString());

  // A request-level error comes back as the response's error; the stream
  // goes on.
  v1::SessionRequest bad = step;
  bad.set_sequence(4);
  bad.mutable_step_batch()->mutable_packed()->clear_actions();
  ASSERT_TRUE(stream->Write(bad) && stream->Read(&response));
  EXPECT_EQ(response.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(response.error().message(), HasSubstr("packed.actions: dtype"));
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());
}

// A Session keeps its request and response messages from one request to the
// next (their storage reused): each answer must still be what that request
// alone gets, whatever the stream carried before: a batch of other envs or
// sizes, item errors, the other form, a request without an op.
TEST(PackedSessionTest, EachAnswerIsItsRequestsAloneWhateverCameBefore) {
  InProcess s;
  grpc::ClientContext context;
  auto stream = s.stub->Session(&context);
  uint64_t sequence = 0;
  const auto call = [&](v1::SessionRequest request) {
    request.set_sequence(++sequence);
    v1::SessionResponse response;
    EXPECT_TRUE(stream->Write(request) && stream->Read(&response));
    EXPECT_EQ(response.sequence(), sequence);
    return response;
  };
  // Envs a and b on the stream, twins stepped by unary StepBatch calls.
  std::vector<std::string> on_stream, twins;
  for (int e = 0; e < 2; ++e) {
    v1::SessionRequest create;
    *create.mutable_create_env() = Config(false);
    on_stream.push_back(call(create).env().name());
    twins.push_back(CreateEnv(*s.stub, Config(false)));
    ASSERT_TRUE(Reset(*s.stub, on_stream[e], 5 + e).ok());
    ASSERT_TRUE(Reset(*s.stub, twins[e], 5 + e).ok());
  }
  const std::string missing = "envs/00000000000000000000000000000000";
  ActionSource source(false, kLanders);
  // Env indices per batch (-1: a name no env has).
  const std::vector<std::vector<int>> batches = {{0, 1}, {1}, {0, -1},
                                                 {1, 0}, {0}, {0, 1}};
  for (size_t b = 0; b < batches.size(); ++b) {
    SCOPED_TRACE(b);
    const std::vector<int>& envs = batches[b];
    const CycleActions actions = Draw(source, static_cast<int>(envs.size()));
    std::vector<std::string> stream_names, twin_names;
    for (int e : envs) {
      stream_names.push_back(e < 0 ? missing : on_stream[e]);
      twin_names.push_back(e < 0 ? missing : twins[e]);
    }
    v1::SessionRequest step;
    *step.mutable_step_batch() =
        PackedRequest(stream_names, actions.Packed(kLanders));
    const v1::SessionResponse answer = call(step);
    ASSERT_TRUE(answer.has_step_batch()) << answer.error().message();

    grpc::ClientContext unary_context;
    v1::StepBatchResponse alone;
    ASSERT_TRUE(
        s.stub
            ->StepBatch(&unary_context,
                        PackedRequest(twin_names, actions.Packed(kLanders)),
                        &alone)
            .ok());
    EXPECT_EQ(answer.step_batch().SerializeAsString(),
              alone.SerializeAsString());
    const bool has_missing =
        std::find(envs.begin(), envs.end(), -1) != envs.end();
    EXPECT_EQ(answer.step_batch().packed().errors_size(), has_missing ? 1 : 0);

    if (b == 2) {  // Between packed batches: a request without an op ...
      const v1::SessionResponse empty = call(v1::SessionRequest());
      EXPECT_EQ(empty.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
      EXPECT_THAT(empty.error().message(), HasSubstr("op: not set"));
      // ... and the `steps` form, answered in its own form.
      v1::SessionRequest steps;
      v1::StepEnvRequest* item = steps.mutable_step_batch()->add_steps();
      item->set_name(missing);
      *item->mutable_actions() = DiscreteActions(source.Discrete());
      const v1::SessionResponse steps_answer = call(steps);
      EXPECT_FALSE(steps_answer.step_batch().has_packed());
      ASSERT_EQ(steps_answer.step_batch().results_size(), 1);
      EXPECT_EQ(steps_answer.step_batch().results(0).error().code(),
                grpc::StatusCode::NOT_FOUND);
    }
  }
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());
}

// A Session steps a batch naming the same envs as a recent one through the
// envs it found then: each such step must still renew the envs' leases, and
// an env deleted or reclaimed since must be NOT_FOUND, as to a fresh call.
TEST(PackedSessionTest, RepeatedBatchesRenewLeasesAndMissGoneEnvs) {
  ServiceOptions options;
  options.idle_timeout = absl::Milliseconds(800);
  InProcess s(options);
  grpc::ClientContext context;
  auto stream = s.stub->Session(&context);
  uint64_t sequence = 0;
  ActionSource source(false, kLanders);
  // The packed answer to stepping `names` on the stream.
  const auto step = [&](const std::vector<std::string>& names) {
    v1::SessionRequest request;
    request.set_sequence(++sequence);
    *request.mutable_step_batch() = PackedRequest(
        names, Draw(source, static_cast<int>(names.size())).Packed(kLanders));
    v1::SessionResponse response;
    EXPECT_TRUE(stream->Write(request) && stream->Read(&response));
    EXPECT_FALSE(response.has_error()) << response.error().message();
    return response.step_batch().packed();
  };
  const auto not_found = [](const v1::PackedStepData& packed) {
    std::vector<int> indices;
    for (const v1::IndexedItemError& error : packed.errors()) {
      EXPECT_EQ(error.error().code(), grpc::StatusCode::NOT_FOUND)
          << error.error().message();
      indices.push_back(error.index());
    }
    return indices;
  };
  std::vector<std::string> names;
  for (int e = 0; e < 3; ++e) {
    names.push_back(CreateEnv(*s.stub, Config(false)));
    ASSERT_TRUE(Reset(*s.stub, names[e], 20 + e).ok());
  }
  const std::string& a = names[0];
  const std::string& b = names[1];
  const std::string& c = names[2];
  EXPECT_THAT(not_found(step({a, b, c})), ::testing::IsEmpty());
  // Only a and b are stepped (the first batch's list but for c, then that
  // list over and over) for 2.5 idle timeouts: c is reclaimed, a and b stay.
  const auto start = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - start <
         std::chrono::milliseconds(2000)) {
    ASSERT_THAT(not_found(step({a, b})), ::testing::IsEmpty());
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  // The first list again: c was reclaimed meanwhile.
  const v1::PackedStepData reclaimed = step({a, b, c});
  EXPECT_THAT(not_found(reclaimed), ::testing::ElementsAre(2));
  EXPECT_THAT(reclaimed.errors(0).error().message(),
              HasSubstr("packed.names[2]: " + c + " was reclaimed"));
  // b deleted by another call: the next [a, b] misses it.
  grpc::ClientContext delete_context;
  v1::DeleteEnvRequest remove;
  remove.set_name(b);
  v1::DeleteEnvResponse removed;
  ASSERT_TRUE(s.stub->DeleteEnv(&delete_context, remove, &removed).ok());
  EXPECT_THAT(not_found(step({a, b})), ::testing::ElementsAre(1));
  EXPECT_THAT(not_found(step({a, b})), ::testing::ElementsAre(1));
  EXPECT_THAT(not_found(step({a})), ::testing::IsEmpty());
  stream->WritesDone();
  EXPECT_TRUE(stream->Finish().ok());
}

// ---------------------------------------------------------------- handles

// A Session stream with its own envs' twins: requests numbered, answers
// checked against their sequence.
class HandleSession {
 public:
  explicit HandleSession(v1::MultiLunarLander::Stub& stub)
      : stream_(stub.Session(&context_)) {}
  ~HandleSession() {
    stream_->WritesDone();
    EXPECT_TRUE(stream_->Finish().ok());
  }
  v1::SessionResponse Call(v1::SessionRequest request) {
    request.set_sequence(++sequence_);
    v1::SessionResponse response;
    EXPECT_TRUE(stream_->Write(request) && stream_->Read(&response));
    EXPECT_EQ(response.sequence(), sequence_);
    return response;
  }
  // A packed StepBatch of `names` (empty: by the handle alone) with handle
  // `handle` (0: none).
  v1::SessionResponse Step(const std::vector<std::string>& names,
                           uint32_t handle, const v1::Array& actions) {
    v1::SessionRequest request;
    *request.mutable_step_batch() = PackedRequest(names, actions);
    request.mutable_step_batch()->mutable_packed()->set_handle(handle);
    return Call(request);
  }

 private:
  grpc::ClientContext context_;
  std::unique_ptr<
      grpc::ClientReaderWriter<v1::SessionRequest, v1::SessionResponse>>
      stream_;
  uint64_t sequence_ = 0;
};

class PackedHandleTest : public ::testing::TestWithParam<bool> {};

// Stepped by a handle (declared by the first step, then the actions alone),
// on a stream over loopback TCP and through shared memory, of the mll_server
// binary, envs give the same bits as their twins stepped by names in unary
// calls, across auto-resets.
TEST_P(PackedHandleTest, StepByHandleMatchesStepByNamesBitForBit) {
  const bool continuous = GetParam();
  const std::vector<uint64_t> seeds = {1, 4, 9, 16, 25};
  const int num_envs = static_cast<int>(seeds.size());
  constexpr int kCycles = 100;
  ServerProcess process({"--threads=2"});
  const int port = process.WaitForPort();
  ASSERT_GT(port, 0);
  const std::shared_ptr<grpc::Channel> channel = grpc::CreateChannel(
      "127.0.0.1:" + std::to_string(port), grpc::InsecureChannelCredentials());
  const std::unique_ptr<v1::MultiLunarLander::Stub> stub =
      v1::MultiLunarLander::NewStub(channel);
  // Three copies of the envs: stepped by names (unary), by a handle on a
  // stream, and by a handle through shared memory.
  std::vector<std::string> by_names, on_stream, in_memory;
  for (int e = 0; e < num_envs; ++e) {
    for (auto* copy : {&by_names, &on_stream, &in_memory}) {
      copy->push_back(CreateEnv(*stub, Config(continuous)));
      ASSERT_TRUE(Reset(*stub, copy->back(), seeds[e]).ok());
    }
  }
  HandleSession stream(*stub);
  SharedMemorySession memory(*stub);
  ASSERT_FALSE(memory.Attach().has_error());
  ActionSource source(continuous, kLanders);
  int auto_resets = 0;
  for (int c = 0; c < kCycles; ++c) {
    SCOPED_TRACE(c);
    const v1::Array actions = Draw(source, num_envs).Packed(kLanders);
    grpc::ClientContext context;
    v1::StepBatchResponse reference;
    ASSERT_TRUE(
        stub->StepBatch(&context, PackedRequest(by_names, actions), &reference)
            .ok());
    ASSERT_EQ(reference.packed().errors_size(), 0);
    const bool declare = c == 0;
    const v1::SessionResponse streamed = stream.Step(
        declare ? on_stream : std::vector<std::string>(), 3, actions);
    ASSERT_FALSE(streamed.has_error()) << streamed.error().message();
    EXPECT_EQ(streamed.step_batch().SerializeAsString(),
              reference.SerializeAsString());
    v1::SessionRequest request;
    *request.mutable_step_batch() = PackedRequest(
        declare ? in_memory : std::vector<std::string>(), actions);
    request.mutable_step_batch()->mutable_packed()->set_handle(64);
    const v1::SessionResponse mapped = memory.Call(request);
    ASSERT_FALSE(mapped.has_error()) << mapped.error().message();
    EXPECT_EQ(mapped.step_batch().SerializeAsString(),
              reference.SerializeAsString());
    for (char reset : reference.packed().auto_reset().data()) {
      auto_resets += reset != 0;
    }
  }
  EXPECT_GE(auto_resets, num_envs) << "the run must cross auto-resets";
}

INSTANTIATE_TEST_SUITE_P(DiscreteAndContinuous, PackedHandleTest,
                         ::testing::Bool(),
                         [](const ::testing::TestParamInfo<bool>& info) {
                           return info.param ? "Continuous" : "Discrete";
                         });

// Bad handles are refused with the field named and nothing stepped; an env
// of a declared batch that is gone is NOT_FOUND as when named; handles are
// the session's; requests with names and no handle go on as before.
TEST(PackedHandleErrorsTest, BadHandlesGoneEnvsAndOldStyleRequests) {
  InProcess s;
  std::vector<std::string> names;
  for (int e = 0; e < 3; ++e) {
    names.push_back(CreateEnv(*s.stub, Config(false)));
    ASSERT_TRUE(Reset(*s.stub, names[e], 30 + e).ok());
  }
  const auto cycles_of = [&](const std::string& name) {
    grpc::ClientContext context;
    v1::GetEnvRequest request;
    request.set_name(name);
    v1::Env env;
    EXPECT_TRUE(s.stub->GetEnv(&context, request, &env).ok());
    return env.cycles();
  };
  const v1::Array three = Int32Array({3, kLanders}, 3 * kLanders);
  HandleSession session(*s.stub);

  // Not declared on this session.
  v1::SessionResponse answer = session.Step({}, 5, three);
  EXPECT_EQ(answer.error().code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(answer.error().message(),
              HasSubstr("packed.handle: 5 is not declared on this session"));
  // Out of range, with names or without.
  answer = session.Step(names, 65, three);
  EXPECT_EQ(answer.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(answer.error().message(),
              HasSubstr("packed.handle: 65 is out of range (allowed: 0 for "
                        "none, 1..64)"));
  // A declaration with a repeated name declares nothing.
  answer = session.Step({names[0], names[0], names[1]}, 6, three);
  EXPECT_EQ(answer.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(answer.error().message(), HasSubstr("packed.names[1]"));
  EXPECT_EQ(session.Step({}, 6, three).error().code(),
            grpc::StatusCode::NOT_FOUND);
  for (const std::string& name : names) EXPECT_EQ(cycles_of(name), 0);

  // Declared: stepped by names, then by the handle alone.
  answer = session.Step(names, 1, three);
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  EXPECT_EQ(answer.step_batch().packed().errors_size(), 0);
  answer = session.Step({}, 1, three);
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  for (const std::string& name : names) EXPECT_EQ(cycles_of(name), 2);
  // The wrong number of actions for the handle's envs.
  answer = session.Step({}, 1, Int32Array({2, kLanders}, 2 * kLanders));
  EXPECT_EQ(answer.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(answer.error().message(),
              HasSubstr("num_envs = the envs declared as packed.handle 1 = 3"));
  for (const std::string& name : names) EXPECT_EQ(cycles_of(name), 2);

  // An old-style request (names, no handle) in between.
  answer = session.Step({names[2], names[0]}, 0,
                        Int32Array({2, kLanders}, 2 * kLanders));
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  EXPECT_EQ(cycles_of(names[0]), 3);
  EXPECT_EQ(cycles_of(names[1]), 2);

  // An env of the batch deleted: NOT_FOUND for its row, naming it as if it
  // had been named; the others step.
  {
    grpc::ClientContext context;
    v1::DeleteEnvRequest remove;
    remove.set_name(names[1]);
    v1::DeleteEnvResponse removed;
    ASSERT_TRUE(s.stub->DeleteEnv(&context, remove, &removed).ok());
  }
  answer = session.Step({}, 1, three);
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  const v1::PackedStepData& packed = answer.step_batch().packed();
  ASSERT_EQ(packed.errors_size(), 1);
  EXPECT_EQ(packed.errors(0).index(), 1);
  EXPECT_EQ(packed.errors(0).error().code(), grpc::StatusCode::NOT_FOUND);
  EXPECT_THAT(packed.errors(0).error().message(),
              HasSubstr("packed.names[1]: " + names[1] + " does not exist"));
  EXPECT_TRUE(RowIsZero(packed, 1, kLanders));
  EXPECT_EQ(cycles_of(names[0]), 4);
  EXPECT_EQ(cycles_of(names[2]), 4);

  // Declared anew as other envs, the handle steps those.
  answer = session.Step({names[2]}, 1, Int32Array({1, kLanders}, kLanders));
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  answer = session.Step({}, 1, Int32Array({1, kLanders}, kLanders));
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  EXPECT_EQ(cycles_of(names[0]), 4);
  EXPECT_EQ(cycles_of(names[2]), 6);

  // Handles are the session's: another stream has none, and a unary call
  // cannot carry one.
  {
    HandleSession other(*s.stub);
    answer = other.Step({}, 1, Int32Array({1, kLanders}, kLanders));
    EXPECT_EQ(answer.error().code(), grpc::StatusCode::NOT_FOUND);
  }
  v1::StepBatchRequest unary =
      PackedRequest({names[0]}, Int32Array({1, kLanders}, kLanders));
  unary.mutable_packed()->set_handle(1);
  grpc::ClientContext context;
  v1::StepBatchResponse response;
  const grpc::Status status = s.stub->StepBatch(&context, unary, &response);
  EXPECT_EQ(status.error_code(), grpc::StatusCode::INVALID_ARGUMENT);
  EXPECT_THAT(status.error_message(),
              HasSubstr("packed.handle: 1 is set on a unary StepBatch"));
  EXPECT_EQ(cycles_of(names[0]), 4);
}

// A session's declared batches hold at most kMaxDeclaredEnvs envs together:
// a declaration past it is RESOURCE_EXHAUSTED; declaring a handle anew
// frees its old envs.
TEST(PackedHandleErrorsTest, DeclaredEnvsAreBounded) {
  InProcess s;
  constexpr size_t kMax = SessionBatches::kMaxDeclaredEnvs;
  // Names of no env: each row fails NOT_FOUND, but the batch is declared.
  const auto names_from = [](size_t first, size_t count) {
    std::vector<std::string> names;
    for (size_t k = first; k < first + count; ++k) {
      names.push_back(absl::StrFormat("envs/%032x", k));
    }
    return names;
  };
  const auto actions = [](size_t count) {
    return Int32Array({static_cast<int>(count), 1}, count);
  };
  HandleSession session(*s.stub);
  const size_t most = kMax - 10;
  v1::SessionResponse answer =
      session.Step(names_from(0, most), 1, actions(most));
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  EXPECT_EQ(answer.step_batch().packed().errors_size(), static_cast<int>(most));
  answer = session.Step(names_from(most, 11), 2, actions(11));
  EXPECT_EQ(answer.error().code(), grpc::StatusCode::RESOURCE_EXHAUSTED);
  EXPECT_THAT(
      answer.error().message(),
      HasSubstr(absl::StrCat("packed.handle: declaring 2 as 11 envs "
                             "would make this session's declared "
                             "batches hold ",
                             kMax + 1, " envs; allowed: at most ", kMax)));
  EXPECT_EQ(session.Step({}, 2, actions(11)).error().code(),
            grpc::StatusCode::NOT_FOUND);
  // Handle 1 declared anew as fewer envs: room for handle 2.
  answer = session.Step(names_from(0, 5), 1, actions(5));
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
  answer = session.Step(names_from(most, 11), 2, actions(11));
  ASSERT_FALSE(answer.has_error()) << answer.error().message();
}

// Steps by a handle renew the leases of its envs, as steps by names do.
TEST(PackedHandleErrorsTest, HandleStepsRenewLeases) {
  ServiceOptions options;
  options.idle_timeout = absl::Milliseconds(800);
  InProcess s(options);
  std::vector<std::string> names;
  for (int e = 0; e < 3; ++e) {
    names.push_back(CreateEnv(*s.stub, Config(false)));
    ASSERT_TRUE(Reset(*s.stub, names[e], 40 + e).ok());
  }
  HandleSession session(*s.stub);
  const v1::Array two = Int32Array({2, kLanders}, 2 * kLanders);
  ASSERT_FALSE(session.Step({names[0], names[1]}, 7, two).has_error());
  // Only the handle's envs are stepped for 2.5 idle timeouts: the third is
  // reclaimed, the handle's stay.
  const auto start = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - start <
         std::chrono::milliseconds(2000)) {
    const v1::SessionResponse answer = session.Step({}, 7, two);
    ASSERT_FALSE(answer.has_error()) << answer.error().message();
    ASSERT_EQ(answer.step_batch().packed().errors_size(), 0)
        << answer.step_batch().packed().errors(0).error().message();
    std::this_thread::sleep_for(std::chrono::milliseconds(100));
  }
  const v1::SessionResponse gone =
      session.Step({names[2]}, 0, Int32Array({1, kLanders}, kLanders));
  ASSERT_EQ(gone.step_batch().packed().errors_size(), 1);
  EXPECT_THAT(gone.step_batch().packed().errors(0).error().message(),
              HasSubstr("was reclaimed"));
}

}  // namespace
}  // namespace mll::service::testing

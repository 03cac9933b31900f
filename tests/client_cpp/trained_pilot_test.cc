// The trained pilot's .qnet reader and forward pass (against a network small
// enough to check by hand, and the shipped network against the Q-values
// examples/dqn's numpy reader computes), and mll_cli play --policy=trained
// flying the shipped network through the real mll_server.
#include "trained_pilot.h"

#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <memory>
#include <string>
#include <vector>

#include "absl/strings/str_cat.h"
#include "cli_runner.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server_process.h"

namespace mll::client {
namespace {

using ::testing::ElementsAre;
using ::testing::HasSubstr;

std::string U32(uint32_t value) {
  std::string bytes(4, '\0');
  for (int i = 0; i < 4; ++i) bytes[i] = static_cast<char>(value >> (8 * i));
  return bytes;
}

std::string F32(float value) {
  uint32_t bits;
  std::memcpy(&bits, &value, sizeof(bits));
  return U32(bits);
}

std::string WriteFile(const std::string& name, const std::string& bytes) {
  const std::string path = absl::StrCat(::testing::TempDir(), "/", name);
  std::ofstream(path, std::ios::binary) << bytes;
  return path;
}

// 2 inputs -> 2 hidden (ReLU) -> 3 Q-values.
std::string SmallNetwork() {
  std::string bytes = "MLLQ" + U32(1) + U32(2) + U32(2) + U32(2) + U32(3);
  for (float w : {1.0f, -1.0f, 0.5f, 2.0f}) bytes += F32(w);  // [2][2]
  for (float b : {0.0f, -10.0f}) bytes += F32(b);
  for (float w : {1.0f, 0.0f, 0.0f, 1.0f, -1.0f, -1.0f}) bytes += F32(w);
  for (float b : {0.0f, 0.0f, 3.0f}) bytes += F32(b);
  return bytes;
}

TEST(QNetworkTest, ForwardPassOfASmallNetwork) {
  absl::StatusOr<QNetwork> network =
      QNetwork::Load(WriteFile("small.qnet", SmallNetwork()));
  ASSERT_TRUE(network.ok()) << network.status();
  EXPECT_THAT(network->sizes(), ElementsAre(2, 2, 3));
  // hidden = relu([3 - 1, 1.5 + 2 - 10]) = [2, 0]; q = [2, 0, 3 - 2].
  const std::vector<float> obs = {3.0f, 1.0f};
  EXPECT_THAT(network->QValues(obs), ElementsAre(2.0f, 0.0f, 1.0f));
  EXPECT_EQ(network->Greedy(obs), 0);
  // hidden = relu([-1, 2 + 6 - 10]) = [0, 0]; q = [0, 0, 3].
  EXPECT_EQ(network->Greedy(std::vector<float>{-1.0f, 0.0f}), 2);
}

// Version 2, neighbors seen by closeness: 12 inputs -> 2 Q-values, the first
// the input [8] (the nearest neighbor's x), the second the input [11] (the
// second neighbor's y), as the network sees them.
std::string ClosenessNetwork() {
  std::string bytes = "MLLQ" + U32(2) + U32(1) + U32(1) + U32(12) + U32(2);
  for (int out = 0; out < 2; ++out) {
    for (int in = 0; in < 12; ++in) {
      bytes +=
          F32((out == 0 && in == 8) || (out == 1 && in == 11) ? 1.0f : 0.0f);
    }
  }
  return bytes + F32(0.0f) + F32(0.0f);
}

TEST(QNetworkTest, ANetworkOfVersion2SeesNeighborsByCloseness) {
  absl::StatusOr<QNetwork> network =
      QNetwork::Load(WriteFile("closeness.qnet", ClosenessNetwork()));
  ASSERT_TRUE(network.ok()) << network.status();
  EXPECT_EQ(network->neighbor_input(), QNetwork::NeighborInput::kCloseness);
  // The nearest neighbor 1 world unit to the right (x offsets are in units of
  // W/2 = 10), the second 6 units below (y offsets: H/2 = 20/3).
  std::vector<float> obs(12, 0.0f);
  obs[8] = -0.1f;
  obs[11] = 0.9f;
  std::vector<float> q = network->QValues(obs);
  EXPECT_NEAR(q[0], -std::exp(-0.5f), 1e-6);
  EXPECT_NEAR(q[1], std::exp(-3.0f), 1e-6);
  // No neighbors: zero offsets are seen as 0, not as a neighbor on top.
  q = network->QValues(std::vector<float>(12, 0.0f));
  EXPECT_THAT(q, ElementsAre(0.0f, 0.0f));
  // A version 1 file sees offsets as they are.
  absl::StatusOr<QNetwork> small =
      QNetwork::Load(WriteFile("small.qnet", SmallNetwork()));
  ASSERT_TRUE(small.ok()) << small.status();
  EXPECT_EQ(small->neighbor_input(), QNetwork::NeighborInput::kOffset);
}

TEST(QNetworkTest, DamagedFilesAreRefusedNamingWhatIsWrong) {
  const std::string good = SmallNetwork();
  const struct {
    std::string bytes;
    std::string message;
  } cases[] = {
      {"XXXX" + good.substr(4), "not a .qnet file"},
      {good.substr(0, 4) + U32(7) + good.substr(8),
       "version 7; allowed: 1 or 2"},
      {good.substr(0, 4) + U32(2) + U32(9) + good.substr(8),
       "inputs 9; allowed: 0 (offset) or 1 (closeness)"},
      {good.substr(0, 4) + U32(2) + U32(1) + good.substr(8),
       "2 inputs; a network that sees neighbors by closeness has 12"},
      {good.substr(0, 8) + U32(99) + good.substr(12), "99 layers"},
      {good.substr(0, good.size() - 4), "layer sizes [2, 2, 3] need"},
      {good.substr(0, 12) + U32(0) + good.substr(16), "layer of size 0"},
  };
  for (const auto& c : cases) {
    absl::StatusOr<QNetwork> network =
        QNetwork::Load(WriteFile("bad.qnet", c.bytes));
    ASSERT_FALSE(network.ok()) << c.message;
    EXPECT_EQ(network.status().code(), absl::StatusCode::kInvalidArgument);
    EXPECT_THAT(network.status().message(), HasSubstr(c.message));
  }
  EXPECT_EQ(QNetwork::Load("/nonexistent/x.qnet").status().code(),
            absl::StatusCode::kNotFound);
}

// The same observations and Q-values as examples/dqn/tests/test_qnet_file.py
// (numpy's forward pass of the shipped file).
TEST(QNetworkTest, ShippedNetworkMatchesNumpy) {
  absl::StatusOr<QNetwork> network = QNetwork::Load(MLL_SHIPPED_QNET);
  ASSERT_TRUE(network.ok()) << network.status();
  EXPECT_THAT(network->sizes(), ElementsAre(12, 256, 64, 4));
  EXPECT_EQ(network->neighbor_input(), QNetwork::NeighborInput::kCloseness);
  const std::vector<std::vector<float>> observations = {
      {0.0f, 1.4f, 0.0f, 0.0f, 0.0f, 0.0f, 0, 0, 0, 0, 0, 0},
      {0.3f, 0.5f, -0.2f, -0.4f, 0.1f, 0.05f, 0, 0, 0.2f, -0.3f, 0.1f, 0.0f},
      {-0.5f, 0.2f, 0.3f, -0.1f, -0.2f, -0.1f, 1, 0, -0.4f, 0.6f, 0, 1},
  };
  const std::vector<std::vector<float>> expected = {
      {0.675502f, 0.639469f, 0.624980f, 0.667969f},
      {-2.340131f, -1.910421f, -2.127151f, -1.987894f},
      {0.409632f, 0.406116f, 0.444865f, 0.358943f},
  };
  const int greedy[] = {0, 1, 2};
  for (size_t k = 0; k < observations.size(); ++k) {
    const std::vector<float> q = network->QValues(observations[k]);
    ASSERT_EQ(q.size(), 4u);
    for (int a = 0; a < 4; ++a) EXPECT_NEAR(q[a], expected[k][a], 2e-6);
    EXPECT_EQ(network->Greedy(observations[k]), greedy[k]);
  }
}

// The network built into the tools is the shipped file, byte for byte.
TEST(QNetworkTest, BuiltInNetworkIsTheShippedFile) {
  absl::StatusOr<QNetwork> built_in = QNetwork::Shipped();
  absl::StatusOr<QNetwork> file = QNetwork::Load(MLL_SHIPPED_QNET);
  ASSERT_TRUE(built_in.ok()) << built_in.status();
  ASSERT_TRUE(file.ok()) << file.status();
  EXPECT_EQ(built_in->sizes(), file->sizes());
  const std::vector<float> observation = {0.1f, 0.9f, -0.2f, -0.3f, 0.05f, 0,
                                          0,    0,    0.3f,  0.2f,  -0.1f, 0};
  EXPECT_EQ(built_in->QValues(observation), file->QValues(observation));
}

TEST(TrainedPilotCliTest, PlayFliesTheShippedNetwork) {
  absl::StatusOr<std::unique_ptr<ServerProcess>> server =
      ServerProcess::Start(MLL_SERVER_PATH);
  ASSERT_TRUE(server.ok()) << server.status();
  const std::string address = absl::StrCat("--address=", (*server)->address());
  const CommandResult played = RunCli(
      {"play", "--policy=trained", "--n_landers=3", "--episodes=3",
       "--seed=3000000", "--max_cycles=2000", "--terminate_on_damage=false",
       "--remove_on_damage=true", address});
  ASSERT_EQ(played.exit_code, 0) << played.err;
  EXPECT_THAT(played.out, HasSubstr("\"landed\""));
  const CommandResult missing = RunCli(
      {"play", "--policy=trained", "--weights=/nonexistent/x.qnet", address});
  EXPECT_EQ(missing.exit_code, 2);
  EXPECT_THAT(missing.err, HasSubstr("/nonexistent/x.qnet"));
  const CommandResult continuous =
      RunCli({"play", "--policy=trained", "--continuous", address});
  EXPECT_EQ(continuous.exit_code, 2);
  EXPECT_THAT(continuous.err, HasSubstr("discrete"));
}

}  // namespace
}  // namespace mll::client

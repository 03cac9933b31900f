// The trained DQN pilot of examples/dqn: a Q-network read from a .qnet file
// (the format of examples/dqn/mll_dqn/qnet_file.py: "MLLQ", version, how the
// network sees the neighbors (version 2), layer sizes, then float32 weights
// and biases, all little-endian) and flown greedily, plus PlayPilot, which
// mll_cli's play uses to fly either it or a RemotePilot.
#ifndef MLL_CLIENT_TOOLS_TRAINED_PILOT_H_
#define MLL_CLIENT_TOOLS_TRAINED_PILOT_H_

#include <cstdint>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/types/span.h"
#include "core_bridge.h"
#include "mll/client.h"

namespace mll::client {

// An MLP with ReLU between layers and a linear output layer.
class QNetwork {
 public:
  // How the network sees an observation's two nearest neighbors [8:12].
  enum class NeighborInput : uint32_t {
    // The offsets as the environment writes them.
    kOffset = 0,
    // Each neighbor's direction times exp(-distance / 2 world units), 0 for
    // an absent one (mll_dqn.agent.neighbor_closeness).
    kCloseness = 1,
  };

  // INVALID_ARGUMENT naming the file and what is wrong with it (NOT_FOUND if
  // it cannot be read).
  static absl::StatusOr<QNetwork> Load(const std::string& path);
  // The same for a .qnet file's bytes; `what` names them in messages.
  static absl::StatusOr<QNetwork> Parse(const std::string& data,
                                        const std::string& what);
  // The network shipped with the tools (examples/dqn/trained.qnet, built into
  // the binary so an installed mll_cli needs no data file).
  static absl::StatusOr<QNetwork> Shipped();

  // Q-values of one observation (input_size() floats).
  std::vector<float> QValues(absl::Span<const float> observation) const;
  // The action of the highest Q-value (the first on a tie, as numpy's argmax).
  int Greedy(absl::Span<const float> observation) const;

  const std::vector<int>& sizes() const { return sizes_; }
  int input_size() const { return sizes_.front(); }
  NeighborInput neighbor_input() const { return neighbor_input_; }

 private:
  NeighborInput neighbor_input_ = NeighborInput::kOffset;
  std::vector<int> sizes_;
  // Per layer: weight [out][in] row-major, then bias [out].
  std::vector<std::vector<float>> layers_;
};

// One env's pilot for play: a RemotePilot (heuristic, random) or the trained
// network, which flies discrete actions only.
class PlayPilot {
 public:
  explicit PlayPilot(RemotePilot remote) : remote_(std::move(remote)) {}
  PlayPilot(std::shared_ptr<const QNetwork> network, int n_landers)
      : network_(std::move(network)), discrete_(n_landers, 0) {}

  // As RemotePilot::Act: actions for the agents still active after `last`.
  Actions Act(const StepData& last);

 private:
  std::optional<RemotePilot> remote_;
  std::shared_ptr<const QNetwork> network_;
  std::vector<int32_t> discrete_;
};

}  // namespace mll::client

#endif  // MLL_CLIENT_TOOLS_TRAINED_PILOT_H_

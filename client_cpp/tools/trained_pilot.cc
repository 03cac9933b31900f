#include "trained_pilot.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <fstream>
#include <iterator>
#include <utility>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_join.h"
#include "shipped_qnet.h"

namespace mll::client {
namespace {

constexpr char kMagic[] = "MLLQ";
// Version 1 has no neighbor-input field (its networks see offsets).
constexpr uint32_t kVersion = 2;
// As qnet_file.py: bounds what a damaged header can ask for.
constexpr uint32_t kMaxLayers = 16;
constexpr uint32_t kMaxLayerSize = 1 << 16;

// Little-endian, whatever the host's byte order.
uint32_t ReadU32(const std::string& data, size_t offset) {
  uint32_t value = 0;
  for (int i = 3; i >= 0; --i) {
    value = (value << 8) | static_cast<uint8_t>(data[offset + i]);
  }
  return value;
}

float ReadF32(const std::string& data, size_t offset) {
  const uint32_t bits = ReadU32(data, offset);
  float value;
  std::memcpy(&value, &bits, sizeof(value));
  return value;
}

// As qnet_file.py's NEIGHBOR_SCALE and NEIGHBOR_REACH: world units per
// observation unit of a neighbor's offset (W/2, H/2), and the distance over
// which closeness falls by e.
constexpr float kNeighborScale[2] = {10.0f, 20.0f / 3.0f};
constexpr float kNeighborReach = 2.0f;

// Replaces each neighbor's offset in x[8:12] by its direction times
// exp(-distance / kNeighborReach); an absent neighbor (zero offset) stays 0.
void SeeNeighborsByCloseness(std::vector<float>& x) {
  for (int slot = 8; slot < kRemoteObservationSize; slot += 2) {
    const float dx = x[slot] * kNeighborScale[0];
    const float dy = x[slot + 1] * kNeighborScale[1];
    const float distance = std::sqrt(dx * dx + dy * dy);
    const float closeness =
        distance > 0 ? std::exp(-distance / kNeighborReach) / distance : 0.0f;
    x[slot] = dx * closeness;
    x[slot + 1] = dy * closeness;
  }
}

}  // namespace

absl::StatusOr<QNetwork> QNetwork::Load(const std::string& path) {
  std::ifstream file(path, std::ios::binary);
  if (!file) {
    return absl::NotFoundError(
        absl::StrCat("weights: cannot read \"", path, "\" (a .qnet file)"));
  }
  const std::string data((std::istreambuf_iterator<char>(file)),
                         std::istreambuf_iterator<char>());
  return Parse(data, absl::StrCat("\"", path, "\""));
}

absl::StatusOr<QNetwork> QNetwork::Shipped() {
  return Parse(std::string(reinterpret_cast<const char*>(kShippedQnet),
                           kShippedQnetSize),
               "the built-in network (examples/dqn/trained.qnet)");
}

absl::StatusOr<QNetwork> QNetwork::Parse(const std::string& data,
                                         const std::string& what) {
  auto invalid = [&what](auto&&... parts) {
    return absl::InvalidArgumentError(
        absl::StrCat("weights: ", what, " ", parts...));
  };
  if (data.size() < 12 || data.compare(0, 4, kMagic) != 0) {
    return invalid("is not a .qnet file (no \"MLLQ\" header)");
  }
  const uint32_t version = ReadU32(data, 4);
  if (version != 1 && version != kVersion) {
    return invalid("has version ", version, "; allowed: 1 or ", kVersion);
  }
  QNetwork network;
  size_t offset = 8;
  if (version >= 2) {
    if (data.size() < 16) return invalid("ends inside its header");
    const uint32_t inputs = ReadU32(data, 8);
    if (inputs > static_cast<uint32_t>(NeighborInput::kCloseness)) {
      return invalid("has inputs ", inputs,
                     "; allowed: 0 (offset) or 1 (closeness)");
    }
    network.neighbor_input_ = static_cast<NeighborInput>(inputs);
    offset = 12;
  }
  const uint32_t n_layers = ReadU32(data, offset);
  offset += 4;
  if (n_layers < 1 || n_layers > kMaxLayers ||
      data.size() < offset + 4 * (n_layers + 1)) {
    return invalid("has ", n_layers, " layers; allowed: 1..", kMaxLayers);
  }
  size_t expected = offset + 4 * (n_layers + 1);
  for (uint32_t i = 0; i <= n_layers; ++i, offset += 4) {
    const uint32_t size = ReadU32(data, offset);
    if (size < 1 || size > kMaxLayerSize) {
      return invalid("has a layer of size ", size, "; allowed: 1..",
                     kMaxLayerSize);
    }
    network.sizes_.push_back(static_cast<int>(size));
    if (i > 0) expected += size_t{4} * size * (network.sizes_[i - 1] + 1);
  }
  if (network.neighbor_input_ == NeighborInput::kCloseness &&
      network.sizes_.front() != kRemoteObservationSize) {
    return invalid("has ", network.sizes_.front(),
                   " inputs; a network that sees neighbors by closeness has ",
                   kRemoteObservationSize);
  }
  if (data.size() != expected) {
    return invalid("has ", data.size(), " bytes; layer sizes [",
                   absl::StrJoin(network.sizes_, ", "), "] need ", expected);
  }
  for (uint32_t l = 0; l < n_layers; ++l) {
    const size_t count =
        size_t{1} * network.sizes_[l + 1] * (network.sizes_[l] + 1);
    std::vector<float>& layer = network.layers_.emplace_back(count);
    for (size_t k = 0; k < count; ++k, offset += 4) {
      layer[k] = ReadF32(data, offset);
    }
  }
  return network;
}

std::vector<float> QNetwork::QValues(
    absl::Span<const float> observation) const {
  std::vector<float> x(observation.begin(), observation.end());
  x.resize(sizes_.front(), 0.0f);
  if (neighbor_input_ == NeighborInput::kCloseness) SeeNeighborsByCloseness(x);
  for (size_t l = 0; l < layers_.size(); ++l) {
    const int n_in = sizes_[l];
    const int n_out = sizes_[l + 1];
    const float* weight = layers_[l].data();
    const float* bias = weight + static_cast<size_t>(n_out) * n_in;
    std::vector<float> y(n_out);
    for (int o = 0; o < n_out; ++o) {
      float sum = bias[o];
      for (int i = 0; i < n_in; ++i) sum += weight[o * n_in + i] * x[i];
      // ReLU between layers, none after the last.
      y[o] = l + 1 < layers_.size() ? std::max(sum, 0.0f) : sum;
    }
    x = std::move(y);
  }
  return x;
}

int QNetwork::Greedy(absl::Span<const float> observation) const {
  const std::vector<float> q = QValues(observation);
  return static_cast<int>(std::max_element(q.begin(), q.end()) - q.begin());
}

Actions PlayPilot::Act(const StepData& last) {
  if (remote_) return remote_->Act(last);
  std::fill(discrete_.begin(), discrete_.end(), 0);
  const int n = std::min<int>(last.n_landers, discrete_.size());
  for (int agent = 0; agent < n; ++agent) {
    if (!last.stepped[agent] || !last.active(agent)) continue;
    discrete_[agent] = network_->Greedy(last.observation(agent));
  }
  return Actions::Discrete(discrete_);
}

}  // namespace mll::client

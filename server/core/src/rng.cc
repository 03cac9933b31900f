#include "rng.h"

namespace mll::core {
namespace internal {

double Rng::Uniform01() {
  // 2^-53: the top 53 bits fill a double's mantissa exactly.
  constexpr double kTwoPowMinus53 = 1.0 / 9007199254740992.0;
  return static_cast<double>(engine_() >> 11) * kTwoPowMinus53;
}

double Rng::Uniform(double low, double high) {
  return low + (high - low) * Uniform01();
}

int64_t Rng::Integer(int64_t low, int64_t high) {
  const uint64_t span = static_cast<uint64_t>(high - low) + 1;
  // Reject the top partial block of the 64-bit range so every value is
  // equally likely.
  const uint64_t limit = UINT64_MAX - UINT64_MAX % span;
  uint64_t draw = engine_();
  while (draw >= limit) draw = engine_();
  return low + static_cast<int64_t>(draw % span);
}

}  // namespace internal
}  // namespace mll::core

// The generator of one environment. std::mt19937_64 is fully specified by the
// C++ standard; the conversions to doubles and bounded integers are our own
// because std::uniform_real_distribution and friends are
// implementation-defined. Same seed -> same numbers on every platform.
#ifndef MLL_CORE_SRC_RNG_H_
#define MLL_CORE_SRC_RNG_H_

#include <cstdint>
#include <random>

namespace mll::core {
namespace internal {

class Rng {
 public:
  explicit Rng(uint64_t seed = 0) : engine_(seed) {}

  void Seed(uint64_t seed) { engine_.seed(seed); }

  // Uniform in [0, 1) from the top 53 bits of one draw.
  double Uniform01();
  // Uniform in [low, high).
  double Uniform(double low, double high);
  // Uniform integer in [low, high], both inclusive, without modulo bias.
  int64_t Integer(int64_t low, int64_t high);

 private:
  std::mt19937_64 engine_;
};

}  // namespace internal
}  // namespace mll::core

#endif  // MLL_CORE_SRC_RNG_H_

"""The core's generator in Python (server/core/src/rng.{h,cc}), for the trajectory fidelity test.

std::mt19937_64 as the C++ standard specifies it (seeding, twist, tempering), plus the core's
own conversions: Uniform01 = (draw >> 11) * 2^-53 and Uniform(low, high) = low + (high - low) *
Uniform01. numpy's Generator.uniform computes the same low + (high - low) * u from its own
53-bit double, so GymnasiumRandom below can stand in for gymnasium's env.np_random and make
Gymnasium's LunarLander consume exactly the numbers our core draws.
"""

import numpy as np

_N = 312
_M = 156
_MATRIX_A = 0xB5026F5AA96619E9
_UPPER = 0xFFFFFFFF80000000  # Top 33 bits.
_LOWER = 0x7FFFFFFF  # Bottom 31 bits.
_MASK64 = (1 << 64) - 1


class MT19937_64:
    def __init__(self, seed=5489):  # 5489: the standard's default seed.
        state = [seed & _MASK64]
        for i in range(1, _N):
            previous = state[-1]
            state.append((6364136223846793005 * (previous ^ (previous >> 62)) + i) & _MASK64)
        self._state = state
        self._index = _N

    def _twist(self):
        s = self._state
        for i in range(_N):
            y = (s[i] & _UPPER) | (s[(i + 1) % _N] & _LOWER)
            s[i] = s[(i + _M) % _N] ^ (y >> 1) ^ (_MATRIX_A if y & 1 else 0)
        self._index = 0

    def next_uint64(self):
        if self._index >= _N:
            self._twist()
        y = self._state[self._index]
        self._index += 1
        y ^= (y >> 29) & 0x5555555555555555
        y ^= (y << 17) & 0x71D67FFFEDA60000
        y ^= (y << 37) & 0xFFF7EEE000000000
        y ^= y >> 43
        return y

    def uniform01(self):
        return (self.next_uint64() >> 11) * (1.0 / 9007199254740992.0)

    def uniform(self, low, high):
        return low + (high - low) * self.uniform01()


class GymnasiumRandom:
    """Stands in for gymnasium's env.unwrapped.np_random: LunarLander's reset and step only call
    .uniform(low, high, size=None), which draw here in our core's order and arithmetic."""

    def __init__(self, seed):
        self.generator = MT19937_64(seed)
        self.draws = 0

    def uniform(self, low=0.0, high=1.0, size=None):
        if size is None:
            self.draws += 1
            return self.generator.uniform(low, high)
        count = int(np.prod(size))
        self.draws += count
        values = [self.generator.uniform(low, high) for _ in range(count)]
        return np.array(values, dtype=np.float64).reshape(size)

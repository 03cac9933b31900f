// The result columns of VectorEnv's Reset, Step and Recv, declared once:
// VectorEnv's arrays (vector_env.cc, and its accessors of the same names in
// mll/vector_env.h) and the C interface's column table (native/
// vector_c_api.cc, from which the Python client derives its arrays) are made
// from this list.
#ifndef MLL_CLIENT_SRC_RESULT_COLUMNS_H_
#define MLL_CLIENT_SRC_RESULT_COLUMNS_H_

#include <cstdint>
#include <type_traits>

#include "mll/client.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::client {
namespace internal {

// X(name, element type, per_agent, width): column `name` holds, per row,
// n_landers entries (per_agent) or one, of `width` elements each.
#define MLL_RESULT_COLUMNS(X)                                         \
  X(observations, float, true, ::mll::client::kRemoteObservationSize) \
  X(rewards, float, true, 1)                                          \
  X(terminations, uint8_t, true, 1)                                   \
  X(truncations, uint8_t, true, 1)                                    \
  X(active, uint8_t, true, 1)                                         \
  X(outcomes, uint8_t, true, 1)                                       \
  X(episode_returns, float, true, 1)                                  \
  X(episode_lengths, int32_t, true, 1)                                \
  X(auto_reset, uint8_t, false, 1)                                    \
  X(episode_over, uint8_t, false, 1)                                  \
  X(env_ids, int32_t, false, 1)

// The wire dtype of a column's element type.
template <typename T>
constexpr v1::DType DTypeOf() {
  static_assert(std::is_same_v<T, float> || std::is_same_v<T, uint8_t> ||
                    std::is_same_v<T, int32_t>,
                "a result column holds float, uint8_t or int32_t");
  if constexpr (std::is_same_v<T, float>) return v1::DTYPE_FLOAT32;
  if constexpr (std::is_same_v<T, uint8_t>) return v1::DTYPE_UINT8;
  return v1::DTYPE_INT32;
}

struct ResultColumn {
  const char* name;
  v1::DType dtype;
  bool per_agent;
  int width;
};

inline constexpr ResultColumn kResultColumns[] = {
#define MLL_RESULT_COLUMN_ENTRY(name, type, per_agent, width) \
  {#name, DTypeOf<type>(), per_agent, width},
    MLL_RESULT_COLUMNS(MLL_RESULT_COLUMN_ENTRY)
#undef MLL_RESULT_COLUMN_ENTRY
};

inline constexpr int kResultColumnCount =
    static_cast<int>(sizeof(kResultColumns) / sizeof(kResultColumns[0]));

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_RESULT_COLUMNS_H_

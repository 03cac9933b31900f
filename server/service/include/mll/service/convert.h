// The one place where proto (mll.v1) and core (mll) types meet: configs,
// specs, step results, AEC state, actions and statuses. Handlers call these
// and contain no conversion of their own.
#ifndef MLL_SERVICE_CONVERT_H_
#define MLL_SERVICE_CONVERT_H_

#include <cstdint>
#include <cstring>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/types/span.h"
#include "grpcpp/support/status.h"
#include "mll/core/aec_env.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::service {

// Arrays travel as little-endian bytes; copying them verbatim is only right
// on a little-endian host, which is all the platforms we build for.
static_assert(__BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__,
              "proto Array bytes are little-endian; add byte swapping");

// The one mapping from the core's absl::Status to the wire's grpc::Status.
// The canonical codes share their numbers; anything else becomes INTERNAL.
grpc::Status ToGrpcStatus(const absl::Status& status);

// A failed item of a batch or a Session request, with the status's code and
// message.
void FillItemError(const absl::Status& status, v1::ItemError* out);

// The element type tag of T in a proto Array.
template <typename T>
constexpr v1::DType DTypeOf();
template <>
constexpr v1::DType DTypeOf<float>() {
  return v1::DTYPE_FLOAT32;
}
template <>
constexpr v1::DType DTypeOf<uint8_t>() {
  return v1::DTYPE_UINT8;
}
template <>
constexpr v1::DType DTypeOf<int32_t>() {
  return v1::DTYPE_INT32;
}

// "[3, 12]".
std::string ShapeString(absl::Span<const int> shape);

// Writes `values` as a `shape`-d array of T into `out`.
template <typename T>
void FillArray(absl::Span<const T> values, absl::Span<const int> shape,
               v1::Array* out) {
  out->set_dtype(DTypeOf<T>());
  out->mutable_shape()->Assign(shape.begin(), shape.end());
  out->mutable_data()->assign(reinterpret_cast<const char*>(values.data()),
                              values.size() * sizeof(T));
}

// INVALID_ARGUMENT naming `field` unless `array` has exactly dtype T and
// `shape`, with the matching number of bytes. `what` explains the expected
// shape to the reader of the error, e.g. "one int32 per agent of n_landers =
// 3".
absl::Status CheckArray(const v1::Array& array, v1::DType dtype,
                        absl::Span<const int> shape, absl::string_view field,
                        absl::string_view what);

// The first two checks of CheckArray, on a dtype and shape that need not
// belong to one Array message (e.g. one row of a packed batch's actions).
absl::Status CheckDTypeAndShape(int got_dtype, absl::Span<const int> got_shape,
                                v1::DType dtype, absl::Span<const int> shape,
                                absl::string_view field,
                                absl::string_view what);

// The elements of `array` if it is a T array of `shape` (see CheckArray).
template <typename T>
absl::StatusOr<std::vector<T>> DecodeArray(const v1::Array& array,
                                           absl::Span<const int> shape,
                                           absl::string_view field) {
  absl::Status status =
      CheckArray(array, DTypeOf<T>(), shape, field, "as the server sends it");
  if (!status.ok()) return status;
  std::vector<T> values(array.data().size() / sizeof(T));
  std::memcpy(values.data(), array.data().data(), array.data().size());
  return values;
}

// Proto config -> core config, every unset field taking the core's default,
// validated by the core (INVALID_ARGUMENT naming the field).
absl::StatusOr<core::EnvConfig> EnvConfigFromProto(const v1::EnvConfig& proto);

// Core config (+ the service's auto_reset) -> proto with every field set.
v1::EnvConfig EnvConfigToProto(const core::EnvConfig& config, bool auto_reset);

// The per-agent observation and action spaces of `config`.
v1::Space ObservationSpace();
v1::Space ActionSpace(const core::EnvConfig& config);

// Storage for actions decoded from the wire; view() borrows it.
struct ActionBuffer {
  std::vector<int32_t> discrete;
  std::vector<float> continuous;
  core::ActionsView view() const {
    return core::ActionsView{discrete, continuous};
  }
};

// Checks the dtype and shape of `array` for `config` (int32 [n_landers] or
// float32 [n_landers, 2]) and copies it into `out`. Values are the core's to
// check. Errors are INVALID_ARGUMENT naming `field`.
absl::Status ParseActions(const v1::Array& array, const core::EnvConfig& config,
                          absl::string_view field, ActionBuffer* out);

// The dtype/shape check of ParseActions alone, with its messages: whether
// one env's actions of `dtype` and `shape` fit `config`.
absl::Status CheckActionLayout(int dtype, absl::Span<const int> shape,
                               const core::EnvConfig& config,
                               absl::string_view field);

// The actions of a packed StepBatch (`PackedSteps.actions`), decoded once for
// the whole batch: int32 [num_envs, n_landers] or float32 [num_envs,
// n_landers, 2].
class PackedActions {
 public:
  // INVALID_ARGUMENT naming `packed.actions` and the expected shape unless
  // the array is one of the two forms above with `num_envs` envs (those of
  // packed.names, or of the batch declared as packed.handle), n_landers in
  // 1..32 and the matching byte count.
  static absl::StatusOr<PackedActions> Parse(const v1::PackedSteps& packed,
                                             int num_envs);

  int n_landers() const { return n_landers_; }
  bool continuous() const { return continuous_; }
  // OK, or the error a StepEnv with env e's row would give (under the field
  // name `packed.actions[e]`) when the env's config does not match.
  absl::Status CheckFits(int e, const core::EnvConfig& config) const;
  // Env e's actions.
  core::ActionsView Row(int e) const;

 private:
  int n_landers_ = 0;
  bool continuous_ = false;
  ActionBuffer values_;
};

// The AEC action of a StepAgentRequest: nullopt when absent (a dead step).
absl::StatusOr<std::optional<core::AgentAction>> ParseAgentAction(
    const v1::StepAgentRequest& request, const core::EnvConfig& config);

// A column of T elements kept as the little-endian bytes of a proto `bytes`
// field. Elements go in with memcpy, by element index, never through a T*
// cast of the bytes (the storage holds chars). Copies share the storage;
// writes to different elements may come from different threads.
template <typename T>
class ByteColumn {
 public:
  ByteColumn() = default;
  explicit ByteColumn(std::string* bytes) : bytes_(bytes) {}

  void Store(size_t index, T value) const {
    std::memcpy(&(*bytes_)[index * sizeof(T)], &value, sizeof(T));
  }
  // `values` at elements [first, first + values.size()).
  void StoreAll(size_t first, absl::Span<const T> values) const {
    // memcpy with a null pointer is undefined even for 0 bytes.
    if (values.empty()) return;
    std::memcpy(&(*bytes_)[first * sizeof(T)], values.data(),
                values.size() * sizeof(T));
  }

 private:
  std::string* bytes_ = nullptr;
};

// The per-agent result columns that StepData and PackedStepData share, in
// the wire's types; row r holds one env's n_landers elements (n_landers * 12
// for observations): row 0 of a StepData, row e of a packed batch.
struct AgentColumns {
  ByteColumn<float> observations;
  ByteColumn<float> rewards;
  ByteColumn<uint8_t> terminations;
  ByteColumn<uint8_t> truncations;
  ByteColumn<uint8_t> stepped;
  ByteColumn<core::Outcome> outcomes;  // The codes of mll.v1.Outcome.
  ByteColumn<float> episode_returns;
  ByteColumn<int32_t> episode_lengths;

  // THE conversion of a step (or reset) result to the wire's per-agent
  // columns: writes `result` into row `row`; the episode bookkeeping
  // (returns, lengths) comes from `env`.
  void Write(size_t row, const core::StepResult& result,
             const core::Env& env) const;
};

// Step (or reset) results as a StepData: sizes its arrays, writes row 0 and
// the per-env fields.
void FillStepData(const core::StepResult& result, const core::Env& env,
                  bool auto_reset, v1::StepData* out);

// The result columns of a packed batch of `num_envs` envs with `n_landers`
// landers each, every column sized once (one allocation per column) and
// zero. Rows are disjoint, so threads may write different rows at once.
// `out` must outlive this object and not be modified while rows are written.
class PackedColumns {
 public:
  PackedColumns(int num_envs, int n_landers, v1::PackedStepData* out);
  // Env e's result, as FillStepData writes a StepData.
  void Write(int e, const core::StepResult& result, const core::Env& env,
             bool auto_reset) const;

 private:
  AgentColumns agents_;
  ByteColumn<uint8_t> episode_over_;
  ByteColumn<uint8_t> auto_reset_;
  ByteColumn<int32_t> cycles_;
};

// The state of a PettingZoo AECEnv, as `aec` holds it.
void FillAecState(const core::AecEnv& aec, bool world_stepped,
                  v1::AecState* out);

}  // namespace mll::service

#endif  // MLL_SERVICE_CONVERT_H_

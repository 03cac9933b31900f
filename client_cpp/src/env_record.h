// An environment's record: what recreates it to the same bits on any server
// of the same release, and its snapshot bytes. The C++ side of the Python
// client's multi_lunar_lander/_record.py, whose docstring defines the record
// and the snapshot format; both clients read each other's snapshots.
//
// An env is deterministic to the bit: its config, the seed of its last seeded
// reset and every operation since (steps with their actions, auto-reset
// steps, unseeded resets) recreate it. VectorEnv keeps one record per env to
// fail over (an env lost with its server is recreated elsewhere and replayed)
// and to give EnvSnapshot / RestoreEnv.
//
// Snapshot format (all integers little-endian): "MLLS", u16 format version, u16
// and u16 the wire protocol (major, minor) of the server that ran the env,
// u16 length + the server's release string, u32 length + the EnvConfig
// message, u64 seed, u8 action wire dtype, u32 action row bytes, u32
// operation count n, n operation bytes, n action rows, u32 length + the last
// observations (float32 [n_landers, 12]), u32 CRC-32 (zlib's) of all before.
#ifndef MLL_CLIENT_SRC_ENV_RECORD_H_
#define MLL_CLIENT_SRC_ENV_RECORD_H_

#include <cstddef>
#include <cstdint>
#include <optional>
#include <string>

#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::client {
namespace internal {

// One byte per operation, as _record.py numbers them. kAutoReset: a step
// that started a new episode (its actions ignored; replayed as a step on an
// auto-reset env, as an unseeded ResetEnv on another); kReset: an unseeded
// ResetEnv (the generator's stream continues).
enum RecordOperation : uint8_t { kStep = 1, kAutoReset = 2, kReset = 3 };

// Operations a record holds since its seeded reset (as MAX_RECORD_STEPS).
inline constexpr size_t kMaxRecordSteps = 100000;

struct EnvRecord {
  // The seed of the last seeded reset; none: never seeded.
  std::optional<uint64_t> seed;
  // One byte per operation, and one action row (wire bytes) per operation.
  std::string operations;
  std::string actions;
  // Empty while the record recreates the env; else why it cannot (operations
  // past kMaxRecordSteps), until the next seeded reset.
  std::string gap;

  // A new record from a seeded reset.
  void Restart(uint64_t new_seed);
  // Appends one operation, or opens the gap past kMaxRecordSteps.
  void Append(RecordOperation operation, absl::string_view action_row);
};

struct DecodedSnapshot {
  int protocol_major = 0;
  int protocol_minor = 0;
  std::string release;
  v1::EnvConfig config;
  EnvRecord record;
  v1::DType dtype = v1::DTYPE_UNSPECIFIED;
  uint32_t row_bytes = 0;
  // float32 [n_landers, 12], the bytes as the snapshot holds them.
  std::string last_observations;
};

// The snapshot bytes of an env with `config` that ran on the server `server`.
std::string EncodeSnapshot(const v1::EnvConfig& config,
                           const v1::ServerInfo& server,
                           const EnvRecord& record, v1::DType dtype,
                           uint32_t row_bytes,
                           absl::string_view last_observations);

// Parses and checks a snapshot: INVALID_ARGUMENT naming what is wrong (not a
// snapshot, damaged CRC, other format version, truncation, bad contents).
absl::StatusOr<DecodedSnapshot> DecodeSnapshot(absl::string_view snapshot);

// INVALID_ARGUMENT unless the snapshot's env has the options of `config`
// (render_mode and auto_reset aside: they do not change the physics) and its
// action rows.
absl::Status CheckSnapshotConfig(const DecodedSnapshot& snapshot,
                                 const v1::EnvConfig& config);

// INVALID_ARGUMENT unless the snapshot can be replayed into an env of `config`
// on the server `server`: CheckSnapshotConfig, and the same wire protocol major
// version (another major may change the physics or the operations). Another
// release of the same major is tried: the replay's bit check decides.
absl::Status CheckRestorable(const DecodedSnapshot& snapshot,
                             const v1::EnvConfig& config,
                             const v1::ServerInfo& server);

}  // namespace internal
}  // namespace mll::client

#endif  // MLL_CLIENT_SRC_ENV_RECORD_H_

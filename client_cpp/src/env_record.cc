#include "env_record.h"

#include <zlib.h>

#include <cstring>
#include <string>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "google/protobuf/io/coded_stream.h"
#include "google/protobuf/io/zero_copy_stream_impl_lite.h"

namespace mll::client {
namespace internal {
namespace {

constexpr absl::string_view kMagic = "MLLS";
constexpr uint16_t kFormatVersion = 1;

uint32_t Crc32(absl::string_view bytes) {
  return static_cast<uint32_t>(
      crc32(crc32(0L, Z_NULL, 0), reinterpret_cast<const Bytef*>(bytes.data()),
            static_cast<uInt>(bytes.size())));
}

// Little-endian integers, whatever the host's order.
template <typename T>
void PutLittleEndian(T value, std::string* out) {
  for (size_t byte = 0; byte < sizeof(T); ++byte) {
    out->push_back(
        static_cast<char>((static_cast<uint64_t>(value) >> (8 * byte)) & 0xff));
  }
}

template <typename T>
T GetLittleEndian(absl::string_view bytes) {
  uint64_t value = 0;
  for (size_t byte = 0; byte < sizeof(T); ++byte) {
    value |= static_cast<uint64_t>(static_cast<uint8_t>(bytes[byte]))
             << (8 * byte);
  }
  return static_cast<T>(value);
}

// Reads the snapshot's fields in order; each read names the field it wanted
// when the snapshot ends before it.
class SnapshotReader {
 public:
  explicit SnapshotReader(absl::string_view body) : body_(body) {}

  absl::StatusOr<absl::string_view> Take(size_t size, absl::string_view what) {
    if (size > body_.size() - offset_) {
      return absl::InvalidArgumentError(
          absl::StrCat("snapshot is truncated in its ", what));
    }
    absl::string_view chunk = body_.substr(offset_, size);
    offset_ += size;
    return chunk;
  }
  template <typename T>
  absl::StatusOr<T> Integer(absl::string_view what) {
    absl::StatusOr<absl::string_view> bytes = Take(sizeof(T), what);
    if (!bytes.ok()) return bytes.status();
    return GetLittleEndian<T>(*bytes);
  }
  // A u32 length, then that many bytes.
  absl::StatusOr<absl::string_view> Sized(absl::string_view what) {
    absl::StatusOr<uint32_t> size =
        Integer<uint32_t>(absl::StrCat(what, " length"));
    if (!size.ok()) return size.status();
    return Take(*size, what);
  }
  size_t left() const { return body_.size() - offset_; }

 private:
  absl::string_view body_;
  size_t offset_ = 0;
};

// The config's bytes as Python's SerializeToString(deterministic=True).
std::string DeterministicBytes(const v1::EnvConfig& config) {
  std::string bytes;
  google::protobuf::io::StringOutputStream stream(&bytes);
  google::protobuf::io::CodedOutputStream coded(&stream);
  coded.SetSerializationDeterministic(true);
  config.SerializeToCodedStream(&coded);
  coded.Trim();
  return bytes;
}

// The options that shape the physics: render_mode and auto_reset cleared.
v1::EnvConfig PhysicsOf(const v1::EnvConfig& config) {
  v1::EnvConfig physics = config;
  physics.clear_render_mode();
  physics.clear_auto_reset();
  return physics;
}

std::string Describe(const v1::EnvConfig& config) {
  const std::string text = config.ShortDebugString();
  return text.empty() ? "defaults" : text;
}

}  // namespace

void EnvRecord::Restart(uint64_t new_seed) {
  seed = new_seed;
  operations.clear();
  actions.clear();
  gap.clear();
}

void EnvRecord::Append(RecordOperation operation,
                       absl::string_view action_row) {
  if (!gap.empty()) return;
  if (operations.size() >= kMaxRecordSteps) {
    gap = absl::StrCat("its record passed ", kMaxRecordSteps,
                       " operations since its last seeded reset");
    return;
  }
  operations.push_back(static_cast<char>(operation));
  actions.append(action_row.data(), action_row.size());
}

std::string EncodeSnapshot(const v1::EnvConfig& config,
                           const v1::ServerInfo& server,
                           const EnvRecord& record, v1::DType dtype,
                           uint32_t row_bytes,
                           absl::string_view last_observations) {
  const std::string config_bytes = DeterministicBytes(config);
  const absl::string_view release =
      absl::string_view(server.server_version()).substr(0, 65535);
  std::string snapshot(kMagic);
  PutLittleEndian<uint16_t>(kFormatVersion, &snapshot);
  PutLittleEndian<uint16_t>(server.protocol_major(), &snapshot);
  PutLittleEndian<uint16_t>(server.protocol_minor(), &snapshot);
  PutLittleEndian<uint16_t>(release.size(), &snapshot);
  snapshot.append(release.data(), release.size());
  PutLittleEndian<uint32_t>(config_bytes.size(), &snapshot);
  snapshot.append(config_bytes);
  PutLittleEndian<uint64_t>(record.seed.value_or(0), &snapshot);
  PutLittleEndian<uint8_t>(dtype, &snapshot);
  PutLittleEndian<uint32_t>(row_bytes, &snapshot);
  PutLittleEndian<uint32_t>(record.operations.size(), &snapshot);
  snapshot.append(record.operations);
  snapshot.append(record.actions);
  PutLittleEndian<uint32_t>(last_observations.size(), &snapshot);
  snapshot.append(last_observations.data(), last_observations.size());
  PutLittleEndian<uint32_t>(Crc32(snapshot), &snapshot);
  return snapshot;
}

absl::StatusOr<DecodedSnapshot> DecodeSnapshot(absl::string_view snapshot) {
  if (snapshot.size() < 8 || snapshot.substr(0, kMagic.size()) != kMagic) {
    return absl::InvalidArgumentError(
        "snapshot does not start with \"MLLS\": not an env snapshot (or "
        "truncated)");
  }
  const absl::string_view body = snapshot.substr(0, snapshot.size() - 4);
  const uint32_t crc = GetLittleEndian<uint32_t>(snapshot.substr(body.size()));
  if (Crc32(body) != crc) {
    return absl::InvalidArgumentError(
        absl::StrFormat("snapshot is damaged: its CRC-32 is 0x%08x, its "
                        "contents' 0x%08x",
                        crc, Crc32(body)));
  }
  SnapshotReader reader(body.substr(kMagic.size()));
  absl::StatusOr<absl::string_view> header = reader.Take(8, "header");
  if (!header.ok()) return header.status();
  const uint16_t version = GetLittleEndian<uint16_t>(*header);
  if (version != kFormatVersion) {
    return absl::InvalidArgumentError(absl::StrCat(
        "snapshot has format version ", version, "; this client reads version ",
        kFormatVersion, " (upgrade the client)"));
  }
  DecodedSnapshot decoded;
  decoded.protocol_major = GetLittleEndian<uint16_t>(header->substr(2));
  decoded.protocol_minor = GetLittleEndian<uint16_t>(header->substr(4));
  absl::StatusOr<absl::string_view> release =
      reader.Take(GetLittleEndian<uint16_t>(header->substr(6)), "release");
  if (!release.ok()) return release.status();
  decoded.release = std::string(*release);
  absl::StatusOr<absl::string_view> config = reader.Sized("config");
  if (!config.ok()) return config.status();
  if (!decoded.config.ParseFromArray(config->data(),
                                     static_cast<int>(config->size()))) {
    return absl::InvalidArgumentError("snapshot's config does not parse");
  }
  absl::StatusOr<absl::string_view> sizes = reader.Take(17, "seed and sizes");
  if (!sizes.ok()) return sizes.status();
  decoded.record.seed = GetLittleEndian<uint64_t>(*sizes);
  const uint8_t dtype = GetLittleEndian<uint8_t>(sizes->substr(8));
  if (dtype != v1::DTYPE_INT32 && dtype != v1::DTYPE_FLOAT32) {
    return absl::InvalidArgumentError(
        absl::StrCat("snapshot's action dtype is ", static_cast<int>(dtype),
                     "; expected int32 or float32"));
  }
  decoded.dtype = static_cast<v1::DType>(dtype);
  decoded.row_bytes = GetLittleEndian<uint32_t>(sizes->substr(9));
  const uint32_t count = GetLittleEndian<uint32_t>(sizes->substr(13));
  if (count > kMaxRecordSteps) {
    return absl::InvalidArgumentError(absl::StrCat(
        "snapshot holds ", count, " operations; at most ", kMaxRecordSteps));
  }
  absl::StatusOr<absl::string_view> operations =
      reader.Take(count, "operations");
  if (!operations.ok()) return operations.status();
  for (char operation : *operations) {
    if (operation != kStep && operation != kAutoReset && operation != kReset) {
      return absl::InvalidArgumentError(
          "snapshot holds an unknown operation code");
    }
  }
  decoded.record.operations = std::string(*operations);
  absl::StatusOr<absl::string_view> actions =
      reader.Take(static_cast<uint64_t>(count) * decoded.row_bytes, "actions");
  if (!actions.ok()) return actions.status();
  decoded.record.actions = std::string(*actions);
  absl::StatusOr<absl::string_view> observations = reader.Sized("observations");
  if (!observations.ok()) return observations.status();
  decoded.last_observations = std::string(*observations);
  if (reader.left() != 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("snapshot has ", reader.left(), " bytes after its end"));
  }
  return decoded;
}

absl::Status CheckSnapshotConfig(const DecodedSnapshot& snapshot,
                                 const v1::EnvConfig& config) {
  const v1::EnvConfig mine = PhysicsOf(config);
  const v1::EnvConfig theirs = PhysicsOf(snapshot.config);
  if (DeterministicBytes(mine) != DeterministicBytes(theirs)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "snapshot is of an env with other options (", Describe(theirs),
        ") than this one's (", Describe(mine), ")"));
  }
  const uint32_t expected = config.n_landers() * (config.continuous() ? 8 : 4);
  const v1::DType dtype =
      config.continuous() ? v1::DTYPE_FLOAT32 : v1::DTYPE_INT32;
  if (snapshot.row_bytes != expected || snapshot.dtype != dtype) {
    return absl::InvalidArgumentError(
        absl::StrCat("snapshot's actions are ", snapshot.row_bytes,
                     " bytes a step; this env's are ", expected));
  }
  return absl::OkStatus();
}

absl::Status CheckRestorable(const DecodedSnapshot& snapshot,
                             const v1::EnvConfig& config,
                             const v1::ServerInfo& server) {
  if (absl::Status status = CheckSnapshotConfig(snapshot, config);
      !status.ok()) {
    return status;
  }
  if (snapshot.protocol_major != static_cast<int>(server.protocol_major())) {
    return absl::InvalidArgumentError(absl::StrCat(
        "snapshot is from a server of wire protocol ", snapshot.protocol_major,
        ".", snapshot.protocol_minor, " (release ",
        snapshot.release.empty() ? "unknown" : snapshot.release,
        "); this server speaks ", server.protocol_major(), ".",
        server.protocol_minor(), " (release ", server.server_version(),
        "): restore it on a server of protocol ", snapshot.protocol_major,
        ".x"));
  }
  return absl::OkStatus();
}

}  // namespace internal
}  // namespace mll::client

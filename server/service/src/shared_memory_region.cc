#include "shared_memory_region.h"

#include <fcntl.h>
#include <sys/mman.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <random>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace mll::service {
namespace {

absl::Status CannotCreate(absl::string_view step) {
  return absl::ResourceExhaustedError(
      absl::StrCat("attach_shared_memory: the server cannot ", step,
                   " its region: ", std::strerror(errno)));
}

}  // namespace

absl::StatusOr<std::unique_ptr<SharedMemoryRegion>>
SharedMemoryRegion::Create() {
  const int fd = memfd_create("mll-session", MFD_CLOEXEC | MFD_ALLOW_SEALING);
  if (fd < 0) return CannotCreate("create");
  const uint64_t bytes = shared_memory::RegionBytes(shared_memory::kCapacity);
  // Sealed at its size: a client cannot shrink the file under the server's
  // mapping (which would crash the server on its next write).
  if (ftruncate(fd, static_cast<off_t>(bytes)) != 0 ||
      fcntl(fd, F_ADD_SEALS, F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_SEAL) != 0) {
    const absl::Status status = CannotCreate("size and seal");
    close(fd);
    return status;
  }
  void* base = mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_SHARED, fd, 0);
  if (base == MAP_FAILED) {
    const absl::Status status = CannotCreate("map");
    close(fd);
    return status;
  }
  std::random_device random;
  const uint64_t nonce = (uint64_t{random()} << 32) ^ random();
  auto& header = *static_cast<shared_memory::Header*>(base);
  header.magic = shared_memory::kMagic;
  header.version = shared_memory::kVersion;
  header.capacity = shared_memory::kCapacity;
  header.nonce = nonce;
  return std::unique_ptr<SharedMemoryRegion>(
      new SharedMemoryRegion(fd, base, bytes, nonce));
}

SharedMemoryRegion::SharedMemoryRegion(int fd, void* base, uint64_t bytes,
                                       uint64_t nonce)
    : fd_(fd),
      base_(base),
      bytes_(bytes),
      nonce_(nonce),
      path_(absl::StrCat("/proc/", getpid(), "/fd/", fd)) {}

SharedMemoryRegion::~SharedMemoryRegion() {
  munmap(base_, bytes_);
  close(fd_);
}

}  // namespace mll::service

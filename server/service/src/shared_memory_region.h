// The server's side of a Session's shared-memory region
// (mll/shared_memory_pipe.h): a sealed memfd, mapped, and the path through
// which the client on the same host opens it; freed when the region goes.
#ifndef MLL_SERVICE_SRC_SHARED_MEMORY_REGION_H_
#define MLL_SERVICE_SRC_SHARED_MEMORY_REGION_H_

#include <cstdint>
#include <memory>
#include <string>

#include "absl/status/statusor.h"
#include "mll/shared_memory_pipe.h"

namespace mll::service {

class SharedMemoryRegion {
 public:
  // A new region with an initialised header (random nonce).
  static absl::StatusOr<std::unique_ptr<SharedMemoryRegion>> Create();
  ~SharedMemoryRegion();
  SharedMemoryRegion(const SharedMemoryRegion&) = delete;
  SharedMemoryRegion& operator=(const SharedMemoryRegion&) = delete;

  shared_memory::Header& header() const {
    return *static_cast<shared_memory::Header*>(base_);
  }
  // /proc/<pid>/fd/<fd>: where the client opens the region.
  const std::string& path() const { return path_; }
  uint64_t bytes() const { return bytes_; }
  uint64_t nonce() const { return nonce_; }
  static constexpr uint64_t capacity() { return shared_memory::kCapacity; }
  const char* request() const { return shared_memory::RequestArea(base_); }
  char* response() const {
    return shared_memory::ResponseArea(base_, capacity());
  }

 private:
  SharedMemoryRegion(int fd, void* base, uint64_t bytes, uint64_t nonce);

  const int fd_;
  void* const base_;
  const uint64_t bytes_;
  const uint64_t nonce_;
  const std::string path_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_SRC_SHARED_MEMORY_REGION_H_

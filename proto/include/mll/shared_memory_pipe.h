// The shared-memory region of a Session attached with attach_shared_memory
// (proto/mll/v1/multi_lunar_lander.proto): the layout both sides map and the
// waits and wake-ups that pass one request and its response at a time. The
// server creates the region as a memfd sealed against resizing (a client
// cannot shrink it under the server), and the client opens it through
// /proc/<server pid>/fd/<n>; it goes when both have let go of it.
//
// One message at a time in each direction: the client writes a serialized
// SessionRequest into the request area, stores its size, then increments
// request_seq; the server runs it, writes the serialized SessionResponse into
// the response area, stores its size, then sets response_seq to the
// request's request_seq. Each side sleeps on the other's counter with a futex
// (after an optional short spin) and wakes the other after its store.
#ifndef MLL_SHARED_MEMORY_PIPE_H_
#define MLL_SHARED_MEMORY_PIPE_H_

#include <linux/futex.h>
#include <sys/syscall.h>
#include <time.h>
#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>

namespace mll::shared_memory {

constexpr uint32_t kMagic = 0x314c4c4d;  // "MLL1" in memory order.
constexpr uint32_t kVersion = 1;
// The header's page; the request area follows it, then the response area.
constexpr uint64_t kHeaderBytes = 4096;
// Bytes of each message area: the largest message the clients' channels
// take. Pages are allocated only when touched (a 64-env step uses a few).
constexpr uint64_t kCapacity = uint64_t{64} << 20;

struct Header {
  uint32_t magic;
  uint32_t version;
  // Bytes of each message area; the file is kHeaderBytes + 2 * capacity.
  uint64_t capacity;
  // The server's random number for this session, also in its attach answer.
  uint64_t nonce;
  std::atomic<uint32_t> request_seq;
  std::atomic<uint32_t> response_seq;
  std::atomic<uint64_t> request_size;
  std::atomic<uint64_t> response_size;
};
static_assert(std::atomic<uint32_t>::is_always_lock_free &&
                  std::atomic<uint64_t>::is_always_lock_free,
              "the counters must be lock-free to be shared between processes");
static_assert(sizeof(Header) <= kHeaderBytes, "the header fits its page");

inline uint64_t RegionBytes(uint64_t capacity) {
  return kHeaderBytes + 2 * capacity;
}
inline char* RequestArea(void* region) {
  return static_cast<char*>(region) + kHeaderBytes;
}
inline char* ResponseArea(void* region, uint64_t capacity) {
  return static_cast<char*>(region) + kHeaderBytes + capacity;
}

// Waits until `*word` differs from `old`, spinning for `spin` first, then
// sleeping on the futex; returns whether it changed within about `timeout`
// (the caller checks its own reasons to stop between waits).
inline bool WaitWhileEqual(const std::atomic<uint32_t>& word, uint32_t old,
                           std::chrono::nanoseconds spin,
                           std::chrono::nanoseconds timeout) {
  if (word.load(std::memory_order_acquire) != old) return true;
  if (spin.count() > 0) {
    const auto until = std::chrono::steady_clock::now() + spin;
    do {
      for (int i = 0; i < 64; ++i) {
        if (word.load(std::memory_order_acquire) != old) return true;
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
      }
    } while (std::chrono::steady_clock::now() < until);
  }
  const auto seconds =
      std::chrono::duration_cast<std::chrono::seconds>(timeout);
  struct timespec relative;
  relative.tv_sec = seconds.count();
  relative.tv_nsec = (timeout - seconds).count();
  // Not FUTEX_PRIVATE_FLAG: the word is shared with another process.
  syscall(SYS_futex, reinterpret_cast<const uint32_t*>(&word), FUTEX_WAIT, old,
          &relative, nullptr, 0);
  return word.load(std::memory_order_acquire) != old;
}

inline void Wake(std::atomic<uint32_t>& word) {
  syscall(SYS_futex, reinterpret_cast<uint32_t*>(&word), FUTEX_WAKE, 1, nullptr,
          nullptr, 0);
}

}  // namespace mll::shared_memory

#endif  // MLL_SHARED_MEMORY_PIPE_H_

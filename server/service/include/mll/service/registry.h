// The registry owns every environment of a server. Its map is guarded by one
// mutex that is never held while an environment steps; each environment has
// its own lock. Environments untouched for the idle timeout are destroyed by
// a reaper thread that sleeps on a condition variable between deadlines.
#ifndef MLL_SERVICE_REGISTRY_H_
#define MLL_SERVICE_REGISTRY_H_

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <deque>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/base/thread_annotations.h"
#include "absl/container/flat_hash_map.h"
#include "absl/status/status.h"
#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"
#include "mll/core/aec_env.h"
#include "mll/core/env.h"
#include "mll/core/env_config.h"
#include "mll/service/auth.h"

namespace mll::service {

// Which API steps an env in its current episode. The AEC adapter buffers
// actions between world steps, so the two step APIs cannot interleave within
// one episode; a reset lets the client choose again.
enum class StepMode { kUnset, kParallel, kAec };

// One hosted environment. Immutable members may be read without the lock;
// everything else needs `mu`.
struct EnvSlot {
  EnvSlot(std::string name, uint64_t serial, std::unique_ptr<core::Env> env,
          bool auto_reset, bool session_bound, std::string owner);

  const std::string name;        // envs/{id}
  const uint64_t serial;         // Creation order, for ListEnvs.
  const core::EnvConfig config;  // Copy of env->config(), readable unlocked.
  const bool auto_reset;         // EnvConfig.auto_reset of the proto.
  const bool session_bound;      // Dies with the session that created it.
  // Who created it (auth.h); only the same owner can find it.
  const std::string owner;
  // Steady-clock nanoseconds of the last lookup; read by the reaper.
  std::atomic<int64_t> last_touched_ns{0};
  // Set when the registry lets go of the env (deleted or reclaimed): from
  // then on no look-up finds it, kept ones included (SessionBatches).
  std::atomic<bool> removed{false};

  absl::Mutex mu;
  std::unique_ptr<core::Env> env ABSL_PT_GUARDED_BY(mu);
  std::unique_ptr<core::AecEnv> aec ABSL_PT_GUARDED_BY(mu);
  StepMode mode ABSL_GUARDED_BY(mu) = StepMode::kUnset;
  int64_t episodes ABSL_GUARDED_BY(mu) = 0;
  // Reset has seeded the generator (explicitly or with a drawn seed).
  bool seeded ABSL_GUARDED_BY(mu) = false;
  // Reused by every step so that stepping does not allocate.
  core::StepResult scratch ABSL_GUARDED_BY(mu);
};

class Registry {
 public:
  // `max_envs` >= 1; `idle_timeout` > 0; `max_envs_per_owner` >= 1 bounds
  // each owner's live envs (0: only max_envs does). Starts the reaper.
  Registry(int max_envs, absl::Duration idle_timeout,
           int max_envs_per_owner = 0);
  // Stops the reaper and destroys every environment.
  ~Registry();
  Registry(const Registry&) = delete;
  Registry& operator=(const Registry&) = delete;

  // Every call below takes the caller's `owner` (auth.h): an env belongs to
  // the owner that created it, and to any other owner it is NOT_FOUND
  // exactly as an unknown name, so that names of others' envs leak nothing.

  // Builds an env under a fresh unguessable name. RESOURCE_EXHAUSTED at
  // max_envs or at the owner's max_envs_per_owner; INVALID_ARGUMENT for a
  // bad config (from the core).
  absl::StatusOr<std::shared_ptr<EnvSlot>> Create(
      const core::EnvConfig& config, bool auto_reset, bool session_bound,
      absl::string_view owner = kAnonymousOwner);

  // The env called `name` (touching it: its idle clock restarts). `field`
  // names the request field in errors. INVALID_ARGUMENT for a name that is
  // not `envs/{id}`, NOT_FOUND for an unknown one (saying so when the idle
  // timeout reclaimed it recently).
  absl::StatusOr<std::shared_ptr<EnvSlot>> Find(
      absl::string_view name, absl::string_view field,
      absl::string_view owner = kAnonymousOwner);

  // Destroys the env (calls holding it finish first). NOT_FOUND if unknown.
  absl::Status Delete(absl::string_view name, absl::string_view field,
                      absl::string_view owner = kAnonymousOwner);

  struct Page {
    std::vector<std::shared_ptr<EnvSlot>> slots;
    std::string next_page_token;  // Empty on the last page.
  };
  // The owner's envs in creation order. page_size 0 means 100, larger than
  // 1000 means 1000, negative is INVALID_ARGUMENT, as is a token not from a
  // Page.
  absl::StatusOr<Page> List(int page_size, absl::string_view page_token,
                            absl::string_view owner = kAnonymousOwner);

  // A seed for an env's first unseeded reset, so independent envs differ.
  // Service-level randomness; physics never draws from it.
  uint64_t DrawSeed();

  int size();
  // Live envs of each owner that has any, sorted by owner.
  std::vector<std::pair<std::string, int>> SizeByOwner();
  absl::Duration idle_timeout() const { return idle_timeout_; }

 private:
  void ReapLoop();
  // Removes expired envs into `expired` (destroyed by the caller, unlocked);
  // returns when the next one can expire.
  absl::Time ReapExpiredLocked(std::vector<std::shared_ptr<EnvSlot>>* expired)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  std::string NewNameLocked() ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Counts an env of `owner` out (it left the map, or was never built).
  void ReleaseOwnerLocked(const std::string& owner)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);
  // Remembers that the reaper destroyed `slot`, forgetting the oldest such
  // name beyond kMaxReclaimedNames.
  void RememberReclaimedLocked(const EnvSlot& slot)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  // Takes `slot` out of the maps (it is in them).
  void RemoveLocked(const std::shared_ptr<EnvSlot>& slot)
      ABSL_EXCLUSIVE_LOCKS_REQUIRED(mu_);

  const int max_envs_;
  const absl::Duration idle_timeout_;
  const int max_envs_per_owner_;

  absl::Mutex mu_;
  absl::CondVar reaper_wake_;
  bool stopping_ ABSL_GUARDED_BY(mu_) = false;
  std::mt19937_64 random_ ABSL_GUARDED_BY(mu_);
  uint64_t next_serial_ ABSL_GUARDED_BY(mu_) = 1;
  // Envs being built outside the lock, counted against max_envs.
  int pending_ ABSL_GUARDED_BY(mu_) = 0;
  absl::flat_hash_map<std::string, std::shared_ptr<EnvSlot>> by_name_
      ABSL_GUARDED_BY(mu_);
  std::map<uint64_t, std::shared_ptr<EnvSlot>> by_serial_ ABSL_GUARDED_BY(mu_);
  // Live and pending envs per owner; owners at zero are erased.
  absl::flat_hash_map<std::string, int> live_by_owner_ ABSL_GUARDED_BY(mu_);
  // Names the reaper destroyed recently -> their owner, so NOT_FOUND can say
  // why; `reclaimed_order_` holds them oldest first.
  absl::flat_hash_map<std::string, std::string> reclaimed_ ABSL_GUARDED_BY(mu_);
  std::deque<std::string> reclaimed_order_ ABSL_GUARDED_BY(mu_);
  std::thread reaper_;
};

// The env lists of one Session's packed StepBatches (one owner, one batch at
// a time), each with its envs' slots, so that stepping them again needs
// neither the check for repeated names nor the registry's lock and look-ups:
//  - declared batches (PackedSteps.handle): the client names the envs once
//    and then sends only the handle and the actions;
//  - recent batches, for clients that send names with every step: a batch
//    naming the same envs in the same order as one of the last kMaxRecent
//    (a vector env's every step, or each of an async vector env's batches)
//    reuses its slots.
// A slot is kept weakly: a deleted or reclaimed env is not kept alive, and is
// never found again through a batch.
class SessionBatches {
 public:
  struct Batch {
    std::vector<std::string> names;
    std::vector<std::weak_ptr<EnvSlot>> slots;
    // Each slot's address when the batch was kept (0: none found), for
    // Prefetch alone: never dereferenced, as the slot may be gone since.
    std::vector<uintptr_t> addresses;
  };

  // PackedSteps.handle's range (0: none) and how many envs a session's
  // declared batches hold together (the wire contract's figures).
  static constexpr uint32_t kMaxHandle = 64;
  static constexpr size_t kMaxDeclaredEnvs = 65536;

  // Env `index` of `batch` as Registry::Find would return it to `owner`
  // (touched), or null when the registry no longer holds it or it was not
  // found then. Safe to call from several threads at once.
  static std::shared_ptr<EnvSlot> Find(const Batch& batch, int index,
                                       absl::string_view owner);

  // Asks the CPU to bring env `index`'s slot of `batch` (its reference
  // counts, flags, lock and config, which Find and the step touch first)
  // into the cache, so that a runner stepping env i fetches env i + 1's
  // meanwhile instead of waiting for it. A hint only: an address that is no
  // longer a slot is never read.
  static void Prefetch(const Batch& batch, int index) {
    const uintptr_t address = batch.addresses[index];
    if (address == 0) return;
    // std::make_shared puts the reference counts just before the slot.
    const char* const slot = reinterpret_cast<const char*>(address);
    for (int line = -1; line < kSlotLines; ++line) {
      __builtin_prefetch(slot + line * kCacheLine);
    }
    // GCC counts a prefetch as no effect and would drop a call of this
    // function, whose result nobody reads; an empty volatile asm keeps it.
    asm volatile("" : : "r"(slot));
  }

  // The kept recent batch whose names are `names`, in order, or null.
  template <typename Names>
  const Batch* Match(const Names& names) const {
    for (const Batch& batch : recent_) {
      if (batch.names.size() == static_cast<size_t>(names.size()) &&
          std::equal(batch.names.begin(), batch.names.end(), names.begin())) {
        return &batch;
      }
    }
    return nullptr;
  }

  // Keeps a recent batch whose names are distinct, with slots[e] the slot
  // found for names[e] (empty if none was), in place of the least recently
  // kept one beyond kMaxRecent.
  template <typename Names>
  void Keep(const Names& names, std::vector<std::weak_ptr<EnvSlot>> slots) {
    if (static_cast<size_t>(names.size()) > kMaxEnvsPerRecent) return;
    if (recent_.size() == kMaxRecent) recent_.pop_front();
    std::vector<uintptr_t> addresses = AddressesOf(slots);
    recent_.push_back(
        Batch{std::vector<std::string>(names.begin(), names.end()),
              std::move(slots), std::move(addresses)});
  }

  // The batch declared as `handle` (1..kMaxHandle), or null.
  const Batch* Declared(uint32_t handle) const {
    return handle < declared_.size() && !declared_[handle].names.empty()
               ? &declared_[handle]
               : nullptr;
  }
  // OK when `handle` (1..kMaxHandle) may be declared as `num_envs` envs:
  // RESOURCE_EXHAUSTED (naming `field`) when the declared batches would then
  // hold more than kMaxDeclaredEnvs envs.
  absl::Status CheckDeclare(uint32_t handle, size_t num_envs,
                            absl::string_view field) const;
  // Declares `handle` (checked by CheckDeclare) as `names` (distinct, at
  // least one), slots[e] the slot found for names[e] (empty if none was).
  template <typename Names>
  void Declare(uint32_t handle, const Names& names,
               std::vector<std::weak_ptr<EnvSlot>> slots) {
    if (declared_.size() <= handle) declared_.resize(handle + 1);
    Batch& batch = declared_[handle];
    declared_envs_ -= batch.names.size();
    batch.names.assign(names.begin(), names.end());
    batch.addresses = AddressesOf(slots);
    batch.slots = std::move(slots);
    declared_envs_ += batch.names.size();
  }

 private:
  static constexpr int kCacheLine = 64;
  static constexpr int kSlotLines =
      static_cast<int>((sizeof(EnvSlot) + kCacheLine - 1) / kCacheLine);

  static std::vector<uintptr_t> AddressesOf(
      const std::vector<std::weak_ptr<EnvSlot>>& slots);

  // An async vector env alternates num_envs / batch_size lists.
  static constexpr size_t kMaxRecent = 8;
  // Larger batches are rare, and their per-call costs are spread thin.
  static constexpr size_t kMaxEnvsPerRecent = 4096;
  std::deque<Batch> recent_;
  // Indexed by handle; a batch without names is not declared.
  std::vector<Batch> declared_;
  size_t declared_envs_ = 0;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_REGISTRY_H_

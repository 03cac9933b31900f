#include "mll/service/registry.h"

#include <algorithm>
#include <chrono>
#include <utility>

#include "absl/strings/match.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"

namespace mll::service {
namespace {

constexpr absl::string_view kNamePrefix = "envs/";
constexpr int kDefaultPageSize = 100;
constexpr int kMaxPageSize = 1000;
// The reaper scans at most this often, so that envs touched just before
// their deadline cannot make it spin; an env may outlive its timeout by
// this much (or a tenth of the timeout, if smaller).
constexpr absl::Duration kMaxReapGranularity = absl::Seconds(1);
// How many reclaimed names NOT_FOUND can explain; 4096 names of ~40 bytes
// and their owners are well under 1 MB.
constexpr size_t kMaxReclaimedNames = 4096;

int64_t SteadyNowNs() {
  return std::chrono::duration_cast<std::chrono::nanoseconds>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
}

void Touch(EnvSlot& slot) { slot.last_touched_ns.store(SteadyNowNs()); }

// Seeds the id generator from the OS's entropy so that names cannot be
// guessed from the server's start time or from other names.
std::mt19937_64 SeededFromEntropy() {
  std::random_device device;
  std::seed_seq seq{device(), device(), device(), device(),
                    device(), device(), device(), device()};
  return std::mt19937_64(seq);
}

}  // namespace

EnvSlot::EnvSlot(std::string name, uint64_t serial,
                 std::unique_ptr<core::Env> env, bool auto_reset,
                 bool session_bound, std::string owner)
    : name(std::move(name)),
      serial(serial),
      config(env->config()),
      auto_reset(auto_reset),
      session_bound(session_bound),
      owner(std::move(owner)),
      env(std::move(env)) {
  aec = std::make_unique<core::AecEnv>(this->env.get());
  Touch(*this);
}

Registry::Registry(int max_envs, absl::Duration idle_timeout,
                   int max_envs_per_owner)
    : max_envs_(max_envs),
      idle_timeout_(idle_timeout),
      max_envs_per_owner_(max_envs_per_owner),
      random_(SeededFromEntropy()) {
  reaper_ = std::thread([this] { ReapLoop(); });
}

Registry::~Registry() {
  {
    absl::MutexLock lock(&mu_);
    stopping_ = true;
    reaper_wake_.Signal();
  }
  reaper_.join();
}

std::string Registry::NewNameLocked() {
  for (;;) {
    const uint64_t high = random_();
    const uint64_t low = random_();
    std::string name = absl::StrFormat("%s%016x%016x", kNamePrefix, high, low);
    if (!by_name_.contains(name)) return name;
  }
}

absl::StatusOr<std::shared_ptr<EnvSlot>> Registry::Create(
    const core::EnvConfig& config, bool auto_reset, bool session_bound,
    absl::string_view owner) {
  {
    absl::MutexLock lock(&mu_);
    if (static_cast<int>(by_name_.size()) + pending_ >= max_envs_) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "the server hosts its maximum of --max_envs = ", max_envs_,
          " environments; delete some (DeleteEnv) or wait for idle ones to "
          "be reclaimed after --idle_timeout_s = ",
          absl::ToDoubleSeconds(idle_timeout_)));
    }
    int& owned = live_by_owner_[owner];
    if (max_envs_per_owner_ > 0 && owned >= max_envs_per_owner_) {
      return absl::ResourceExhaustedError(absl::StrCat(
          "tenant ", owner.empty() ? "anonymous" : owner,
          " hosts its quota of --max_envs_per_token=", max_envs_per_owner_,
          " environments (the server hosts ", by_name_.size() + pending_,
          " of --max_envs=", max_envs_,
          "); delete some of yours (DeleteEnv) or wait for idle ones to be "
          "reclaimed after --idle_timeout_s = ",
          absl::ToDoubleSeconds(idle_timeout_)));
    }
    ++owned;
    ++pending_;
  }
  // Building a Box2D world takes a while: not under the registry's lock.
  absl::StatusOr<std::unique_ptr<core::Env>> env = core::Env::Create(config);
  absl::MutexLock lock(&mu_);
  --pending_;
  if (!env.ok()) {
    ReleaseOwnerLocked(std::string(owner));
    return env.status();
  }
  const std::string name = NewNameLocked();
  auto slot =
      std::make_shared<EnvSlot>(name, next_serial_++, *std::move(env),
                                auto_reset, session_bound, std::string(owner));
  by_name_.emplace(name, slot);
  by_serial_.emplace(slot->serial, slot);
  return slot;
}

absl::StatusOr<std::shared_ptr<EnvSlot>> Registry::Find(
    absl::string_view name, absl::string_view field, absl::string_view owner) {
  if (!absl::StartsWith(name, kNamePrefix) ||
      name.size() == kNamePrefix.size()) {
    return absl::InvalidArgumentError(
        absl::StrCat(field, ": \"", name,
                     "\" is not an env name (allowed: envs/{id}, as "
                     "CreateEnv returned it)"));
  }
  std::shared_ptr<EnvSlot> slot;
  {
    // Shared: a StepBatch's workers look up their envs at the same time.
    absl::ReaderMutexLock lock(&mu_);
    auto it = by_name_.find(name);
    if (it != by_name_.end() && it->second->owner == owner) slot = it->second;
  }
  if (slot == nullptr) {
    absl::ReaderMutexLock lock(&mu_);
    auto reclaimed = reclaimed_.find(name);
    if (reclaimed != reclaimed_.end() && reclaimed->second == owner) {
      return absl::NotFoundError(absl::StrCat(
          field, ": ", name, " was reclaimed after being idle ",
          absl::ToDoubleSeconds(idle_timeout_),
          " s (--idle_timeout_s): no call touched it for that long; keep "
          "the client's env object alive (it renews the lease with KeepAlive "
          "while it lives) or raise the server's --idle_timeout_s"));
    }
    return absl::NotFoundError(absl::StrCat(
        field, ": ", name,
        " does not exist (never created, deleted, ended with its session, or "
        "reclaimed after --idle_timeout_s = ",
        absl::ToDoubleSeconds(idle_timeout_), ")"));
  }
  Touch(*slot);
  return slot;
}

absl::Status Registry::Delete(absl::string_view name, absl::string_view field,
                              absl::string_view owner) {
  absl::StatusOr<std::shared_ptr<EnvSlot>> found = Find(name, field, owner);
  if (!found.ok()) return found.status();
  {
    absl::MutexLock lock(&mu_);
    // A concurrent Delete or the reaper may have removed it already.
    if (!(*found)->removed.load()) RemoveLocked(*found);
  }
  // The last holder (maybe this call, maybe an in-flight step) destroys the
  // world, outside the registry's lock.
  return absl::OkStatus();
}

absl::StatusOr<Registry::Page> Registry::List(int page_size,
                                              absl::string_view page_token,
                                              absl::string_view owner) {
  if (page_size < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("page_size: ", page_size, " is negative (allowed: 0 for ",
                     kDefaultPageSize, ", up to ", kMaxPageSize, ")"));
  }
  if (page_size == 0) page_size = kDefaultPageSize;
  page_size = std::min(page_size, kMaxPageSize);
  // The token is the serial of the first env of the page; serials only grow,
  // so pages stay consistent while envs come and go.
  uint64_t first = 0;
  if (!page_token.empty() &&
      (!absl::StartsWith(page_token, "s") ||
       !absl::SimpleAtoi(page_token.substr(1), &first))) {
    return absl::InvalidArgumentError(absl::StrCat(
        "page_token: \"", page_token,
        "\" is not a token from ListEnvsResponse.next_page_token"));
  }
  Page page;
  absl::MutexLock lock(&mu_);
  for (auto it = by_serial_.lower_bound(first); it != by_serial_.end(); ++it) {
    if (it->second->owner != owner) continue;
    if (static_cast<int>(page.slots.size()) == page_size) {
      page.next_page_token = absl::StrCat("s", it->first);
      break;
    }
    page.slots.push_back(it->second);
  }
  return page;
}

uint64_t Registry::DrawSeed() {
  absl::MutexLock lock(&mu_);
  return random_();
}

int Registry::size() {
  absl::MutexLock lock(&mu_);
  return static_cast<int>(by_name_.size());
}

std::vector<std::pair<std::string, int>> Registry::SizeByOwner() {
  std::vector<std::pair<std::string, int>> sizes;
  {
    absl::MutexLock lock(&mu_);
    sizes.assign(live_by_owner_.begin(), live_by_owner_.end());
  }
  std::sort(sizes.begin(), sizes.end());
  return sizes;
}

void Registry::ReleaseOwnerLocked(const std::string& owner) {
  auto it = live_by_owner_.find(owner);
  if (it != live_by_owner_.end() && --it->second <= 0) {
    live_by_owner_.erase(it);
  }
}

void Registry::RemoveLocked(const std::shared_ptr<EnvSlot>& slot) {
  slot->removed.store(true);
  ReleaseOwnerLocked(slot->owner);
  by_serial_.erase(slot->serial);
  by_name_.erase(slot->name);
}

void Registry::RememberReclaimedLocked(const EnvSlot& slot) {
  if (!reclaimed_.emplace(slot.name, slot.owner).second) return;
  reclaimed_order_.push_back(slot.name);
  if (reclaimed_order_.size() > kMaxReclaimedNames) {
    reclaimed_.erase(reclaimed_order_.front());
    reclaimed_order_.pop_front();
  }
}

absl::Time Registry::ReapExpiredLocked(
    std::vector<std::shared_ptr<EnvSlot>>* expired) {
  const int64_t now_ns = SteadyNowNs();
  const int64_t timeout_ns = absl::ToInt64Nanoseconds(idle_timeout_);
  int64_t next_ns = now_ns + timeout_ns;  // A new env expires no sooner.
  for (auto it = by_name_.begin(); it != by_name_.end();) {
    const int64_t deadline_ns = it->second->last_touched_ns.load() + timeout_ns;
    if (deadline_ns <= now_ns) {
      std::shared_ptr<EnvSlot> slot = (it++)->second;
      RememberReclaimedLocked(*slot);
      RemoveLocked(slot);
      expired->push_back(std::move(slot));
    } else {
      next_ns = std::min(next_ns, deadline_ns);
      ++it;
    }
  }
  const absl::Duration granularity =
      std::min(kMaxReapGranularity, idle_timeout_ / 10);
  return absl::Now() +
         std::max(absl::Nanoseconds(next_ns - now_ns), granularity);
}

void Registry::ReapLoop() {
  absl::MutexLock lock(&mu_);
  while (!stopping_) {
    std::vector<std::shared_ptr<EnvSlot>> expired;
    const absl::Time wake = ReapExpiredLocked(&expired);
    if (!expired.empty()) {
      mu_.Unlock();
      expired.clear();  // Destroys the worlds without blocking lookups.
      mu_.Lock();
      continue;
    }
    // Sleeps until the earliest deadline: no CPU while nothing expires.
    reaper_wake_.WaitWithDeadline(&mu_, wake);
  }
}

std::vector<uintptr_t> SessionBatches::AddressesOf(
    const std::vector<std::weak_ptr<EnvSlot>>& slots) {
  std::vector<uintptr_t> addresses;
  addresses.reserve(slots.size());
  for (const std::weak_ptr<EnvSlot>& slot : slots) {
    const std::shared_ptr<EnvSlot> held = slot.lock();
    addresses.push_back(reinterpret_cast<uintptr_t>(held.get()));
  }
  return addresses;
}

std::shared_ptr<EnvSlot> SessionBatches::Find(const Batch& batch, int index,
                                              absl::string_view owner) {
  std::shared_ptr<EnvSlot> slot = batch.slots[index].lock();
  if (slot == nullptr || slot->removed.load() || slot->owner != owner) {
    return nullptr;
  }
  Touch(*slot);
  return slot;
}

absl::Status SessionBatches::CheckDeclare(uint32_t handle, size_t num_envs,
                                          absl::string_view field) const {
  const Batch* replaced = Declared(handle);
  const size_t held =
      declared_envs_ - (replaced != nullptr ? replaced->names.size() : 0);
  if (held + num_envs <= kMaxDeclaredEnvs) return absl::OkStatus();
  return absl::ResourceExhaustedError(absl::StrCat(
      field, ": declaring ", handle, " as ", num_envs,
      " envs would make this session's declared batches hold ", held + num_envs,
      " envs; allowed: at most ", kMaxDeclaredEnvs,
      " (declare the handles of batches no longer stepped anew, or send "
      "names without a handle)"));
}

}  // namespace mll::service

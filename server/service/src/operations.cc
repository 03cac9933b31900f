#include "mll/service/operations.h"

#include <algorithm>
#include <charconv>
#include <memory>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "absl/container/flat_hash_map.h"
#include "absl/functional/function_ref.h"
#include "absl/strings/str_cat.h"
#include "mll/core/renderer.h"
#include "mll/service/convert.h"

namespace mll::service {
namespace {

// The fewest agent-steps a runner of a packed batch is handed: some 0.2 ms of
// physics, which pays for waking a thread (a few microseconds of CPU on both
// sides) and for its envs' state moving to that thread's core.
constexpr int kMinAgentStepsPerRunner = 16;

// Starts a new episode through the AEC adapter, which resets the Env and the
// turn order together, so both step APIs can follow.
void ResetLocked(EnvSlot& slot, std::optional<uint64_t> seed)
    ABSL_EXCLUSIVE_LOCKS_REQUIRED(slot.mu) {
  slot.aec->Reset(seed, &slot.scratch);
  slot.mode = StepMode::kUnset;
  ++slot.episodes;
}

absl::Status CheckStarted(const EnvSlot& slot)
    ABSL_EXCLUSIVE_LOCKS_REQUIRED(slot.mu) {
  if (slot.env->episode_started()) return absl::OkStatus();
  return absl::FailedPreconditionError(absl::StrCat(
      "name: ", slot.name, " has no episode yet; call ResetEnv first"));
}

// The two step APIs cannot interleave within an episode (see StepMode); the
// mode is taken by the first successful step.
absl::Status CheckMode(const EnvSlot& slot, StepMode mode)
    ABSL_EXCLUSIVE_LOCKS_REQUIRED(slot.mu) {
  if (slot.mode == StepMode::kUnset || slot.mode == mode) {
    return absl::OkStatus();
  }
  return absl::FailedPreconditionError(absl::StrCat(
      "name: ", slot.name, " is stepped with ",
      slot.mode == StepMode::kAec ? "StepAgent" : "StepEnv/StepBatch",
      " in this episode; the other step API needs a new episode (call "
      "ResetEnv)"));
}

// Steps `slot` with `actions`, already checked against its config (dtype and
// shape; values are the core's to check), and hands the result to
// emit(result, env, auto_reset) while the env is still locked. The one step
// of StepEnv and of both StepBatch forms.
absl::Status StepSlot(
    EnvSlot& slot, const core::ActionsView& actions,
    absl::FunctionRef<void(const core::StepResult&, const core::Env&, bool)>
        emit) {
  absl::MutexLock lock(&slot.mu);
  absl::Status status = CheckStarted(slot);
  if (!status.ok()) return status;
  if (slot.env->episode_over()) {
    if (!slot.auto_reset) {
      return absl::FailedPreconditionError(
          absl::StrCat("name: ", slot.name,
                       " episode is over; call ResetEnv (or create the env "
                       "with config.auto_reset)"));
    }
    ResetLocked(slot, std::nullopt);  // Continues the generator's stream.
    emit(slot.scratch, *slot.env, /*auto_reset=*/true);
    return absl::OkStatus();
  }
  status = CheckMode(slot, StepMode::kParallel);
  if (!status.ok()) return status;
  status = slot.env->Step(actions, &slot.scratch);
  if (!status.ok()) return status;
  slot.mode = StepMode::kParallel;
  emit(slot.scratch, *slot.env, /*auto_reset=*/false);
  return absl::OkStatus();
}

// "<prefix><index><suffix>", e.g. "steps[3].", without touching the heap:
// every item of a batch carries its field name, and few ever fail.
class ItemField {
 public:
  // `prefix` and `suffix` are short literals; beyond kAffixChars characters
  // each they would be cut.
  ItemField(absl::string_view prefix, int index, absl::string_view suffix) {
    prefix = prefix.substr(0, kAffixChars);
    suffix = suffix.substr(0, kAffixChars);
    char* end = std::copy(prefix.begin(), prefix.end(), buffer_);
    end = std::to_chars(end, end + kIntChars, index).ptr;
    end = std::copy(suffix.begin(), suffix.end(), end);
    size_ = static_cast<size_t>(end - buffer_);
  }
  absl::string_view view() const { return absl::string_view(buffer_, size_); }

 private:
  static constexpr size_t kAffixChars = 15;
  static constexpr size_t kIntChars = 11;  // "-2147483648".
  char buffer_[kAffixChars + kIntChars + kAffixChars];
  size_t size_;
};

// INVALID_ARGUMENT naming the first repeated name of a batch's `count`
// names; item_of(i) is how the error calls item i.
template <typename NameOf, typename ItemOf>
absl::Status CheckDistinctNames(int count, NameOf name_of, ItemOf item_of,
                                absl::string_view name_suffix) {
  absl::flat_hash_map<absl::string_view, int> first_index;
  first_index.reserve(count);
  for (int i = 0; i < count; ++i) {
    auto [it, inserted] = first_index.emplace(name_of(i), i);
    if (!inserted) {
      return absl::InvalidArgumentError(
          absl::StrCat(item_of(i).view(), name_suffix, ": ", name_of(i),
                       " also appears at ", item_of(it->second).view(),
                       "; the envs of one batch must be distinct"));
    }
  }
  return absl::OkStatus();
}

// The most names one KeepAlive renews: a client holding more sends several.
constexpr int kMaxKeepAliveNames = 10000;

void FillEnvLocked(const EnvSlot& slot, absl::Duration idle_timeout,
                   v1::Env* out) ABSL_EXCLUSIVE_LOCKS_REQUIRED(slot.mu) {
  out->set_name(slot.name);
  *out->mutable_config() = EnvConfigToProto(slot.config, slot.auto_reset);
  for (int i = 0; i < slot.config.n_landers; ++i) {
    out->add_possible_agents(core::AgentName(i));
  }
  *out->mutable_observation_space() = ObservationSpace();
  *out->mutable_action_space() = ActionSpace(slot.config);
  out->set_render_fps(50);
  out->set_episode_started(slot.env->episode_started());
  out->set_episode_over(slot.env->episode_over());
  out->set_cycles(slot.env->cycles());
  out->set_episodes(slot.episodes);
  out->set_session_bound(slot.session_bound);
  out->set_idle_timeout_s(absl::ToDoubleSeconds(idle_timeout));
}

}  // namespace

Operations::Operations(Registry* registry, WorkerPool* pool)
    : registry_(registry), pool_(pool) {}

absl::Status Operations::CreateEnv(const v1::CreateEnvRequest& request,
                                   bool session_bound, v1::Env* out,
                                   absl::string_view owner) {
  absl::StatusOr<core::EnvConfig> config = EnvConfigFromProto(request.config());
  if (!config.ok()) return config.status();
  absl::StatusOr<std::shared_ptr<EnvSlot>> slot = registry_->Create(
      *config, request.config().auto_reset(), session_bound, owner);
  if (!slot.ok()) return slot.status();
  absl::MutexLock lock(&(*slot)->mu);
  FillEnvLocked(**slot, registry_->idle_timeout(), out);
  return absl::OkStatus();
}

absl::Status Operations::GetEnv(const v1::GetEnvRequest& request, v1::Env* out,
                                absl::string_view owner) {
  absl::StatusOr<std::shared_ptr<EnvSlot>> slot =
      registry_->Find(request.name(), "name", owner);
  if (!slot.ok()) return slot.status();
  absl::MutexLock lock(&(*slot)->mu);
  FillEnvLocked(**slot, registry_->idle_timeout(), out);
  return absl::OkStatus();
}

absl::Status Operations::ListEnvs(const v1::ListEnvsRequest& request,
                                  v1::ListEnvsResponse* out,
                                  absl::string_view owner) {
  absl::StatusOr<Registry::Page> page =
      registry_->List(request.page_size(), request.page_token(), owner);
  if (!page.ok()) return page.status();
  for (const std::shared_ptr<EnvSlot>& slot : page->slots) {
    absl::MutexLock lock(&slot->mu);
    FillEnvLocked(*slot, registry_->idle_timeout(), out->add_envs());
  }
  out->set_next_page_token(page->next_page_token);
  return absl::OkStatus();
}

absl::Status Operations::DeleteEnv(const v1::DeleteEnvRequest& request,
                                   absl::string_view owner) {
  return registry_->Delete(request.name(), "name", owner);
}

absl::Status Operations::KeepAlive(const v1::KeepAliveRequest& request,
                                   v1::KeepAliveResponse* out,
                                   absl::string_view owner) {
  if (request.names_size() > kMaxKeepAliveNames) {
    return absl::InvalidArgumentError(absl::StrCat(
        "names: ", request.names_size(), " names (allowed: at most ",
        kMaxKeepAliveNames, " per call; send several calls)"));
  }
  for (int i = 0; i < request.names_size(); ++i) {
    // Find renews the lease; a name that is malformed, unknown or another
    // owner's is reported alike.
    if (!registry_->Find(request.names(i), "names", owner).ok()) {
      out->add_not_found(request.names(i));
    }
  }
  out->set_idle_timeout_s(absl::ToDoubleSeconds(registry_->idle_timeout()));
  return absl::OkStatus();
}

absl::Status Operations::ResetEnv(const v1::ResetEnvRequest& request,
                                  v1::ResetEnvResponse* out,
                                  absl::string_view owner) {
  absl::StatusOr<std::shared_ptr<EnvSlot>> found =
      registry_->Find(request.name(), "name", owner);
  if (!found.ok()) return found.status();
  EnvSlot& slot = **found;
  absl::MutexLock lock(&slot.mu);
  std::optional<uint64_t> seed;
  if (request.has_seed()) {
    seed = request.seed();
  } else if (!slot.seeded) {
    // Gymnasium seeds an unseeded first reset from entropy: independent envs
    // must not all replay seed 0.
    seed = registry_->DrawSeed();
  }
  if (seed.has_value()) {
    slot.seeded = true;
    out->set_seed(*seed);
  }
  ResetLocked(slot, seed);
  FillStepData(slot.scratch, *slot.env, /*auto_reset=*/false,
               out->mutable_data());
  FillAecState(*slot.aec, /*world_stepped=*/false, out->mutable_aec());
  return absl::OkStatus();
}

absl::Status Operations::StepEnv(const v1::StepEnvRequest& request,
                                 absl::string_view field, v1::StepData* out,
                                 absl::string_view owner) {
  absl::StatusOr<std::shared_ptr<EnvSlot>> found =
      registry_->Find(request.name(), absl::StrCat(field, "name"), owner);
  if (!found.ok()) return found.status();
  EnvSlot& slot = **found;
  ActionBuffer actions;
  absl::Status status = ParseActions(request.actions(), slot.config,
                                     absl::StrCat(field, "actions"), &actions);
  if (!status.ok()) return status;
  return StepSlot(
      slot, actions.view(),
      [out](const core::StepResult& result, const core::Env& env,
            bool auto_reset) { FillStepData(result, env, auto_reset, out); });
}

absl::Status Operations::StepAgent(const v1::StepAgentRequest& request,
                                   v1::StepAgentResponse* out,
                                   absl::string_view owner) {
  absl::StatusOr<std::shared_ptr<EnvSlot>> found =
      registry_->Find(request.name(), "name", owner);
  if (!found.ok()) return found.status();
  EnvSlot& slot = **found;
  absl::StatusOr<std::optional<core::AgentAction>> action =
      ParseAgentAction(request, slot.config);
  if (!action.ok()) return action.status();

  absl::MutexLock lock(&slot.mu);
  absl::Status status = CheckStarted(slot);
  if (!status.ok()) return status;
  if (request.has_agent() && request.agent() != slot.aec->agent_selection()) {
    return absl::FailedPreconditionError(
        absl::StrCat("agent: ", request.agent(), " is not agent_selection (",
                     slot.aec->agent_selection(), ") of ", slot.name));
  }
  status = CheckMode(slot, StepMode::kAec);
  if (!status.ok()) return status;
  const int cycles_before = slot.env->cycles();
  status = slot.aec->Step(*action);
  if (!status.ok()) return status;
  slot.mode = StepMode::kAec;
  FillAecState(*slot.aec, slot.env->cycles() != cycles_before,
               out->mutable_aec());
  return absl::OkStatus();
}

absl::Status Operations::RenderEnv(const v1::RenderEnvRequest& request,
                                   v1::Frame* out, absl::string_view owner) {
  if (!v1::FrameFormat_IsValid(request.format())) {
    return absl::InvalidArgumentError(
        absl::StrCat("format: ", request.format(),
                     " is not a FrameFormat (allowed: FRAME_FORMAT_RGB = 1, "
                     "FRAME_FORMAT_PNG = 2)"));
  }
  absl::StatusOr<std::shared_ptr<EnvSlot>> found =
      registry_->Find(request.name(), "name", owner);
  if (!found.ok()) return found.status();
  absl::StatusOr<core::Frame> frame;
  {
    absl::MutexLock lock(&(*found)->mu);
    frame = mll::core::RenderEnv(*(*found)->env);
  }
  if (!frame.ok()) return frame.status();
  out->set_width(frame->width);
  out->set_height(frame->height);
  if (request.format() == v1::FRAME_FORMAT_PNG) {
    // Encoding is pure and slow: done after the env is released.
    absl::StatusOr<std::string> png = core::EncodePng(*frame);
    if (!png.ok()) return png.status();
    out->set_format(v1::FRAME_FORMAT_PNG);
    out->set_data(*std::move(png));
  } else {
    out->set_format(v1::FRAME_FORMAT_RGB);
    out->set_data(reinterpret_cast<const char*>(frame->rgb.data()),
                  frame->rgb.size());
  }
  return absl::OkStatus();
}

void Operations::StepBatch(const v1::StepBatchRequest& request,
                           v1::StepBatchResponse* out,
                           std::function<void(absl::Status)> done,
                           absl::string_view owner, SessionBatches* batches) {
  if (request.has_packed()) {
    if (request.steps_size() > 0) {
      done(absl::InvalidArgumentError(absl::StrCat(
          "steps, packed: both set (", request.steps_size(),
          " steps and a packed batch of ", request.packed().names_size(),
          " envs); a StepBatchRequest carries exactly one of the two forms")));
      return;
    }
    StepPacked(request.packed(), out->mutable_packed(), std::move(done), owner,
               batches);
    return;
  }
  absl::Status status = CheckDistinctNames(
      request.steps_size(),
      [&request](int i) -> absl::string_view {
        return request.steps(i).name();
      },
      [](int i) { return ItemField("steps[", i, "]"); }, ".name");
  if (!status.ok()) {
    done(status);
    return;
  }
  for (int i = 0; i < request.steps_size(); ++i) out->add_results();
  pool_->ParallelFor(
      request.steps_size(),
      [this, &request, out, owner](int i) {
        v1::StepBatchResult* result = out->mutable_results(i);
        absl::Status status =
            StepEnv(request.steps(i), ItemField("steps[", i, "].").view(),
                    result->mutable_data(), owner);
        if (!status.ok()) FillItemError(status, result->mutable_error());
      },
      [done = std::move(done)] { done(absl::OkStatus()); });
}

void Operations::StepPacked(const v1::PackedSteps& request,
                            v1::PackedStepData* out,
                            std::function<void(absl::Status)> done,
                            absl::string_view owner, SessionBatches* batches) {
  const uint32_t handle = request.handle();
  const bool by_handle = handle != 0 && request.names_size() == 0;
  if (handle > SessionBatches::kMaxHandle) {
    done(absl::InvalidArgumentError(absl::StrCat(
        "packed.handle: ", handle, " is out of range (allowed: 0 for none, 1..",
        SessionBatches::kMaxHandle, ")")));
    return;
  }
  if (handle != 0 && batches == nullptr) {
    done(absl::InvalidArgumentError(absl::StrCat(
        "packed.handle: ", handle,
        " is set on a unary StepBatch (allowed: 0; handles exist only on a "
        "Session stream, which keeps them; send the names)")));
    return;
  }
  // The envs stepped before and their slots: a declared batch, or a recent
  // batch naming the same envs in the same order (distinct, then).
  const SessionBatches::Batch* kept = nullptr;
  if (by_handle) {
    kept = batches->Declared(handle);
    if (kept == nullptr) {
      done(absl::NotFoundError(absl::StrCat(
          "packed.handle: ", handle,
          " is not declared on this session (a handle is declared by a "
          "packed StepBatch carrying it with the names of its envs, on the "
          "same Session stream; a new stream has none)")));
      return;
    }
  } else if (batches != nullptr && handle == 0) {
    kept = batches->Match(request.names());
  }
  const int num_envs = kept != nullptr ? static_cast<int>(kept->names.size())
                                       : request.names_size();
  absl::StatusOr<PackedActions> actions =
      PackedActions::Parse(request, num_envs);
  if (!actions.ok()) {
    done(actions.status());
    return;
  }
  if (kept == nullptr) {
    absl::Status status = CheckDistinctNames(
        request.names_size(),
        [&request](int e) -> absl::string_view { return request.names(e); },
        [](int e) { return ItemField("packed.names[", e, "]"); }, "");
    if (status.ok() && handle != 0) {
      status = batches->CheckDeclare(handle, num_envs, "packed.handle");
    }
    if (!status.ok()) {
      done(status);
      return;
    }
  }
  // The envs' names: the declared batch's, or the request's.
  const std::vector<std::string>* declared_names =
      by_handle ? &kept->names : nullptr;
  // Lives until the last item is done; workers write disjoint rows of the
  // columns (sized here, once) and their own entries of `statuses` and
  // `slots`.
  struct Batch {
    Batch(PackedActions actions, int num_envs, v1::PackedStepData* out,
          bool keep)
        : actions(std::move(actions)),
          columns(num_envs, this->actions.n_landers(), out),
          statuses(num_envs),
          slots(keep ? num_envs : 0) {}
    const PackedActions actions;
    const PackedColumns columns;
    std::vector<absl::Status> statuses;
    // The slots found, for SessionBatches::Keep or Declare (empty: neither).
    std::vector<std::weak_ptr<EnvSlot>> slots;
  };
  auto batch = std::make_shared<Batch>(*std::move(actions), num_envs, out,
                                       batches != nullptr && kept == nullptr);
  const int n_landers = std::max(1, batch->actions.n_landers());
  pool_->ParallelFor(
      num_envs,
      [this, &request, declared_names, batch, owner, kept, num_envs](int e) {
        // This runner's next env is most often e + 1.
        if (kept != nullptr && e + 1 < num_envs) {
          SessionBatches::Prefetch(*kept, e + 1);
        }
        batch->statuses[e] = [&]() -> absl::Status {
          std::shared_ptr<EnvSlot> slot =
              kept != nullptr ? SessionBatches::Find(*kept, e, owner) : nullptr;
          if (slot == nullptr) {
            absl::StatusOr<std::shared_ptr<EnvSlot>> found = registry_->Find(
                declared_names != nullptr ? (*declared_names)[e]
                                          : request.names(e),
                ItemField("packed.names[", e, "]").view(), owner);
            if (!found.ok()) return found.status();
            slot = *std::move(found);
            if (!batch->slots.empty()) batch->slots[e] = slot;
          }
          absl::Status status = batch->actions.CheckFits(e, slot->config);
          if (!status.ok()) return status;
          return StepSlot(*slot, batch->actions.Row(e),
                          [&](const core::StepResult& result,
                              const core::Env& env, bool auto_reset) {
                            batch->columns.Write(e, result, env, auto_reset);
                          });
        }();
      },
      [batch, out, &request, batches, handle, done = std::move(done)] {
        // Appended here, in index order: workers never touch `errors`.
        for (int e = 0; e < static_cast<int>(batch->statuses.size()); ++e) {
          if (batch->statuses[e].ok()) continue;
          v1::IndexedItemError* error = out->add_errors();
          error->set_index(e);
          FillItemError(batch->statuses[e], error->mutable_error());
        }
        // An env not found is kept as no slot: looked up again next time.
        if (!batch->slots.empty()) {
          if (handle != 0) {
            batches->Declare(handle, request.names(), std::move(batch->slots));
          } else {
            batches->Keep(request.names(), std::move(batch->slots));
          }
        }
        done(absl::OkStatus());
      },
      (kMinAgentStepsPerRunner + n_landers - 1) / n_landers);
}

}  // namespace mll::service

// What each RPC does, independent of how it arrived (unary call or Session
// stream): parse, look up, call the core, convert. Every method validates its
// request completely before touching an environment and reports failures as
// absl::Status with the field, the value and what is allowed.
#ifndef MLL_SERVICE_OPERATIONS_H_
#define MLL_SERVICE_OPERATIONS_H_

#include <functional>

#include "absl/status/status.h"
#include "absl/strings/string_view.h"
#include "mll/service/auth.h"
#include "mll/service/registry.h"
#include "mll/service/worker_pool.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::service {

class Operations {
 public:
  // Neither is owned; both must outlive this object.
  Operations(Registry* registry, WorkerPool* pool);

  // Every method acts for `owner`, the authenticated caller (auth.h): it
  // creates envs for it and sees only its envs (Registry).

  // `session_bound`: the env dies with the session creating it.
  absl::Status CreateEnv(const v1::CreateEnvRequest& request,
                         bool session_bound, v1::Env* out,
                         absl::string_view owner = kAnonymousOwner);
  absl::Status GetEnv(const v1::GetEnvRequest& request, v1::Env* out,
                      absl::string_view owner = kAnonymousOwner);
  absl::Status ListEnvs(const v1::ListEnvsRequest& request,
                        v1::ListEnvsResponse* out,
                        absl::string_view owner = kAnonymousOwner);
  absl::Status DeleteEnv(const v1::DeleteEnvRequest& request,
                         absl::string_view owner = kAnonymousOwner);
  // Renews the lease of each named env; names it cannot find go to
  // out->not_found. INVALID_ARGUMENT for more than 10000 names.
  absl::Status KeepAlive(const v1::KeepAliveRequest& request,
                         v1::KeepAliveResponse* out,
                         absl::string_view owner = kAnonymousOwner);
  absl::Status ResetEnv(const v1::ResetEnvRequest& request,
                        v1::ResetEnvResponse* out,
                        absl::string_view owner = kAnonymousOwner);
  // `field` prefixes the request's field names in errors ("" for a single
  // call, "steps[3]." inside a batch).
  absl::Status StepEnv(const v1::StepEnvRequest& request,
                       absl::string_view field, v1::StepData* out,
                       absl::string_view owner = kAnonymousOwner);
  absl::Status StepAgent(const v1::StepAgentRequest& request,
                         v1::StepAgentResponse* out,
                         absl::string_view owner = kAnonymousOwner);
  absl::Status RenderEnv(const v1::RenderEnvRequest& request, v1::Frame* out,
                         absl::string_view owner = kAnonymousOwner);

  // Steps the batch's envs on the worker pool and calls done() with the
  // call's status once every item has its result or error in `out`: the
  // `steps` form answers in out->results, the `packed` form in out->packed.
  // Returns at once. A request-level error (both forms set, duplicate names,
  // a packed actions array of the wrong dtype or shape) calls done() before
  // returning, with no env stepped. `request` and `out` must live until
  // done() runs, and `owner`'s characters too. `batches` (null: a unary
  // call, which has none): the Session's packed batches. A packed batch with
  // a handle declares it or steps the batch declared as it; one without
  // names the same envs in the same order as a recent one uses its slots, or
  // joins the recent ones. It must not be used elsewhere until done() has
  // run.
  void StepBatch(const v1::StepBatchRequest& request,
                 v1::StepBatchResponse* out,
                 std::function<void(absl::Status)> done,
                 absl::string_view owner = kAnonymousOwner,
                 SessionBatches* batches = nullptr);

 private:
  // StepBatch's `packed` form.
  void StepPacked(const v1::PackedSteps& request, v1::PackedStepData* out,
                  std::function<void(absl::Status)> done,
                  absl::string_view owner, SessionBatches* batches);

  Registry* registry_;
  WorkerPool* pool_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_OPERATIONS_H_

// The gRPC face of the server: mll.v1.MultiLunarLander on gRPC's callback
// API. Each handler parses nothing itself: it authenticates the caller
// (auth.h), hands the request to Operations on the caller's behalf, records
// the call in Metrics and finishes with the status mapped by ToGrpcStatus.
// Handlers never wait: StepBatch completes from the worker pool.
#ifndef MLL_SERVICE_SERVICE_H_
#define MLL_SERVICE_SERVICE_H_

#include <atomic>
#include <cstdint>
#include <memory>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"
#include "absl/time/time.h"
#include "grpcpp/grpcpp.h"
#include "mll/service/auth.h"
#include "mll/service/metrics.h"
#include "mll/service/operations.h"
#include "mll/service/registry.h"
#include "mll/service/worker_pool.h"
#include "mll/v1/multi_lunar_lander.grpc.pb.h"

namespace mll::service {

struct ServiceOptions {
  // Worker threads for StepBatch (--threads). >= 1.
  int threads = 1;
  // Most environments hosted at once (--max_envs). >= 1.
  int max_envs = 10000;
  // Most environments one token (tenant) hosts at once
  // (--max_envs_per_token). >= 0; 0 picks the default of
  // EffectiveMaxEnvsPerToken.
  int max_envs_per_token = 0;
  // An env untouched this long is destroyed (--idle_timeout_s). > 0.
  absl::Duration idle_timeout = absl::Seconds(300);
  // Bearer tokens a caller must present (--auth_token_file, read with
  // ReadTokenFile); empty: no authentication, one anonymous owner.
  std::vector<std::string> auth_tokens;
  // Most Sessions attached to shared memory at once, each served by a
  // thread of its own (--shared_memory_sessions). >= 0; 0 refuses every
  // attach (the sessions stay on their streams).
  int shared_memory_sessions = 64;
  // The largest message the server's listener takes or sends, in bytes, as
  // GetServerInfo reports it (Server::Start sets it from --max_message_mb);
  // 0: unknown.
  int64_t max_message_bytes = 0;
};

// The count of Sessions attached to shared memory, bounded by
// ServiceOptions::shared_memory_sessions: Take() hands out a Slot, which
// gives its place back when it goes.
class SharedMemorySessions {
 public:
  class Slot {
   public:
    Slot() = default;
    explicit Slot(std::atomic<int>* attached) : attached_(attached) {}
    Slot(Slot&& other) noexcept
        : attached_(std::exchange(other.attached_, nullptr)) {}
    Slot& operator=(Slot&& other) noexcept {
      Release();
      attached_ = std::exchange(other.attached_, nullptr);
      return *this;
    }
    ~Slot() { Release(); }

   private:
    void Release() {
      if (attached_ != nullptr) attached_->fetch_sub(1);
      attached_ = nullptr;
    }
    std::atomic<int>* attached_ = nullptr;
  };

  explicit SharedMemorySessions(int limit) : limit_(limit) {}
  // A slot, or PERMISSION_DENIED when the limit is 0, RESOURCE_EXHAUSTED
  // when every slot is taken.
  absl::StatusOr<Slot> Take();

 private:
  const int limit_;
  std::atomic<int> attached_{0};
};

// The per-token quota `options` give: max_envs_per_token when set; else,
// with tokens, max(1, max_envs / tokens), so that every tenant can always
// get its share however many envs the others hold; without tokens 0
// (unlimited: every caller is the one anonymous tenant).
int EffectiveMaxEnvsPerToken(const ServiceOptions& options);

// The message every refusal of a draining server starts with, which clients
// recognise as "move to another server" (UNAVAILABLE, so that a client's
// failover moves its envs).
inline constexpr absl::string_view kDrainingPrefix = "draining: ";

class SessionTracker;  // The open Session streams (service.cc).

class MultiLunarLanderService final
    : public v1::MultiLunarLander::CallbackService {
 public:
  explicit MultiLunarLanderService(const ServiceOptions& options);
  ~MultiLunarLanderService() override;

  Registry& registry() { return registry_; }
  // Who a caller is, for the dashboard's own token check.
  const Authenticator& authenticator() const { return authenticator_; }
  // The Prometheus exposition of the metrics and the live env count.
  std::string MetricsText();
  // From now on new calls and Session streams get UNAVAILABLE, so clients
  // go elsewhere while admitted calls finish (Server::Shutdown).
  void RefuseNewCalls() { refusing_.store(true); }
  // Starts draining (Server::Drain): CreateEnv, GetServerInfo and new
  // Session streams get UNAVAILABLE "draining: ..."; every open Session
  // stream is ended with UNAVAILABLE "draining: ..." once its operation in
  // flight, if any, has answered (its bound envs deleted first); calls on
  // existing envs go on being served. Idempotent.
  void StartDraining();
  bool draining() const { return draining_.load(); }

  grpc::ServerUnaryReactor* CreateEnv(grpc::CallbackServerContext* context,
                                      const v1::CreateEnvRequest* request,
                                      v1::Env* response) override;
  grpc::ServerUnaryReactor* GetEnv(grpc::CallbackServerContext* context,
                                   const v1::GetEnvRequest* request,
                                   v1::Env* response) override;
  grpc::ServerUnaryReactor* ListEnvs(grpc::CallbackServerContext* context,
                                     const v1::ListEnvsRequest* request,
                                     v1::ListEnvsResponse* response) override;
  grpc::ServerUnaryReactor* DeleteEnv(grpc::CallbackServerContext* context,
                                      const v1::DeleteEnvRequest* request,
                                      v1::DeleteEnvResponse* response) override;
  grpc::ServerUnaryReactor* ResetEnv(grpc::CallbackServerContext* context,
                                     const v1::ResetEnvRequest* request,
                                     v1::ResetEnvResponse* response) override;
  grpc::ServerUnaryReactor* StepEnv(grpc::CallbackServerContext* context,
                                    const v1::StepEnvRequest* request,
                                    v1::StepEnvResponse* response) override;
  grpc::ServerUnaryReactor* StepAgent(grpc::CallbackServerContext* context,
                                      const v1::StepAgentRequest* request,
                                      v1::StepAgentResponse* response) override;
  grpc::ServerUnaryReactor* StepBatch(grpc::CallbackServerContext* context,
                                      const v1::StepBatchRequest* request,
                                      v1::StepBatchResponse* response) override;
  grpc::ServerUnaryReactor* RenderEnv(grpc::CallbackServerContext* context,
                                      const v1::RenderEnvRequest* request,
                                      v1::Frame* response) override;
  grpc::ServerUnaryReactor* KeepAlive(grpc::CallbackServerContext* context,
                                      const v1::KeepAliveRequest* request,
                                      v1::KeepAliveResponse* response) override;
  grpc::ServerUnaryReactor* GetServerInfo(
      grpc::CallbackServerContext* context,
      const v1::GetServerInfoRequest* request,
      v1::ServerInfo* response) override;

 private:
  // The caller of a new call (see Authenticator), or UNAVAILABLE once
  // RefuseNewCalls ran.
  absl::StatusOr<absl::string_view> Admit(
      const grpc::CallbackServerContext& context) const;
  // As Admit, for calls that start new work here (CreateEnv, GetServerInfo,
  // a Session stream): also UNAVAILABLE while draining.
  absl::StatusOr<absl::string_view> AdmitNewWork(
      const grpc::CallbackServerContext& context, absl::string_view what) const;

  // A Session stream (registered as a raw method in the constructor: the
  // stream parses its requests itself, reusing their storage; see
  // SessionMessages in service.cc).
  grpc::ServerBidiReactor<grpc::ByteBuffer, grpc::ByteBuffer>* OpenSession(
      grpc::CallbackServerContext* context);
  // GetServerInfo's load: envs hosted, CPU and agent-steps over the last
  // 10 s, cores available, now.
  void FillLoad(v1::ServerLoad* load);

  // Puts each StepBatch call's request and response on one protobuf arena:
  // a `steps` batch of 64 envs is ~2,000 sub-messages and strings, which
  // would otherwise be as many mallocs and frees per call.
  class StepBatchArenas final
      : public grpc::MessageAllocator<v1::StepBatchRequest,
                                      v1::StepBatchResponse> {
   public:
    grpc::MessageHolder<v1::StepBatchRequest, v1::StepBatchResponse>*
    AllocateMessages() override;
  };

  std::atomic<bool> refusing_{false};
  std::atomic<bool> draining_{false};
  const std::unique_ptr<SessionTracker> sessions_;
  StepBatchArenas step_batch_arenas_;
  // Declared in this order so that destruction first stops the workers
  // (finishing queued steps), which use the operations, the envs, the
  // owners' names and the metrics.
  const Authenticator authenticator_;
  Metrics metrics_;
  Registry registry_;
  Operations operations_;
  WorkerPool pool_;
  SharedMemorySessions shared_memory_sessions_;
  // GetServerInfo's answer but its load, fixed at construction
  // (server_info.h).
  const v1::ServerInfo server_info_;
};

}  // namespace mll::service

#endif  // MLL_SERVICE_SERVICE_H_

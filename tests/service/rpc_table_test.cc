// The places an RPC is named besides the proto, checked against the proto's
// descriptors (docs/design.md, "Adding an RPC"): the RPC table
// (MLL_RPCS in mll/session_ops.h) that the metrics' Method enum, the server's
// Session dispatch and the C++ client's unary transport expand, and a handler
// for every method of the service, each counted under its own label.
#include <future>
#include <set>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "gmock/gmock.h"
#include "google/protobuf/descriptor.h"
#include "grpcpp/generic/generic_stub.h"
#include "gtest/gtest.h"
#include "mll/service/metrics.h"
#include "mll/session_ops.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::google::protobuf::FieldDescriptor;
using ::google::protobuf::MethodDescriptor;

struct SessionOp {
  int op_case;
  std::string request_member;
  std::string rpc;
  std::string response_member;
};

std::vector<SessionOp> SessionOps() {
  return {
#define MLL_ROW(op_case, request_member, rpc, response_member) \
  {v1::SessionRequest::op_case, #request_member, #rpc, #response_member},
      MLL_SESSION_OPS(MLL_ROW)
#undef MLL_ROW
  };
}

struct RpcRow {
  std::string method;  // The enumerator's name, "kStepEnv".
  std::string rpc;
};

std::vector<RpcRow> RpcRows() {
  return {
#define MLL_SESSION_ROW(method, request_member, rpc, response_member) \
  {#method, #rpc},
#define MLL_OTHER_ROW(method, rpc) {#method, #rpc},
      MLL_RPCS(MLL_SESSION_ROW, MLL_SESSION_ROW, MLL_OTHER_ROW)
#undef MLL_SESSION_ROW
#undef MLL_OTHER_ROW
  };
}

// The count of `method`'s calls in the /metrics text.
double CallCount(const std::string& metrics, absl::string_view method) {
  const std::string prefix =
      absl::StrCat("mll_rpc_duration_seconds_count{method=\"", method, "\"} ");
  const size_t at = metrics.find(prefix);
  if (at == std::string::npos) return -1;
  const size_t end = metrics.find('\n', at);
  double count = -1;
  EXPECT_TRUE(absl::SimpleAtod(
      metrics.substr(at + prefix.size(), end - at - prefix.size()), &count));
  return count;
}

TEST(RpcTableTest, MethodEnumIsTheServiceDescriptorsMethods) {
  const google::protobuf::ServiceDescriptor& service = ServiceDescriptor();
  EXPECT_EQ(service.full_name(), "mll.v1.MultiLunarLander");
  ASSERT_EQ(kMethodCount, service.method_count())
      << "metrics.h's Method enum and kMethodCount, expanded from MLL_RPCS, "
         "list every RPC of the proto's service";
  std::set<std::string> labels;
  for (int i = 0; i < kMethodCount; ++i) {
    labels.insert(std::string(MethodName(static_cast<Method>(i))));
  }
  EXPECT_EQ(labels.size(), static_cast<size_t>(kMethodCount));
  // The enumerators the server files calls under, at their RPC's index.
  EXPECT_EQ(MethodName(Method::kCreateEnv), "CreateEnv");
  EXPECT_EQ(MethodName(Method::kRenderEnv), "RenderEnv");
  EXPECT_EQ(MethodName(Method::kSession), "Session");
  EXPECT_EQ(MethodName(Method::kGetServerInfo), "GetServerInfo");
}

TEST(RpcTableTest, RpcTableIsTheServiceDescriptorsMethodsInOrder) {
  const google::protobuf::ServiceDescriptor& service = ServiceDescriptor();
  std::vector<std::string> in_proto;
  for (int i = 0; i < service.method_count(); ++i) {
    in_proto.push_back(service.method(i)->name());
  }
  std::vector<std::string> in_table;
  for (const RpcRow& row : RpcRows()) {
    in_table.push_back(row.rpc);
    EXPECT_EQ(row.method, absl::StrCat("k", row.rpc));
  }
  EXPECT_EQ(in_table, in_proto)
      << "mll/session_ops.h's MLL_RPCS has one row per RPC of the proto's "
         "service, in its order";
}

TEST(RpcTableTest, SessionOpsTableMatchesTheProto) {
  const google::protobuf::Descriptor& request =
      *v1::SessionRequest::descriptor();
  const google::protobuf::Descriptor& response =
      *v1::SessionResponse::descriptor();
  std::set<std::string> listed;
  for (const SessionOp& op : SessionOps()) {
    SCOPED_TRACE(op.rpc);
    const FieldDescriptor* in = request.FindFieldByName(op.request_member);
    const FieldDescriptor* out = response.FindFieldByName(op.response_member);
    const MethodDescriptor* rpc = ServiceDescriptor().FindMethodByName(op.rpc);
    ASSERT_NE(in, nullptr);
    ASSERT_NE(out, nullptr);
    ASSERT_NE(rpc, nullptr);
    EXPECT_EQ(in->number(), op.op_case);
    ASSERT_NE(in->containing_oneof(), nullptr);
    EXPECT_EQ(in->containing_oneof()->name(), "op");
    ASSERT_NE(out->containing_oneof(), nullptr);
    EXPECT_EQ(out->containing_oneof()->name(), "result");
    EXPECT_EQ(in->message_type(), rpc->input_type());
    EXPECT_EQ(out->message_type(), rpc->output_type());
    listed.insert(op.request_member);
  }
  // Every operation of a Session but its own attach_shared_memory is an
  // RPC's, and needs its row.
  const google::protobuf::OneofDescriptor& ops = *request.FindOneofByName("op");
  for (int i = 0; i < ops.field_count(); ++i) {
    const std::string& name = ops.field(i)->name();
    if (name == "attach_shared_memory") continue;
    EXPECT_TRUE(listed.count(name))
        << "SessionRequest." << name << " has no row in mll/session_ops.h";
  }
}

// Each RPC of the descriptor is served (the generated base class would
// answer UNIMPLEMENTED) and counted under its own name: an empty request
// is a valid message of every request type.
TEST(RpcTableTest, EveryMethodIsServedAndCountedUnderItsName) {
  InProcess s;
  std::shared_ptr<grpc::Channel> channel = s.server->InProcessChannel();
  grpc::GenericStub generic(channel);
  const google::protobuf::ServiceDescriptor& service = ServiceDescriptor();
  for (int i = 0; i < service.method_count(); ++i) {
    const MethodDescriptor& method = *service.method(i);
    SCOPED_TRACE(method.name());
    grpc::ClientContext context;
    if (method.client_streaming() || method.server_streaming()) {
      ASSERT_EQ(method.name(), "Session");
      auto stream = s.stub->Session(&context);
      v1::SessionRequest request;
      v1::SessionResponse response;
      ASSERT_TRUE(stream->Write(request));
      ASSERT_TRUE(stream->Read(&response));
      EXPECT_EQ(response.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
      EXPECT_EQ(response.error().message(),
                "op: not set (sequence 0); allowed: create_env, reset_env, "
                "step_env, step_agent, step_batch, render_env, delete_env, "
                "get_env, attach_shared_memory");
      stream->WritesDone();
      EXPECT_TRUE(stream->Finish().ok());
    } else {
      grpc::Slice empty(std::string{});
      grpc::ByteBuffer request(&empty, 1);
      grpc::ByteBuffer response;
      std::promise<grpc::Status> done;
      generic.UnaryCall(
          &context, absl::StrCat("/", service.full_name(), "/", method.name()),
          grpc::StubOptions(), &request, &response,
          [&done](grpc::Status status) { done.set_value(status); });
      EXPECT_NE(done.get_future().get().error_code(),
                grpc::StatusCode::UNIMPLEMENTED);
    }
    EXPECT_EQ(CallCount(s.server->service().MetricsText(), method.name()), 1);
  }
}

}  // namespace
}  // namespace mll::service::testing

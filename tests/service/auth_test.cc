// Bearer-token authentication and per-token ownership of environments: the
// token file, the Authenticator, and a real server (in-process channel)
// reached with no token, wrong tokens and two valid ones, over every unary
// method and the Session stream.
#include "mll/service/auth.h"

#include <chrono>
#include <fstream>
#include <functional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "absl/strings/str_replace.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "server_process.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::AllOf;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using ::testing::IsEmpty;
using ::testing::Not;

constexpr char kAlpha[] = "alpha-7f3c";
constexpr char kBeta[] = "beta-19d2";
// A well-formed name that no server has created.
constexpr char kUnknownName[] = "envs/00000000000000000000000000000000";

std::string WriteFile(const std::string& name, const std::string& contents) {
  const std::string path = ::testing::TempDir() + name;
  std::ofstream(path, std::ios::trunc) << contents;
  return path;
}

TEST(ReadTokenFileTest, SkipsBlankLinesCommentsAndDuplicates) {
  const std::string path = WriteFile(
      "tokens_ok.txt", "# trainers\n\n  alpha  \r\nbeta\n\t\nalpha\n#x\n");
  absl::StatusOr<std::vector<std::string>> tokens = ReadTokenFile(path);
  ASSERT_TRUE(tokens.ok()) << tokens.status();
  EXPECT_THAT(*tokens, ElementsAre("alpha", "beta"));
}

TEST(ReadTokenFileTest, RejectsMissingEmptyAndMalformedFiles) {
  absl::StatusOr<std::vector<std::string>> tokens =
      ReadTokenFile(::testing::TempDir() + "no_such_tokens.txt");
  EXPECT_EQ(tokens.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(tokens.status().message(),
              HasSubstr("--auth_token_file: cannot read"));

  tokens = ReadTokenFile(WriteFile("tokens_empty.txt", "# none\n\n"));
  EXPECT_EQ(tokens.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(tokens.status().message(), HasSubstr("holds no token"));

  tokens = ReadTokenFile(WriteFile("tokens_space.txt", "ok\nsecret part\n"));
  EXPECT_EQ(tokens.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(tokens.status().message(),
              AllOf(HasSubstr("line 2"), Not(HasSubstr("secret"))));
}

TEST(AuthenticatorTest, OffMeansOneAnonymousOwner) {
  const Authenticator off({});
  EXPECT_FALSE(off.enabled());
  for (std::optional<absl::string_view> value :
       {std::optional<absl::string_view>(),
        std::optional<absl::string_view>("Bearer anything")}) {
    absl::StatusOr<absl::string_view> owner = off.Authenticate(value);
    ASSERT_TRUE(owner.ok());
    EXPECT_EQ(*owner, kAnonymousOwner);
  }
}

TEST(AuthenticatorTest, AcceptsOnlyItsBearerTokens) {
  const Authenticator auth({kAlpha, kBeta});
  EXPECT_TRUE(auth.enabled());

  absl::StatusOr<absl::string_view> alpha =
      auth.Authenticate(absl::StrCat("Bearer ", kAlpha));
  absl::StatusOr<absl::string_view> beta =
      auth.Authenticate(absl::StrCat("Bearer ", kBeta));
  // The scheme is case-insensitive (RFC 7235).
  absl::StatusOr<absl::string_view> alpha_again =
      auth.Authenticate(absl::StrCat("bearer ", kAlpha));
  ASSERT_TRUE(alpha.ok() && beta.ok() && alpha_again.ok());
  EXPECT_NE(*alpha, *beta);
  EXPECT_EQ(*alpha, *alpha_again);
  EXPECT_NE(*alpha, kAnonymousOwner);
  // Owners name tokens without containing them.
  EXPECT_THAT(std::string(*alpha), Not(HasSubstr(kAlpha)));

  struct Case {
    std::optional<absl::string_view> value;
    const char* problem;
  };
  const std::string prefix_of_alpha = std::string("Bearer ") + "alpha";
  const std::string longer_alpha = absl::StrCat("Bearer ", kAlpha, "x");
  for (const Case& c :
       std::vector<Case>{{std::nullopt, "missing"},
                         {"Basic YWxwaGE=", "not of the form `Bearer <token>`"},
                         {"Bearer ", "not of the form `Bearer <token>`"},
                         {kAlpha, "not of the form `Bearer <token>`"},
                         {"Bearer wrong-token", "the token is not accepted"},
                         {prefix_of_alpha, "the token is not accepted"},
                         {longer_alpha, "the token is not accepted"}}) {
    absl::StatusOr<absl::string_view> owner = auth.Authenticate(c.value);
    ASSERT_FALSE(owner.ok()) << c.value.value_or("(none)");
    EXPECT_EQ(owner.status().code(), absl::StatusCode::kUnauthenticated);
    EXPECT_THAT(owner.status().message(),
                AllOf(HasSubstr(c.problem),
                      HasSubstr("expects `authorization: Bearer <token>`"),
                      Not(HasSubstr("wrong-token")), Not(HasSubstr("YWxw"))));
  }
}

// A server with the tokens alpha and beta.
class AuthServerTest : public ::testing::Test {
 protected:
  AuthServerTest() : s_(WithTokens({kAlpha, kBeta})) {}

  static ServiceOptions WithTokens(std::vector<std::string> tokens) {
    ServiceOptions options;
    options.auth_tokens = std::move(tokens);
    return options;
  }

  // Creates and resets a 2-lander env that renders, as `token`.
  std::string CreateAs(const std::string& token) {
    grpc::ClientContext context;
    AddToken(token, &context);
    v1::CreateEnvRequest request = CreateRequest(2);
    request.mutable_config()->set_render_mode(v1::RENDER_MODE_RGB_ARRAY);
    v1::Env env;
    EXPECT_TRUE(s_.stub->CreateEnv(&context, request, &env).ok());
    grpc::ClientContext reset_context;
    AddToken(token, &reset_context);
    v1::ResetEnvRequest reset;
    reset.set_name(env.name());
    reset.set_seed(3);
    v1::ResetEnvResponse response;
    EXPECT_TRUE(s_.stub->ResetEnv(&reset_context, reset, &response).ok());
    return env.name();
  }

  // The names `token` lists.
  std::vector<std::string> ListAs(const std::string& token) {
    grpc::ClientContext context;
    AddToken(token, &context);
    v1::ListEnvsResponse response;
    EXPECT_TRUE(
        s_.stub->ListEnvs(&context, v1::ListEnvsRequest(), &response).ok());
    std::vector<std::string> names;
    for (const v1::Env& env : response.envs()) names.push_back(env.name());
    return names;
  }

  InProcess s_;
};

// Every unary method on the env `name`, each with a context prepared by
// `prepare`; the status of each (StepBatch: its item's, or the call's when
// the call fails). DeleteEnv comes last.
std::vector<std::pair<std::string, grpc::Status>> CallEveryMethod(
    v1::MultiLunarLander::Stub& stub, const std::string& name,
    const std::function<void(grpc::ClientContext*)>& prepare) {
  std::vector<std::pair<std::string, grpc::Status>> statuses;
  auto call = [&](const char* method, auto rpc) {
    grpc::ClientContext context;
    prepare(&context);
    statuses.emplace_back(method, rpc(&context));
  };
  call("CreateEnv", [&](grpc::ClientContext* c) {
    v1::Env env;
    return stub.CreateEnv(c, CreateRequest(1), &env);
  });
  call("ListEnvs", [&](grpc::ClientContext* c) {
    v1::ListEnvsResponse response;
    return stub.ListEnvs(c, v1::ListEnvsRequest(), &response);
  });
  call("GetEnv", [&](grpc::ClientContext* c) {
    v1::GetEnvRequest request;
    request.set_name(name);
    v1::Env env;
    return stub.GetEnv(c, request, &env);
  });
  call("StepEnv", [&](grpc::ClientContext* c) {
    v1::StepEnvRequest request;
    request.set_name(name);
    *request.mutable_actions() = DiscreteActions({0, 2});
    v1::StepEnvResponse response;
    return stub.StepEnv(c, request, &response);
  });
  call("StepBatch", [&](grpc::ClientContext* c) {
    v1::StepBatchRequest request;
    request.add_steps()->set_name(name);
    *request.mutable_steps(0)->mutable_actions() = DiscreteActions({0, 2});
    v1::StepBatchResponse response;
    grpc::Status status = stub.StepBatch(c, request, &response);
    if (!status.ok() || !response.results(0).has_error()) return status;
    return grpc::Status(
        static_cast<grpc::StatusCode>(response.results(0).error().code()),
        response.results(0).error().message());
  });
  call("RenderEnv", [&](grpc::ClientContext* c) {
    v1::RenderEnvRequest request;
    request.set_name(name);
    request.set_format(v1::FRAME_FORMAT_RGB);
    v1::Frame frame;
    return stub.RenderEnv(c, request, &frame);
  });
  call("ResetEnv", [&](grpc::ClientContext* c) {
    v1::ResetEnvRequest request;
    request.set_name(name);
    v1::ResetEnvResponse response;
    return stub.ResetEnv(c, request, &response);
  });
  call("StepAgent", [&](grpc::ClientContext* c) {
    v1::StepAgentRequest request;
    request.set_name(name);
    request.mutable_action()->set_discrete(2);
    v1::StepAgentResponse response;
    return stub.StepAgent(c, request, &response);
  });
  call("KeepAlive", [&](grpc::ClientContext* c) {
    v1::KeepAliveRequest request;
    request.add_names(name);
    v1::KeepAliveResponse response;
    return stub.KeepAlive(c, request, &response);
  });
  call("DeleteEnv", [&](grpc::ClientContext* c) {
    v1::DeleteEnvRequest request;
    request.set_name(name);
    v1::DeleteEnvResponse response;
    return stub.DeleteEnv(c, request, &response);
  });
  return statuses;
}

TEST_F(AuthServerTest, EveryMethodRefusesMissingOrWrongTokens) {
  const std::string name = CreateAs(kAlpha);
  const std::vector<std::function<void(grpc::ClientContext*)>> bad = {
      [](grpc::ClientContext*) {},
      [](grpc::ClientContext* c) { AddToken("not-a-token", c); },
      [](grpc::ClientContext* c) {
        c->AddMetadata("authorization", std::string("Basic ") + kAlpha);
      },
  };
  for (const auto& prepare : bad) {
    for (const auto& [method, status] :
         CallEveryMethod(*s_.stub, name, prepare)) {
      EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAUTHENTICATED)
          << method;
      EXPECT_THAT(status.error_message(),
                  AllOf(HasSubstr("authorization: Bearer <token>"),
                        Not(HasSubstr("not-a-token")), Not(HasSubstr(kAlpha))))
          << method;
    }
  }
  // Nothing above touched the env or created one.
  EXPECT_THAT(ListAs(kAlpha), ElementsAre(name));
  EXPECT_EQ(s_.server->service().registry().size(), 1);
}

TEST_F(AuthServerTest, AnotherTokensEnvIsNotFoundLikeAnUnknownName) {
  const std::string name = CreateAs(kAlpha);
  const auto as_beta = [](grpc::ClientContext* c) { AddToken(kBeta, c); };
  const auto theirs = CallEveryMethod(*s_.stub, name, as_beta);
  const auto unknown = CallEveryMethod(*s_.stub, kUnknownName, as_beta);
  ASSERT_EQ(theirs.size(), unknown.size());
  for (size_t i = 0; i < theirs.size(); ++i) {
    const auto& [method, status] = theirs[i];
    // KeepAlive reports unknown names in its response (TenancyTest).
    if (method == "CreateEnv" || method == "ListEnvs" ||
        method == "KeepAlive") {
      EXPECT_TRUE(status.ok()) << method << ": " << status.error_message();
      continue;
    }
    EXPECT_EQ(status.error_code(), grpc::StatusCode::NOT_FOUND) << method;
    // Same words as for a name nobody created: existence does not leak.
    EXPECT_EQ(absl::StrReplaceAll(status.error_message(), {{name, "NAME"}}),
              absl::StrReplaceAll(unknown[i].second.error_message(),
                                  {{kUnknownName, "NAME"}}))
        << method;
  }
  // beta's DeleteEnv did nothing: alpha still has the env and can use it.
  EXPECT_THAT(ListAs(kAlpha), ElementsAre(name));
  const auto mine = CallEveryMethod(
      *s_.stub, name, [](grpc::ClientContext* c) { AddToken(kAlpha, c); });
  for (const auto& [method, status] : mine) {
    // ResetEnv runs between StepEnv and StepAgent, so the two step APIs
    // do not meet in one episode and every call succeeds.
    EXPECT_TRUE(status.ok()) << method << ": " << status.error_message();
  }
  EXPECT_THAT(ListAs(kAlpha), Not(::testing::Contains(name)));
}

TEST_F(AuthServerTest, ListEnvsShowsOnlyTheCallersEnvs) {
  const std::string a1 = CreateAs(kAlpha);
  const std::string b1 = CreateAs(kBeta);
  const std::string a2 = CreateAs(kAlpha);
  EXPECT_THAT(ListAs(kAlpha), ElementsAre(a1, a2));
  EXPECT_THAT(ListAs(kBeta), ElementsAre(b1));

  // Paging counts only the caller's envs.
  grpc::ClientContext context;
  AddToken(kAlpha, &context);
  v1::ListEnvsRequest request;
  request.set_page_size(1);
  v1::ListEnvsResponse page;
  ASSERT_TRUE(s_.stub->ListEnvs(&context, request, &page).ok());
  ASSERT_EQ(page.envs_size(), 1);
  EXPECT_EQ(page.envs(0).name(), a1);
  grpc::ClientContext next_context;
  AddToken(kAlpha, &next_context);
  request.set_page_token(page.next_page_token());
  ASSERT_TRUE(s_.stub->ListEnvs(&next_context, request, &page).ok());
  ASSERT_EQ(page.envs_size(), 1);
  EXPECT_EQ(page.envs(0).name(), a2);
}

TEST_F(AuthServerTest, HealthNeedsNoToken) {
  grpc::Status status;
  EXPECT_EQ(HealthCheck(s_.server->InProcessChannel(), &status),
            std::string("\x08\x01", 2));
  EXPECT_TRUE(status.ok()) << status.error_message();
}

TEST_F(AuthServerTest, SessionWithoutTokenEndsUnauthenticated) {
  grpc::ClientContext context;
  AddToken("not-a-token", &context);
  auto stream = s_.stub->Session(&context);
  v1::SessionRequest request;
  request.set_sequence(1);
  *request.mutable_create_env() = CreateRequest(1);
  stream->Write(request);  // May fail: the server may have finished already.
  v1::SessionResponse response;
  EXPECT_FALSE(stream->Read(&response));
  const grpc::Status status = stream->Finish();
  EXPECT_EQ(status.error_code(), grpc::StatusCode::UNAUTHENTICATED);
  EXPECT_THAT(status.error_message(), Not(HasSubstr("not-a-token")));
  EXPECT_EQ(s_.server->service().registry().size(), 0);
}

// One request/response exchange on a Session stream.
v1::SessionResponse Exchange(
    grpc::ClientReaderWriter<v1::SessionRequest, v1::SessionResponse>& stream,
    const v1::SessionRequest& request) {
  EXPECT_TRUE(stream.Write(request));
  v1::SessionResponse response;
  EXPECT_TRUE(stream.Read(&response));
  EXPECT_EQ(response.sequence(), request.sequence());
  return response;
}

TEST_F(AuthServerTest, SessionActsAsItsTokenOnly) {
  const std::string alphas = CreateAs(kAlpha);
  std::string bound;
  {
    grpc::ClientContext context;
    AddToken(kBeta, &context);
    auto stream = s_.stub->Session(&context);
    v1::SessionRequest request;

    // beta's session cannot see, step, render or delete alpha's env.
    request.set_sequence(1);
    request.mutable_get_env()->set_name(alphas);
    EXPECT_EQ(Exchange(*stream, request).error().code(), grpc::NOT_FOUND);
    request.set_sequence(2);
    request.mutable_step_env()->set_name(alphas);
    *request.mutable_step_env()->mutable_actions() = DiscreteActions({0, 0});
    EXPECT_EQ(Exchange(*stream, request).error().code(), grpc::NOT_FOUND);
    request.set_sequence(3);
    request.mutable_step_agent()->set_name(alphas);
    EXPECT_EQ(Exchange(*stream, request).error().code(), grpc::NOT_FOUND);
    request.set_sequence(4);
    request.mutable_render_env()->set_name(alphas);
    request.mutable_render_env()->set_format(v1::FRAME_FORMAT_PNG);
    EXPECT_EQ(Exchange(*stream, request).error().code(), grpc::NOT_FOUND);
    request.set_sequence(5);
    request.mutable_step_batch()->add_steps()->set_name(alphas);
    *request.mutable_step_batch()->mutable_steps(0)->mutable_actions() =
        DiscreteActions({0, 0});
    EXPECT_EQ(Exchange(*stream, request).step_batch().results(0).error().code(),
              grpc::NOT_FOUND);
    request.set_sequence(6);
    request.mutable_reset_env()->set_name(alphas);
    EXPECT_EQ(Exchange(*stream, request).error().code(), grpc::NOT_FOUND);
    request.set_sequence(7);
    request.mutable_delete_env()->set_name(alphas);
    EXPECT_EQ(Exchange(*stream, request).error().code(), grpc::NOT_FOUND);

    // Its own env works and belongs to beta.
    request.set_sequence(8);
    *request.mutable_create_env() = CreateRequest(2);
    bound = Exchange(*stream, request).env().name();
    ASSERT_FALSE(bound.empty());
    request.set_sequence(9);
    request.mutable_reset_env()->set_name(bound);
    EXPECT_FALSE(Exchange(*stream, request).has_error());
    EXPECT_THAT(ListAs(kBeta), ElementsAre(bound));
    EXPECT_THAT(ListAs(kAlpha), ElementsAre(alphas));
    stream->WritesDone();
    EXPECT_TRUE(stream->Finish().ok());
  }
  // The session's env dies with it (just after the stream's status reaches
  // the client); alpha's is untouched.
  const auto deadline =
      std::chrono::steady_clock::now() + std::chrono::seconds(5);
  while (!ListAs(kBeta).empty() &&
         std::chrono::steady_clock::now() < deadline) {
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
  EXPECT_THAT(ListAs(kBeta), IsEmpty());
  EXPECT_THAT(ListAs(kAlpha), ElementsAre(alphas));
}

TEST(AuthOffTest, EveryCallerIsTheAnonymousOwner) {
  InProcess s;
  // A token is ignored by a server without tokens: same owner either way.
  const std::string name = CreateEnv(*s.stub, CreateRequest(2));
  grpc::ClientContext context;
  AddToken(kAlpha, &context);
  v1::GetEnvRequest request;
  request.set_name(name);
  v1::Env env;
  EXPECT_TRUE(s.stub->GetEnv(&context, request, &env).ok());
  EXPECT_EQ(env.name(), name);
}

}  // namespace
}  // namespace mll::service::testing

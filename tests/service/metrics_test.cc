// Prometheus metrics: the exposition text parses (HELP/TYPE lines, label
// syntax, histogram invariants), and a real server's /metrics, scraped over
// loopback HTTP, moves as the traffic sent to it says it must.
#include "mll/service/metrics.h"

#include <sys/resource.h>

#include <chrono>
#include <map>
#include <regex>
#include <set>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "httplib.h"
#include "test_util.h"

namespace mll::service::testing {
namespace {

using ::testing::HasSubstr;

// Samples by their full series name (`name{labels}` as written), asserting
// the text follows the exposition format 0.0.4: every sample belongs to a
// family announced by one HELP and one TYPE line before it, labels are
// `name="value"` lists, values are numbers, and each histogram's buckets are
// cumulative and end with le="+Inf" equal to _count.
std::map<std::string, double> Parse(const std::string& text) {
  static const std::regex kHelp(R"(# HELP ([a-zA-Z_:][a-zA-Z0-9_:]*) .+)");
  static const std::regex kType(
      R"(# TYPE ([a-zA-Z_:][a-zA-Z0-9_:]*) (counter|gauge|histogram))");
  static const std::regex kSample(
      R"(([a-zA-Z_:][a-zA-Z0-9_:]*)(\{[a-zA-Z_][a-zA-Z0-9_]*="[^"\\]*")"
      R"((,[a-zA-Z_][a-zA-Z0-9_]*="[^"\\]*")*\})? ([-+0-9.eE]+|\+Inf))");
  std::map<std::string, double> samples;
  std::set<std::string> helped;
  std::map<std::string, std::string> types;
  EXPECT_TRUE(!text.empty() && text.back() == '\n');
  std::istringstream lines(text);
  for (std::string line; std::getline(lines, line);) {
    std::smatch match;
    if (std::regex_match(line, match, kHelp)) {
      EXPECT_TRUE(helped.insert(match[1]).second) << "second HELP: " << line;
    } else if (std::regex_match(line, match, kType)) {
      EXPECT_TRUE(helped.count(match[1])) << "TYPE before HELP: " << line;
      EXPECT_TRUE(types.emplace(match[1], match[2]).second) << line;
    } else if (std::regex_match(line, match, kSample)) {
      std::string family = match[1];
      for (const char* suffix : {"_bucket", "_sum", "_count"}) {
        const std::string base =
            family.substr(0, family.size() - std::string(suffix).size());
        if (family.size() > std::string(suffix).size() &&
            family.compare(base.size(), std::string::npos, suffix) == 0 &&
            types.count(base) && types[base] == "histogram") {
          family = base;
        }
      }
      EXPECT_TRUE(types.count(family)) << "sample without TYPE: " << line;
      const std::string series = line.substr(0, line.rfind(' '));
      EXPECT_TRUE(samples.emplace(series, std::stod(match[4])).second)
          << "duplicate series: " << line;
    } else {
      ADD_FAILURE() << "not exposition format: \"" << line << "\"";
    }
  }
  // Histogram invariants, per method.
  for (int m = 0; m < kMethodCount; ++m) {
    const std::string label =
        absl::StrCat("method=\"", MethodName(static_cast<Method>(m)), "\"");
    double previous = 0;
    for (int64_t bound : Metrics::kBucketBoundsNs) {
      const std::string series =
          absl::StrCat("mll_rpc_duration_seconds_bucket{", label, ",le=\"",
                       bound * 1e-9, "\"}");
      EXPECT_TRUE(samples.count(series)) << series;
      EXPECT_GE(samples[series], previous) << series;
      previous = samples[series];
    }
    const double inf = samples[absl::StrCat("mll_rpc_duration_seconds_bucket{",
                                            label, ",le=\"+Inf\"}")];
    EXPECT_GE(inf, previous);
    EXPECT_EQ(
        inf,
        samples[absl::StrCat("mll_rpc_duration_seconds_count{", label, "}")]);
  }
  return samples;
}

std::string Series(const std::string& family, const std::string& method) {
  return absl::StrCat(family, "{method=\"", method, "\"}");
}

TEST(MetricsTest, RecordsLandInTheirSeries) {
  Metrics metrics;
  metrics.RecordCall(Method::kGetEnv, absl::StatusCode::kOk, 10'000);
  metrics.RecordCall(Method::kGetEnv, absl::StatusCode::kNotFound, 30'000);
  metrics.RecordCall(Method::kGetEnv, absl::StatusCode::kNotFound, 2e9);
  v1::StepData data;
  data.mutable_stepped()->set_data(std::string("\x01\x00\x01", 3));
  metrics.RecordStepData(Method::kStepBatch, data);
  data.set_auto_reset(true);
  metrics.RecordStepData(Method::kStepBatch, data);  // An episode, no step.
  metrics.RecordStepAgent(Method::kStepAgent, /*acted=*/true);
  metrics.RecordStepAgent(Method::kStepAgent, /*acted=*/false);
  metrics.RecordReset();

  std::map<std::string, double> s = Parse(metrics.Render(7));
  EXPECT_EQ(s["mll_envs_live"], 7);
  EXPECT_EQ(s["mll_episodes_started_total"], 2);
  EXPECT_EQ(s[Series("mll_steps_total", "StepBatch")], 1);
  EXPECT_EQ(s[Series("mll_agent_steps_total", "StepBatch")], 2);
  EXPECT_EQ(s[Series("mll_steps_total", "StepAgent")], 2);
  EXPECT_EQ(s[Series("mll_agent_steps_total", "StepAgent")], 1);
  const std::string get = "method=\"GetEnv\"";
  EXPECT_EQ(s["mll_rpc_duration_seconds_bucket{" + get + ",le=\"2.5e-05\"}"],
            1);
  EXPECT_EQ(s["mll_rpc_duration_seconds_bucket{" + get + ",le=\"5e-05\"}"], 2);
  EXPECT_EQ(s["mll_rpc_duration_seconds_bucket{" + get + ",le=\"1\"}"], 2);
  EXPECT_EQ(s["mll_rpc_duration_seconds_bucket{" + get + ",le=\"+Inf\"}"], 3);
  EXPECT_DOUBLE_EQ(s["mll_rpc_duration_seconds_sum{" + get + "}"], 2.00004);
  EXPECT_EQ(s["mll_rpc_errors_total{" + get + ",code=\"NOT_FOUND\"}"], 2);
  EXPECT_GT(s["process_resident_memory_bytes"], 1 << 20);
}

// process_cpu_seconds_total is the process's CPU (every thread's), so that an
// operator can divide its rate by mll_agent_steps_total's: it grows by the
// CPU burnt between two renders, and agrees with getrusage.
TEST(MetricsTest, ProcessCpuSecondsFollowGetrusage) {
  const auto cpu_now = [] {
    rusage usage = {};
    getrusage(RUSAGE_SELF, &usage);
    return usage.ru_utime.tv_sec + usage.ru_stime.tv_sec +
           (usage.ru_utime.tv_usec + usage.ru_stime.tv_usec) * 1e-6;
  };
  Metrics metrics;
  const double before_rusage = cpu_now();
  std::map<std::string, double> before = Parse(metrics.Render(0));
  // Burns about 50 ms of CPU on a second thread.
  std::thread([&cpu_now, start = cpu_now()] {
    volatile uint64_t sink = 0;
    while (cpu_now() - start < 0.05) {
      for (int i = 0; i < 100000; ++i) sink = sink + i;
    }
  }).join();
  std::map<std::string, double> after = Parse(metrics.Render(0));
  const double after_rusage = cpu_now();
  EXPECT_GE(before["process_cpu_seconds_total"], before_rusage - 1e-6);
  EXPECT_LE(after["process_cpu_seconds_total"], after_rusage + 1e-6);
  EXPECT_GE(
      after["process_cpu_seconds_total"] - before["process_cpu_seconds_total"],
      0.05);
  EXPECT_GT(after["mll_process_context_switches_total{kind=\"voluntary\"}"], 0);
  EXPECT_EQ(
      after.count("mll_process_context_switches_total{kind=\"involuntary\"}"),
      1);
}

// A packed StepBatch counts each env row as a StepData would, except rows of
// failed envs (zero, listed in `errors`).
TEST(MetricsTest, PackedBatchRowsCountAsSteps) {
  Metrics metrics;
  v1::StepBatchResponse response;
  v1::PackedStepData* packed = response.mutable_packed();
  // 4 envs x 2 landers: env 0 stepped both, env 1 failed, env 2 auto-reset,
  // env 3 stepped one.
  packed->mutable_stepped()->set_data(
      std::string("\x01\x01\x00\x00\x01\x01\x01\x00", 8));
  packed->mutable_auto_reset()->set_data(std::string("\x00\x00\x01\x00", 4));
  packed->add_errors()->set_index(1);
  metrics.RecordStepBatch(Method::kStepBatch, response);
  std::map<std::string, double> s = Parse(metrics.Render(0));
  EXPECT_EQ(s[Series("mll_steps_total", "StepBatch")], 2);
  EXPECT_EQ(s[Series("mll_agent_steps_total", "StepBatch")], 3);
  EXPECT_EQ(s["mll_episodes_started_total"], 1);
}

// A server with a metrics endpoint on a free loopback port; calls go
// through an in-process channel.
class MetricsServerTest : public ::testing::Test {
 protected:
  MetricsServerTest() : s_(Options()) {}

  static ServerOptions Options() {
    ServerOptions options;
    options.metrics_address = "127.0.0.1:0";
    options.service.threads = 2;
    return options;
  }

  httplib::Result Get(const std::string& path) {
    httplib::Client http("127.0.0.1", s_.server->metrics_port());
    http.set_connection_timeout(5);
    http.set_read_timeout(5);
    return http.Get(path.c_str());
  }

  std::map<std::string, double> Scrape() {
    httplib::Result result = Get("/metrics");
    EXPECT_TRUE(result) << httplib::to_string(result.error());
    if (!result) return {};
    EXPECT_EQ(result->status, 200);
    EXPECT_THAT(result->get_header_value("Content-Type"),
                HasSubstr("text/plain; version=0.0.4"));
    return Parse(result->body);
  }

  void Reset(const std::string& name) {
    grpc::ClientContext context;
    v1::ResetEnvRequest request;
    request.set_name(name);
    request.set_seed(1);
    v1::ResetEnvResponse response;
    ASSERT_TRUE(s_.stub->ResetEnv(&context, request, &response).ok());
  }

  InProcess s_;
};

TEST_F(MetricsServerTest, ScrapeFollowsTheTraffic) {
  ASSERT_GT(s_.server->metrics_port(), 0);
  std::map<std::string, double> before = Scrape();
  EXPECT_EQ(before["mll_envs_live"], 0);
  EXPECT_EQ(before[Series("mll_rpc_duration_seconds_count", "StepEnv")], 0);

  const std::string two = CreateEnv(*s_.stub, CreateRequest(2));
  const std::string three = CreateEnv(*s_.stub, CreateRequest(3));
  Reset(two);
  Reset(three);
  constexpr int kSteps = 5;
  for (int i = 0; i < kSteps; ++i) {
    grpc::ClientContext context;
    v1::StepEnvRequest request;
    request.set_name(two);
    *request.mutable_actions() = DiscreteActions({0, 0});
    v1::StepEnvResponse response;
    ASSERT_TRUE(s_.stub->StepEnv(&context, request, &response).ok());
  }
  constexpr int kBatches = 3;
  for (int i = 0; i < kBatches; ++i) {
    grpc::ClientContext context;
    v1::StepBatchRequest request;
    request.add_steps()->set_name(three);
    *request.mutable_steps(0)->mutable_actions() = DiscreteActions({0, 0, 0});
    request.add_steps()->set_name("envs/unknown");  // An item error only.
    v1::StepBatchResponse response;
    ASSERT_TRUE(s_.stub->StepBatch(&context, request, &response).ok());
  }
  {
    grpc::ClientContext context;
    v1::GetEnvRequest request;
    request.set_name("envs/unknown");
    v1::Env env;
    EXPECT_EQ(s_.stub->GetEnv(&context, request, &env).error_code(),
              grpc::StatusCode::NOT_FOUND);
  }
  {
    // A session: a reset, two parallel steps, and one bad request.
    grpc::ClientContext context;
    auto stream = s_.stub->Session(&context);
    v1::SessionRequest request;
    v1::SessionResponse response;
    request.set_sequence(1);
    request.mutable_reset_env()->set_name(two);
    ASSERT_TRUE(stream->Write(request) && stream->Read(&response));
    for (int i = 2; i <= 3; ++i) {
      request.set_sequence(i);
      request.mutable_step_env()->set_name(two);
      *request.mutable_step_env()->mutable_actions() = DiscreteActions({2, 2});
      ASSERT_TRUE(stream->Write(request) && stream->Read(&response));
      ASSERT_FALSE(response.has_error()) << response.error().message();
    }
    request.set_sequence(4);
    request.mutable_step_env()->set_name(two);
    request.mutable_step_env()->clear_actions();
    ASSERT_TRUE(stream->Write(request) && stream->Read(&response));
    EXPECT_EQ(response.error().code(), grpc::StatusCode::INVALID_ARGUMENT);
    stream->WritesDone();
    ASSERT_TRUE(stream->Finish().ok());
  }

  std::map<std::string, double> after = Scrape();
  EXPECT_EQ(after["mll_envs_live"], 2);
  EXPECT_EQ(after["mll_episodes_started_total"], 3);
  EXPECT_EQ(after[Series("mll_steps_total", "StepEnv")], kSteps);
  EXPECT_EQ(after[Series("mll_agent_steps_total", "StepEnv")], kSteps * 2);
  EXPECT_EQ(after[Series("mll_steps_total", "StepBatch")], kBatches);
  EXPECT_EQ(after[Series("mll_agent_steps_total", "StepBatch")], kBatches * 3);
  EXPECT_EQ(after[Series("mll_steps_total", "Session")], 2);
  EXPECT_EQ(after[Series("mll_agent_steps_total", "Session")], 4);
  EXPECT_EQ(after[Series("mll_steps_total", "StepAgent")], 0);
  EXPECT_EQ(after[Series("mll_rpc_duration_seconds_count", "CreateEnv")], 2);
  EXPECT_EQ(after[Series("mll_rpc_duration_seconds_count", "StepEnv")], kSteps);
  EXPECT_EQ(after[Series("mll_rpc_duration_seconds_count", "StepBatch")],
            kBatches);
  EXPECT_EQ(after[Series("mll_rpc_duration_seconds_count", "Session")], 4);
  EXPECT_GT(after[Series("mll_rpc_duration_seconds_sum", "StepEnv")], 0);
  EXPECT_EQ(after["mll_rpc_errors_total{method=\"GetEnv\",code=\"NOT_FOUND\"}"],
            1);
  EXPECT_EQ(after["mll_rpc_errors_total{method=\"Session\","
                  "code=\"INVALID_ARGUMENT\"}"],
            1);
  // Batch items' errors are inside an OK call: not a StepBatch error.
  EXPECT_EQ(after.count("mll_rpc_errors_total{method=\"StepBatch\","
                        "code=\"NOT_FOUND\"}"),
            0);
  EXPECT_GT(after["process_resident_memory_bytes"], 1 << 20);
  EXPECT_GT(after["process_cpu_seconds_total"], 0);

  grpc::ClientContext context;
  v1::DeleteEnvRequest remove;
  remove.set_name(three);
  v1::DeleteEnvResponse removed;
  ASSERT_TRUE(s_.stub->DeleteEnv(&context, remove, &removed).ok());
  EXPECT_EQ(Scrape()["mll_envs_live"], 1);
}

TEST_F(MetricsServerTest, OnlyMetricsIsServed) {
  httplib::Result other = Get("/");
  ASSERT_TRUE(other);
  EXPECT_EQ(other->status, 404);
}

TEST(MetricsAddressTest, BadOrBusyAddressIsAnErrorNamingTheFlag) {
  ExpectListenerRefusesBadAndBusyAddresses("--metrics_address",
                                           &ServerOptions::metrics_address,
                                           &Server::metrics_port);
}

}  // namespace
}  // namespace mll::service::testing

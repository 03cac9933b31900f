// mll_cli: the Multi Lunar Lander server from the command line, through the
// C++ client library. Output is JSON, one object per line.
//
//   mll_cli health
//   mll_cli info
//   mll_cli list
//   mll_cli create --n_landers=5 --continuous --render_mode=rgb_array
//   mll_cli get envs/ID
//   mll_cli reset envs/ID --seed=7
//   mll_cli step envs/ID --actions=2,0,3
//   mll_cli render envs/ID --out=frame.png
//   mll_cli delete envs/ID
//   mll_cli play --policy=heuristic --episodes=3 --n_landers=4 [--name=envs/ID]
//   mll_cli play --address=HOST1:PORT,HOST2:PORT --envs=4
//   mll_cli play --policy=trained --max_cycles=2000 --terminate_on_damage=false
//                [--weights=FILE.qnet]
//
// Every command takes --address (default 127.0.0.1:50051), a comma-separated
// list for several servers: `list` lists all of them, `play` spreads its envs
// over them round-robin and steps them with one StepBatch per server, `create`
// uses --server (default the first), and commands naming an env find it on
// whichever server has it. Security:
//   --tls                  TLS with gRPC's default root certificates;
//   --tls_root_cert=PATH   TLS trusting the PEM certificates in PATH (for a
//                          self-signed server certificate, the certificate);
//   --tls_server_name=NAME check the server's certificate for NAME;
//   --token=T | --token_file=PATH | environment variable MLL_TOKEN
//                          bearer token sent with every call. Precedence:
//                          --token, then --token_file (giving both is an
//                          error), then MLL_TOKEN; none sends no token.
// Exit codes: 0 done, 1 the server or the transport failed (its code and
// message are printed), 2 bad command line.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <future>
#include <iostream>
#include <iterator>
#include <map>
#include <memory>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/status/status.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "absl/strings/strip.h"
#include "config_flags.h"
#include "core_bridge.h"
#include "grpc/support/log.h"
#include "mll/client.h"
#include "mll/vector_env.h"
#include "program_usage.h"
#include "trained_pilot.h"

ABSL_FLAG(std::string, address, "127.0.0.1:50051",
          "Server address host:port, or a comma-separated list of servers; "
          "a host name stands for every address it resolves to (e.g. a "
          "Kubernetes headless Service), each one server.");
ABSL_FLAG(std::string, token, "",
          "Bearer token sent with every call (beats --token_file's and "
          "MLL_TOKEN's).");
ABSL_FLAG(std::string, token_file, "",
          "File holding the bearer token: its one line that is not blank and "
          "does not start with '#' (beats MLL_TOKEN).");
ABSL_FLAG(bool, tls, false, "TLS with gRPC's default root certificates.");
ABSL_FLAG(std::string, tls_root_cert, "",
          "TLS trusting the PEM root certificates in this file.");
ABSL_FLAG(std::string, tls_server_name, "",
          "TLS: check the server's certificate for this name instead of the "
          "address's host.");
ABSL_FLAG(int, server, -1,
          "create: index of the server in --address's list (default: the "
          "first).");
ABSL_FLAG(int, envs, 0,
          "play: number of envs flown together, spread over the servers "
          "(default: one per server). bench: envs per client (default 64).");
ABSL_FLAG(std::string, transport, "auto",
          "play, bench: how the batched steps travel: auto (shared memory "
          "with a server on this host, else the gRPC stream), shared_memory "
          "(or fail saying why not) or native (the gRPC stream).");
ABSL_FLAG(double, seconds, 5.0,
          "bench: how long to step, in seconds (0, 3600].");
ABSL_FLAG(int, batch_size, 0,
          "bench: 0 steps every env per call (Step); K in 1..--envs uses "
          "EnvPool's async API instead: Recv the first K envs done, Send "
          "their actions, with every other env's step in flight.");
ABSL_FLAG(int, clients, 1,
          "bench: independent clients (threads), each with its own --envs "
          "envs and Session streams, 1..256.");
ABSL_FLAG(int, timeout_ms, 30000,
          "Deadline of each unary call in ms; 0: --step_timeout_s's.");
ABSL_FLAG(double, step_timeout_s, 5.0,
          "How long a server may take to answer a request of the play and "
          "bench Session streams (plus 1 ms per lander action of a batch) "
          "before it counts as stalled: DEADLINE_EXCEEDED naming it, or "
          "failover with several servers; 0 for none.");
ABSL_FLAG(double, rediscover_interval_s, 10.0,
          "play and bench: how often the host names of --address are "
          "resolved again, so that envs move onto servers that joined them "
          "(and none go to servers gone from them); 0: never.");
ABSL_FLAG(std::string, name, "",
          "Environment name envs/ID (or give it as the argument after the "
          "command). For play: fly this env instead of creating one.");
ABSL_FLAG(std::string, seed, "",
          "reset: reseed with this unsigned integer (empty continues the "
          "stream). play: episode k of env j (of N) is reset with seed + k*N "
          "+ j (default seed 0); seed + j also seeds env j's random policy.");
ABSL_FLAG(std::string, actions, "",
          "step: comma-separated actions, one per lander (discrete) or two per "
          "lander [main, lateral] (continuous).");
ABSL_FLAG(std::string, out, "frame.png", "render: output file.");
ABSL_FLAG(std::string, format, "png", "render: png or rgb (raw bytes).");
ABSL_FLAG(std::string, policy, "heuristic",
          "play: heuristic, random, or trained (the DQN network of --weights, "
          "discrete actions; docs/dqn.md).");
ABSL_FLAG(std::string, weights, "",
          "play --policy=trained: a .qnet file; empty: the network shipped "
          "with mll_cli (examples/dqn/trained.qnet, built in).");
ABSL_FLAG(int, episodes, 1, "play: number of episodes, >= 1.");
ABSL_FLAG(bool, auto_reset, false,
          "create: the step after an episode ends starts a new one.");

namespace mll::client {
namespace {

constexpr int kExitServerError = 1;
constexpr int kExitUsage = 2;

// A failure and the exit code it maps to.
struct Failure {
  absl::Status status;
  int exit_code;
};
Failure Usage(absl::Status status) { return {std::move(status), kExitUsage}; }
Failure Server(absl::Status status) {
  return {std::move(status), kExitServerError};
}
using Result = std::optional<Failure>;

// Shortest text that reads back as the same float; JSON has no NaN or inf.
std::string JsonNumber(double value) {
  if (!std::isfinite(value)) return "null";
  return absl::StrFormat("%.9g", value);
}

// {"lander_0": value(0), ...} for agents 0..n-1.
template <typename ValueFn>
std::string PerAgent(int n, ValueFn value) {
  std::vector<std::string> members;
  for (int agent = 0; agent < n; ++agent) {
    members.push_back(absl::StrCat("\"lander_", agent, "\":", value(agent)));
  }
  return absl::StrCat("{", absl::StrJoin(members, ","), "}");
}

std::string Quoted(absl::string_view text) {
  return absl::StrCat("\"", text, "\"");
}

std::string StepDataJson(const StepData& data) {
  const int n = data.n_landers;
  std::string json = absl::StrCat(
      "{\"observations\":",
      PerAgent(n,
               [&](int a) {
                 std::vector<std::string> values;
                 for (float v : data.observation(a))
                   values.push_back(JsonNumber(v));
                 return absl::StrCat("[", absl::StrJoin(values, ","), "]");
               }),
      ",\"rewards\":",
      PerAgent(n, [&](int a) { return JsonNumber(data.rewards[a]); }),
      ",\"terminations\":",
      PerAgent(n,
               [&](int a) { return data.terminations[a] ? "true" : "false"; }),
      ",\"truncations\":",
      PerAgent(n,
               [&](int a) { return data.truncations[a] ? "true" : "false"; }),
      ",\"outcomes\":",
      PerAgent(
          n,
          [&](int a) { return Quoted(LanderOutcomeName(data.outcomes[a])); }),
      ",\"episode_over\":", data.episode_over ? "true" : "false",
      ",\"cycles\":", data.cycles);
  if (data.seed.has_value()) absl::StrAppend(&json, ",\"seed\":", *data.seed);
  absl::StrAppend(&json, "}");
  return json;
}

absl::StatusOr<std::string> EnvName(const std::vector<std::string>& args) {
  const std::string flag = absl::GetFlag(FLAGS_name);
  if (!args.empty()) return args[0];
  if (!flag.empty()) return flag;
  return absl::InvalidArgumentError(
      "this command needs an environment name: mll_cli <command> envs/ID");
}

absl::StatusOr<std::optional<uint64_t>> SeedFlag() {
  const std::string text = absl::GetFlag(FLAGS_seed);
  if (text.empty()) return std::optional<uint64_t>();
  uint64_t seed = 0;
  if (!absl::SimpleAtoi(text, &seed)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "seed is \"", text, "\"; expected an unsigned 64-bit integer"));
  }
  return std::optional<uint64_t>(seed);
}

absl::StatusOr<std::string> ReadFile(const std::string& path,
                                     absl::string_view flag) {
  std::ifstream file(path, std::ios::binary);
  if (!file) {
    return absl::InvalidArgumentError(
        absl::StrCat(flag, " is \"", path, "\", which cannot be read"));
  }
  return std::string(std::istreambuf_iterator<char>(file), {});
}

// The token from --token, --token_file or MLL_TOKEN, in that order; the
// messages never repeat a token.
absl::StatusOr<std::string> Token() {
  const std::string flag = absl::GetFlag(FLAGS_token);
  const std::string path = absl::GetFlag(FLAGS_token_file);
  if (!flag.empty() && !path.empty()) {
    return absl::InvalidArgumentError(
        "token and token_file are both set; give one");
  }
  if (!flag.empty()) return flag;
  if (path.empty()) {
    const char* environment = std::getenv("MLL_TOKEN");
    return std::string(environment != nullptr ? environment : "");
  }
  absl::StatusOr<std::string> text = ReadFile(path, "token_file");
  if (!text.ok()) return text.status();
  std::vector<std::string> tokens;
  for (absl::string_view line : absl::StrSplit(*text, '\n')) {
    line = absl::StripAsciiWhitespace(line);
    if (!line.empty() && line[0] != '#') tokens.emplace_back(line);
  }
  if (tokens.size() != 1) {
    return absl::InvalidArgumentError(absl::StrCat(
        "token_file \"", path, "\" has ", tokens.size(),
        " tokens; expected exactly one line that is not blank or a comment"));
  }
  return tokens[0];
}

absl::StatusOr<ClientOptions> OptionsFromFlags() {
  ClientOptions options;
  const int timeout_ms = absl::GetFlag(FLAGS_timeout_ms);
  if (timeout_ms < 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("timeout_ms is ", timeout_ms, "; must be >= 0"));
  }
  options.call_timeout = std::chrono::milliseconds(timeout_ms);
  const double step_timeout_s = absl::GetFlag(FLAGS_step_timeout_s);
  if (!(step_timeout_s >= 0 && step_timeout_s <= 86400)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "step_timeout_s is ", step_timeout_s, "; must be in [0, 86400]"));
  }
  // At least 1 ms when set: 0 would mean none.
  options.step_timeout = std::chrono::milliseconds(std::max<int64_t>(
      step_timeout_s > 0, std::llround(step_timeout_s * 1000)));
  const double rediscover_s = absl::GetFlag(FLAGS_rediscover_interval_s);
  if (!(rediscover_s >= 0 && rediscover_s <= 86400)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "rediscover_interval_s is ", rediscover_s, "; must be in [0, 86400]"));
  }
  // At least 1 ms when set: 0 would mean never.
  options.rediscover_interval = std::chrono::milliseconds(
      std::max<int64_t>(rediscover_s > 0, std::llround(rediscover_s * 1000)));
  absl::StatusOr<std::string> token = Token();
  if (!token.ok()) return token.status();
  options.token = *std::move(token);
  const std::string root_path = absl::GetFlag(FLAGS_tls_root_cert);
  if (!root_path.empty()) {
    absl::StatusOr<std::string> roots = ReadFile(root_path, "tls_root_cert");
    if (!roots.ok()) return roots.status();
    options.tls_root_certificates = *std::move(roots);
  }
  options.tls_target_name_override = absl::GetFlag(FLAGS_tls_server_name);
  options.use_tls = absl::GetFlag(FLAGS_tls) || !root_path.empty() ||
                    !options.tls_target_name_override.empty();
  const std::string transport = absl::GetFlag(FLAGS_transport);
  bool known = false;
  for (SessionTransport choice :
       {SessionTransport::kAuto, SessionTransport::kSharedMemory,
        SessionTransport::kNative}) {
    if (transport == SessionTransportName(choice)) {
      options.session_transport = choice;
      known = true;
    }
  }
  if (!known) {
    return absl::InvalidArgumentError(
        absl::StrCat("transport is \"", transport,
                     "\"; allowed: \"auto\", \"shared_memory\", \"native\""));
  }
  return options;
}

absl::Status WriteFile(const std::string& path, const std::string& bytes) {
  std::ofstream file(path, std::ios::binary);
  file.write(bytes.data(), static_cast<std::streamsize>(bytes.size()));
  file.close();
  if (!file) {
    return absl::UnavailableError(
        absl::StrCat("cannot write --out file \"", path, "\""));
  }
  return absl::OkStatus();
}

// ------------------------------------------------------------------ commands

Result Health(const Client& client, const std::vector<std::string>&) {
  absl::Status status = client.CheckHealth();
  if (!status.ok()) return Server(status);
  std::cout << "{\"status\":\"SERVING\"}" << std::endl;
  return std::nullopt;
}

// One JSON line per server: its address and GetServerInfo's answer (a
// release without GetServerInfo shows as protocol 1.0), in address order.
Result Info(const Client& client, const std::vector<std::string>&) {
  for (int server = 0; server < client.server_count(); ++server) {
    absl::StatusOr<ServerInfo> info = client.GetServerInfo(server);
    if (!info.ok()) return Server(info.status());
    absl::string_view fields = info->json;
    absl::ConsumePrefix(&fields, "{");
    std::cout << "{\"address\":" << Quoted(client.address(server))
              << (fields == "}" ? "" : ",") << fields << std::endl;
  }
  return std::nullopt;
}

Result List(const Client& client, const std::vector<std::string>&) {
  absl::StatusOr<std::vector<EnvInfo>> envs = client.ListEnvs();
  if (!envs.ok()) return Server(envs.status());
  if (envs->empty()) {
    // On stderr: stdout stays one JSON object per environment.
    std::cerr << "mll_cli list: no environments on "
              << absl::GetFlag(FLAGS_address) << std::endl;
  }
  for (const EnvInfo& env : *envs) std::cout << env.json << "\n";
  std::cout << std::flush;
  return std::nullopt;
}

Result Create(const Client& client, const std::vector<std::string>&) {
  absl::StatusOr<core::EnvConfig> config = core::EnvConfigFromFlags();
  if (!config.ok()) return Usage(config.status());
  RemoteEnvConfig remote = RemoteConfigFrom(*config);
  remote.auto_reset = absl::GetFlag(FLAGS_auto_reset);
  const int server = absl::GetFlag(FLAGS_server);
  if (server < -1 || server >= client.server_count()) {
    return Usage(absl::InvalidArgumentError(absl::StrCat(
        "server is ", server, "; allowed: -1 (the first) or 0..",
        client.server_count() - 1, " (an index into --address's list)")));
  }
  absl::StatusOr<RemoteEnv> env =
      client.CreateEnvOn(server < 0 ? 0 : server, remote);
  if (!env.ok()) return Server(env.status());
  // The env outlives this process: the caller refers to it by name.
  env->Release();
  std::cout << env->info().json << std::endl;
  return std::nullopt;
}

Result Get(const Client& client, const std::vector<std::string>& args) {
  absl::StatusOr<std::string> name = EnvName(args);
  if (!name.ok()) return Usage(name.status());
  absl::StatusOr<EnvInfo> info = client.GetEnv(*name);
  if (!info.ok()) return Server(info.status());
  std::cout << info->json << std::endl;
  return std::nullopt;
}

Result Delete(const Client& client, const std::vector<std::string>& args) {
  absl::StatusOr<std::string> name = EnvName(args);
  if (!name.ok()) return Usage(name.status());
  absl::Status status = client.DeleteEnv(*name);
  if (!status.ok()) return Server(status);
  std::cout << "{\"deleted\":" << Quoted(*name) << "}" << std::endl;
  return std::nullopt;
}

Result Reset(const Client& client, const std::vector<std::string>& args) {
  absl::StatusOr<std::string> name = EnvName(args);
  if (!name.ok()) return Usage(name.status());
  absl::StatusOr<std::optional<uint64_t>> seed = SeedFlag();
  if (!seed.ok()) return Usage(seed.status());
  absl::StatusOr<RemoteEnv> env = client.Attach(*name);
  if (!env.ok()) return Server(env.status());
  absl::StatusOr<StepData> data = env->Reset(*seed);
  if (!data.ok()) return Server(data.status());
  std::cout << StepDataJson(*data) << std::endl;
  return std::nullopt;
}

Result Step(const Client& client, const std::vector<std::string>& args) {
  absl::StatusOr<std::string> name = EnvName(args);
  if (!name.ok()) return Usage(name.status());
  absl::StatusOr<RemoteEnv> env = client.Attach(*name);
  if (!env.ok()) return Server(env.status());
  const std::string text = absl::GetFlag(FLAGS_actions);
  std::vector<int32_t> discrete;
  std::vector<float> continuous;
  for (absl::string_view item : absl::StrSplit(text, ',', absl::SkipEmpty())) {
    int32_t integer = 0;
    float real = 0.0f;
    const bool parsed = env->continuous() ? absl::SimpleAtof(item, &real)
                                          : absl::SimpleAtoi(item, &integer);
    if (!parsed) {
      return Usage(absl::InvalidArgumentError(
          absl::StrCat("actions has \"", item, "\"; expected ",
                       env->continuous() ? "numbers" : "integers 0..3",
                       " separated by commas")));
    }
    discrete.push_back(integer);
    continuous.push_back(real);
  }
  if (discrete.empty()) {
    return Usage(absl::InvalidArgumentError(
        "step needs --actions, e.g. --actions=2,0,3 (one per lander)"));
  }
  absl::StatusOr<StepData> data =
      env->Step(env->continuous() ? Actions::Continuous(continuous)
                                  : Actions::Discrete(discrete));
  if (!data.ok()) return Server(data.status());
  std::cout << StepDataJson(*data) << std::endl;
  return std::nullopt;
}

Result Render(const Client& client, const std::vector<std::string>& args) {
  absl::StatusOr<std::string> name = EnvName(args);
  if (!name.ok()) return Usage(name.status());
  const std::string format_name = absl::GetFlag(FLAGS_format);
  if (format_name != "png" && format_name != "rgb") {
    return Usage(absl::InvalidArgumentError(absl::StrCat(
        "format is \"", format_name, "\"; allowed: \"png\", \"rgb\"")));
  }
  absl::StatusOr<RemoteEnv> env = client.Attach(*name);
  if (!env.ok()) return Server(env.status());
  absl::StatusOr<RenderedFrame> frame =
      env->Render(format_name == "png" ? FrameFormat::kPng : FrameFormat::kRgb);
  if (!frame.ok()) return Server(frame.status());
  const std::string out = absl::GetFlag(FLAGS_out);
  absl::Status written = WriteFile(out, frame->data);
  if (!written.ok()) return Server(written);
  std::cout << absl::StrCat("{\"out\":", Quoted(out),
                            ",\"width\":", frame->width,
                            ",\"height\":", frame->height,
                            ",\"format\":", Quoted(format_name),
                            ",\"bytes\":", frame->data.size(), "}")
            << std::endl;
  return std::nullopt;
}

// What play's flags ask for.
struct PlayFlags {
  PilotPolicy policy;
  // --policy=trained: the network every env's pilot flies (else null).
  std::shared_ptr<const QNetwork> trained;
  int episodes;
  uint64_t base_seed;
  // An existing env to fly (--name), or empty to create n_envs.
  std::string name;
  int n_envs;
};

// --weights' network, which must read observations and choose discrete
// actions.
absl::StatusOr<std::shared_ptr<const QNetwork>> LoadPlayNetwork() {
  const std::string path = absl::GetFlag(FLAGS_weights);
  absl::StatusOr<QNetwork> network =
      path.empty() ? QNetwork::Shipped() : QNetwork::Load(path);
  if (!network.ok()) return network.status();
  const std::vector<int>& sizes = network->sizes();
  if (sizes.front() != core::kObservationSize ||
      sizes.back() != core::kDiscreteActionCount) {
    return absl::InvalidArgumentError(absl::StrCat(
        "weights: \"", path, "\" has layer sizes [", absl::StrJoin(sizes, ", "),
        "]; play needs ", core::kObservationSize, " inputs and ",
        core::kDiscreteActionCount, " outputs"));
  }
  return std::make_shared<const QNetwork>(*std::move(network));
}

absl::StatusOr<PlayFlags> ParsePlayFlags(const Client& client) {
  std::shared_ptr<const QNetwork> trained;
  if (absl::GetFlag(FLAGS_policy) == "trained") {
    absl::StatusOr<std::shared_ptr<const QNetwork>> network = LoadPlayNetwork();
    if (!network.ok()) return network.status();
    trained = *std::move(network);
  }
  absl::StatusOr<PilotPolicy> policy =
      trained ? PilotPolicy::kHeuristic
              : ParsePilotPolicy(absl::GetFlag(FLAGS_policy));
  if (!policy.ok()) return policy.status();
  const int episodes = absl::GetFlag(FLAGS_episodes);
  if (episodes < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("episodes is ", episodes, "; must be >= 1"));
  }
  absl::StatusOr<std::optional<uint64_t>> seed_flag = SeedFlag();
  if (!seed_flag.ok()) return seed_flag.status();
  const std::string name = absl::GetFlag(FLAGS_name);
  const int envs_flag = absl::GetFlag(FLAGS_envs);
  // Bounded so that a typo cannot ask the servers for millions of envs.
  constexpr int kMaxPlayEnvs = 1024;
  if (envs_flag < 0 || envs_flag > kMaxPlayEnvs ||
      (!name.empty() && envs_flag > 1)) {
    return absl::InvalidArgumentError(absl::StrCat(
        "envs is ", envs_flag, "; allowed: 0 (one per server) or 1..",
        kMaxPlayEnvs, ", and only 0 or 1 with --name"));
  }
  return PlayFlags{
      *policy,
      std::move(trained),
      episodes,
      seed_flag->value_or(0),
      name,
      !name.empty() ? 1 : (envs_flag > 0 ? envs_flag : client.server_count())};
}

// The envs play flies, as one VectorEnv: the one named, or n_envs new ones
// over the servers (env j on server j mod S; they go with the VectorEnv).
absl::StatusOr<VectorEnv> OpenPlayEnvs(const Client& client,
                                       const PlayFlags& flags,
                                       bool* usage_error) {
  if (!flags.name.empty()) return VectorEnv::Attach(client, {flags.name});
  absl::StatusOr<core::EnvConfig> config = core::EnvConfigFromFlags();
  if (!config.ok()) {
    *usage_error = true;
    return config.status();
  }
  return VectorEnv::Create(client, flags.n_envs, RemoteConfigFrom(*config));
}

// One episode of every env: resets env j with seeds[j], then steps every env
// (one packed StepBatch per server) until all episodes are over (they are
// bounded by max_cycles). An env whose episode ended before the others' is
// auto-reset by its next step and flies on with zero actions, outside the
// report; its pilot is not asked. Leaves each env's last result of the
// episode and its step count.
Result FlyEpisode(VectorEnv& envs, std::vector<PlayPilot>& pilots,
                  absl::Span<const uint64_t> seeds, std::vector<StepData>* last,
                  std::vector<int>* steps) {
  const int n_envs = envs.num_envs();
  const int n = envs.n_landers();
  const int per_env = envs.continuous() ? 2 * n : n;
  if (absl::Status status = envs.Reset(seeds); !status.ok()) {
    return Server(status);
  }
  last->assign(n_envs, StepData());
  steps->assign(n_envs, 0);
  std::vector<bool> flying(n_envs);
  int n_flying = 0;
  for (int j = 0; j < n_envs; ++j) {
    (*last)[j] = envs.Result(j);
    flying[j] = !(*last)[j].episode_over;
    n_flying += flying[j];
  }
  std::vector<int32_t> discrete(envs.continuous() ? 0 : n_envs * per_env);
  std::vector<float> continuous(envs.continuous() ? n_envs * per_env : 0);
  while (n_flying > 0) {
    std::fill(discrete.begin(), discrete.end(), 0);
    std::fill(continuous.begin(), continuous.end(), 0.0f);
    for (int j = 0; j < n_envs; ++j) {
      if (!flying[j]) continue;
      const Actions actions = pilots[j].Act((*last)[j]);
      if (envs.continuous()) {
        std::copy(actions.continuous.begin(), actions.continuous.end(),
                  continuous.begin() + j * per_env);
      } else {
        std::copy(actions.discrete.begin(), actions.discrete.end(),
                  discrete.begin() + j * per_env);
      }
    }
    absl::Status status = envs.continuous()
                              ? envs.Step(absl::MakeConstSpan(continuous))
                              : envs.Step(absl::MakeConstSpan(discrete));
    if (!status.ok()) return Server(status);
    for (int j = 0; j < n_envs; ++j) {
      if (!flying[j]) continue;
      (*last)[j] = envs.Result(j);
      ++(*steps)[j];
      if ((*last)[j].episode_over) {
        flying[j] = false;
        --n_flying;
      }
    }
  }
  return std::nullopt;
}

// Play's totals over every env and episode, and its output lines in
// mll_rollout's format.
class PlayReport {
 public:
  explicit PlayReport(int n_landers) : n_(n_landers), return_sums_(n_, 0.0) {}

  // One line for env j's finished episode. Outcomes, returns and lengths are
  // reported for every agent, done or not.
  void Episode(const VectorEnv& envs, int env, int episode, uint64_t seed,
               int steps, const StepData& last) {
    const std::vector<float>& returns = last.episode_returns;
    const std::vector<int32_t>& lengths = last.episode_lengths;
    const std::vector<LanderOutcome>& outcomes = last.outcomes;
    for (int a = 0; a < n_; ++a) {
      return_sums_[a] += returns[a];
      landed_ += outcomes[a] == LanderOutcome::kLanded;
      agent_steps_ += lengths[a];
    }
    total_steps_ += steps;
    ++env_episodes_;
    std::cout
        << absl::StrCat(
               "{\"episode\":", episode, ",\"seed\":", seed,
               ",\"steps\":", steps, ",\"returns\":",
               PerAgent(n_, [&](int a) { return JsonNumber(returns[a]); }),
               ",\"lengths\":", PerAgent(n_, [&](int a) { return lengths[a]; }),
               ",\"outcomes\":",
               PerAgent(n_,
                        [&](int a) {
                          return Quoted(LanderOutcomeName(outcomes[a]));
                        }),
               ",\"env\":", Quoted(envs.names()[env]),
               ",\"server\":", Quoted(envs.address(env)), "}")
        << std::endl;
  }

  void Summary(int episodes, int n_envs, double seconds,
               absl::string_view transport) const {
    std::cout
        << absl::StrCat(
               "{\"summary\":true,\"episodes\":", episodes,
               ",\"envs\":", n_envs, ",\"mean_return\":",
               PerAgent(n_,
                        [&](int a) {
                          return JsonNumber(return_sums_[a] / env_episodes_);
                        }),
               ",\"landing_rate\":",
               JsonNumber(static_cast<double>(landed_) / (env_episodes_ * n_)),
               ",\"mean_steps\":",
               JsonNumber(static_cast<double>(total_steps_) / env_episodes_),
               ",\"agent_steps\":", agent_steps_,
               ",\"agent_steps_per_second\":",
               JsonNumber(seconds > 0 ? agent_steps_ / seconds : 0.0),
               ",\"transport\":", Quoted(transport), "}")
        << std::endl;
  }

 private:
  const int n_;
  std::vector<double> return_sums_;
  int64_t landed_ = 0;
  int64_t total_steps_ = 0;
  int64_t agent_steps_ = 0;
  int64_t env_episodes_ = 0;
};

// Flies every lander of N envs (spread over the servers) through the
// servers, stepping them together with StepBatch; prints one line per env and
// episode and a summary, in mll_rollout's format (with one env, the same
// lines as mll_rollout's).
Result Play(const Client& client, const std::vector<std::string>&) {
  absl::StatusOr<PlayFlags> flags = ParsePlayFlags(client);
  if (!flags.ok()) return Usage(flags.status());
  bool usage_error = false;
  absl::StatusOr<VectorEnv> envs = OpenPlayEnvs(client, *flags, &usage_error);
  if (!envs.ok()) {
    return usage_error ? Usage(envs.status()) : Server(envs.status());
  }
  const int n_envs = envs->num_envs();
  const int n = envs->n_landers();
  if (flags->trained && envs->continuous()) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("policy is \"trained\", which flies discrete actions; ",
                     envs->names()[0], " is continuous")));
  }
  std::vector<PlayPilot> pilots;
  for (int j = 0; j < n_envs; ++j) {
    if (flags->trained) {
      pilots.emplace_back(flags->trained, n);
    } else {
      pilots.emplace_back(
          RemotePilot(flags->policy, n, envs->continuous(),
                      flags->base_seed + static_cast<uint64_t>(j)));
    }
  }

  PlayReport report(n);
  const auto start = std::chrono::steady_clock::now();
  for (int episode = 0; episode < flags->episodes; ++episode) {
    std::vector<uint64_t> seeds(n_envs);
    for (int j = 0; j < n_envs; ++j) {
      seeds[j] = flags->base_seed + static_cast<uint64_t>(episode) * n_envs + j;
    }
    std::vector<StepData> last;
    std::vector<int> steps;
    if (Result failed = FlyEpisode(*envs, pilots, seeds, &last, &steps)) {
      return failed;
    }
    for (int j = 0; j < n_envs; ++j) {
      report.Episode(*envs, j, episode, seeds[j], steps[j], last[j]);
    }
  }
  report.Summary(
      flags->episodes, n_envs,
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count(),
      envs->transport());
  return std::nullopt;
}

// What one bench client stepped.
struct BenchCount {
  int64_t env_steps = 0;
  int64_t agent_steps = 0;
  // How long each counted call (Step, or Recv) took, in seconds: a call
  // waits for its answer, so its slowest ones say what step_timeout must
  // allow.
  std::vector<double> call_seconds;
  std::string transport;
  absl::Status status;
};

// One bench client: its own Client (and so its own channels and Session
// streams) and VectorEnv of `n_envs`, stepped with uniform random actions
// (seeded by `seed`) until `until`.
BenchCount RunBenchClient(const std::vector<std::string>& addresses,
                          const ClientOptions& options,
                          const RemoteEnvConfig& config, int n_envs,
                          int batch_size, uint64_t seed,
                          std::chrono::steady_clock::time_point start,
                          std::chrono::steady_clock::time_point until) {
  BenchCount count;
  absl::StatusOr<Client> client = Client::Create(addresses, options);
  absl::StatusOr<VectorEnv> envs =
      client.ok() ? VectorEnv::Create(*client, n_envs, config, batch_size)
                  : absl::StatusOr<VectorEnv>(client.status());
  if (!envs.ok()) {
    count.status = envs.status();
    return count;
  }
  count.transport = envs->transport();
  const bool async = batch_size > 0 && batch_size < n_envs;
  count.status = async ? envs->AsyncReset(seed) : envs->Reset(seed);
  std::mt19937_64 rng(seed);
  // Async: each call carries the batch_size envs just received.
  const int per_call = async ? batch_size : n_envs;
  const size_t values = static_cast<size_t>(per_call) * envs->n_landers() *
                        (envs->continuous() ? 2 : 1);
  std::vector<int32_t> discrete(envs->continuous() ? 0 : values);
  std::vector<float> continuous(envs->continuous() ? values : 0);
  std::uniform_int_distribution<int32_t> engine(0, 3);
  std::uniform_real_distribution<float> throttle(-1.0f, 1.0f);
  // Steps until `start` are warm-up, not counted.
  while (count.status.ok() && std::chrono::steady_clock::now() < until) {
    for (int32_t& action : discrete) action = engine(rng);
    for (float& action : continuous) action = throttle(rng);
    const auto call_start = std::chrono::steady_clock::now();
    if (async) {
      count.status = envs->Recv();
      if (!count.status.ok()) break;
      const std::vector<int> ids(envs->env_ids().begin(),
                                 envs->env_ids().end());
      count.status = envs->continuous()
                         ? envs->Send(absl::MakeConstSpan(continuous), ids)
                         : envs->Send(absl::MakeConstSpan(discrete), ids);
    } else {
      count.status = envs->continuous()
                         ? envs->Step(absl::MakeConstSpan(continuous))
                         : envs->Step(absl::MakeConstSpan(discrete));
    }
    const auto call_end = std::chrono::steady_clock::now();
    if (call_end < start) continue;
    count.call_seconds.push_back(
        std::chrono::duration<double>(call_end - call_start).count());
    count.env_steps += per_call;
    for (uint8_t active : envs->active()) count.agent_steps += active;
  }
  return count;
}

// The load generator: --clients independent clients, each stepping --envs
// auto-resetting envs with random actions for --seconds (after a warm-up of
// a tenth of that), every call carrying every env; prints one JSON line.
Result Bench(const Client& client, const std::vector<std::string>&) {
  const int clients = absl::GetFlag(FLAGS_clients);
  const int envs_flag = absl::GetFlag(FLAGS_envs);
  const int n_envs = envs_flag > 0 ? envs_flag : 64;
  const double seconds = absl::GetFlag(FLAGS_seconds);
  const int batch_size = absl::GetFlag(FLAGS_batch_size);
  if (batch_size < 0 || batch_size > n_envs) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("batch_size is ", batch_size, "; allowed: 0 (Step) or 1..",
                     n_envs, " (--envs)")));
  }
  if (clients < 1 || clients > 256) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("clients is ", clients, "; allowed: 1..256")));
  }
  if (envs_flag < 0 || n_envs > 65536) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("envs is ", envs_flag, "; allowed: 0 (64) or 1..65536")));
  }
  if (!(seconds > 0 && seconds <= 3600)) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("seconds is ", seconds, "; allowed: (0, 3600]")));
  }
  absl::StatusOr<core::EnvConfig> config = core::EnvConfigFromFlags();
  if (!config.ok()) return Usage(config.status());
  absl::StatusOr<ClientOptions> options = OptionsFromFlags();
  if (!options.ok()) return Usage(options.status());
  std::vector<std::string> addresses;
  for (int server = 0; server < client.server_count(); ++server) {
    addresses.push_back(client.address(server));
  }
  const auto warm_up = std::chrono::duration<double>(seconds / 10);
  const auto start =
      std::chrono::steady_clock::now() +
      std::chrono::duration_cast<std::chrono::nanoseconds>(warm_up);
  const auto until =
      start + std::chrono::duration_cast<std::chrono::nanoseconds>(
                  std::chrono::duration<double>(seconds));
  std::vector<std::future<BenchCount>> runs;
  for (int c = 0; c < clients; ++c) {
    runs.push_back(std::async(std::launch::async, RunBenchClient, addresses,
                              *options, RemoteConfigFrom(*config), n_envs,
                              batch_size, static_cast<uint64_t>(c) << 32, start,
                              until));
  }
  BenchCount total;
  std::vector<std::string> transports;
  for (std::future<BenchCount>& run : runs) {
    BenchCount count = run.get();
    if (!count.status.ok() && total.status.ok()) total.status = count.status;
    total.call_seconds.insert(total.call_seconds.end(),
                              count.call_seconds.begin(),
                              count.call_seconds.end());
    total.env_steps += count.env_steps;
    total.agent_steps += count.agent_steps;
    transports.push_back(count.transport);
  }
  if (!total.status.ok()) return Server(total.status);
  const double elapsed =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  // "shared_memory" only when every client's streams use it.
  const bool all_shared = std::all_of(
      transports.begin(), transports.end(),
      [](const std::string& name) { return name == "shared_memory"; });
  // Each call's time in ms at quantile q (nearest rank), over every client.
  std::sort(total.call_seconds.begin(), total.call_seconds.end());
  const auto call_ms = [&](double q) {
    if (total.call_seconds.empty()) return 0.0;
    const size_t rank = static_cast<size_t>(
        std::ceil(q * static_cast<double>(total.call_seconds.size())));
    return 1000 * total.call_seconds[std::max<size_t>(rank, 1) - 1];
  };
  std::cout << absl::StrCat(
                   "{\"clients\":", clients, ",\"envs\":", n_envs,
                   ",\"batch_size\":", batch_size > 0 ? batch_size : n_envs,
                   ",\"n_landers\":", config->n_landers,
                   ",\"seconds\":", JsonNumber(elapsed),
                   ",\"env_steps\":", total.env_steps,
                   ",\"agent_steps\":", total.agent_steps,
                   ",\"env_steps_per_second\":",
                   JsonNumber(total.env_steps / elapsed),
                   ",\"agent_steps_per_second\":",
                   JsonNumber(total.agent_steps / elapsed),
                   ",\"calls\":", total.call_seconds.size(),
                   ",\"call_ms_p50\":", JsonNumber(call_ms(0.5)),
                   ",\"call_ms_p99\":", JsonNumber(call_ms(0.99)),
                   ",\"call_ms_p999\":", JsonNumber(call_ms(0.999)),
                   ",\"call_ms_max\":", JsonNumber(call_ms(1.0)),
                   ",\"transport\":",
                   Quoted(all_shared ? "shared_memory" : "native"), "}")
            << std::endl;
  return std::nullopt;
}

using Command = Result (*)(const Client&, const std::vector<std::string>&);

// What a command does, the arguments it takes and the flags it reads beyond
// the connection flags every command reads.
struct CommandSpec {
  Command run;
  int max_arguments;  // 1 for the commands naming an environment.
  const char* arguments;
  const char* summary;
  std::vector<absl::string_view> flags;
  bool takes_env_options;  // --n_landers, --continuous, ... (create, play).
};

const std::map<std::string, CommandSpec>& Commands() {
  static const auto* const kCommands = new std::map<std::string, CommandSpec>{
      {"health",
       {Health, 0, "", "checks that the server is serving", {}, false}},
      {"info",
       {Info,
        0,
        "",
        "prints each server's release, protocol version, capabilities and "
        "limits (one JSON line each)",
        {},
        false}},
      {"list",
       {List, 0, "", "lists the environments (one JSON line each)", {}, false}},
      {"create",
       {Create,
        0,
        "",
        "creates an environment and prints its name",
        {"server", "auto_reset"},
        true}},
      {"get", {Get, 1, " envs/ID", "prints an environment", {"name"}, false}},
      {"delete",
       {Delete, 1, " envs/ID", "deletes an environment", {"name"}, false}},
      {"reset",
       {Reset,
        1,
        " envs/ID",
        "resets an environment",
        {"name", "seed"},
        false}},
      {"step",
       {Step,
        1,
        " envs/ID",
        "steps every active lander once",
        {"name", "actions"},
        false}},
      {"render",
       {Render,
        1,
        " envs/ID",
        "writes a frame",
        {"name", "out", "format"},
        false}},
      {"play",
       {Play,
        0,
        "",
        "flies landers with a pilot and prints one JSON line per "
        "episode",
        {"policy", "weights", "episodes", "seed", "envs", "name", "transport"},
        true}},
      {"bench",
       {Bench,
        0,
        "",
        "steps --clients x --envs auto-resetting envs with random actions for "
        "--seconds and prints the throughput (one JSON line)",
        {"envs", "batch_size", "clients", "seconds", "transport"},
        true}},
  };
  return *kCommands;
}

std::string CommandNames() {
  std::vector<std::string> names;
  for (const auto& [name, command] : Commands()) names.push_back(name);
  return absl::StrJoin(names, ", ");
}

constexpr absl::string_view kConnectionFlags[] = {
    "address",       "timeout_ms",      "step_timeout_s", "tls",
    "tls_root_cert", "tls_server_name", "token",          "token_file"};

// `mll_cli --help`, or `mll_cli COMMAND --help` for one command's flags.
std::string Help(const std::vector<std::string>& words) {
  const std::vector<const absl::CommandLineFlag*> connection =
      core::tools::FlagsNamed(
          {std::begin(kConnectionFlags), std::end(kConnectionFlags)});
  for (const std::string& word : words) {
    const auto command = Commands().find(word);
    if (command == Commands().end()) continue;
    const CommandSpec& spec = command->second;
    std::string text = absl::StrCat("mll_cli ", word, spec.arguments,
                                    " [--flags]: ", spec.summary, "\n");
    if (!spec.flags.empty()) {
      absl::StrAppend(
          &text, "\nFlags:\n",
          core::tools::DescribeFlags(core::tools::FlagsNamed(spec.flags)));
    }
    if (spec.takes_env_options) {
      absl::StrAppend(&text, "\nEnvironment options:\n",
                      core::tools::DescribeFlags(
                          core::tools::FlagsDefinedIn("config_flags.cc")));
    }
    absl::StrAppend(&text, "\nConnection flags:\n",
                    core::tools::DescribeFlags(connection));
    return text;
  }
  std::string text =
      "mll_cli: talks to Multi Lunar Lander servers; prints JSON lines.\n"
      "Usage: mll_cli COMMAND [envs/ID] [--flags]; mll_cli COMMAND --help "
      "lists a command's flags.\nExit codes: 0 done, 1 the server or the "
      "connection failed, 2 bad command line.\n\nCommands:\n";
  for (const auto& [name, spec] : Commands()) {
    absl::StrAppend(&text, "  ", name, spec.arguments, ": ", spec.summary,
                    "\n");
  }
  absl::StrAppend(&text, "\nConnection flags (every command):\n",
                  core::tools::DescribeFlags(connection));
  return text;
}

int Run(const std::vector<std::string>& positional) {
  if (positional.empty()) {
    std::cerr << "mll_cli: missing command; one of " << CommandNames()
              << std::endl;
    return kExitUsage;
  }
  const std::string& command_name = positional[0];
  const auto command = Commands().find(command_name);
  if (command == Commands().end()) {
    std::cerr << "mll_cli: unknown command \"" << command_name << "\"; one of "
              << CommandNames() << std::endl;
    return kExitUsage;
  }
  absl::StatusOr<ClientOptions> options = OptionsFromFlags();
  if (!options.ok()) {
    std::cerr << "mll_cli: " << options.status() << std::endl;
    return kExitUsage;
  }
  const std::vector<std::string> addresses =
      absl::StrSplit(absl::GetFlag(FLAGS_address), ',');
  absl::StatusOr<Client> client = Client::Create(addresses, *options);
  if (!client.ok()) {
    std::cerr << "mll_cli: " << client.status() << std::endl;
    return kExitUsage;
  }
  const std::vector<std::string> args(positional.begin() + 1, positional.end());
  if (static_cast<int>(args.size()) > command->second.max_arguments) {
    std::cerr << "mll_cli " << command_name << ": takes "
              << (command->second.max_arguments == 0
                      ? "flags only"
                      : "one environment name and flags")
              << "; got \"" << absl::StrJoin(args, " ") << "\"; see mll_cli "
              << command_name << " --help" << std::endl;
    return kExitUsage;
  }
  Result failure = command->second.run(*client, args);
  if (!failure.has_value()) return 0;
  std::cerr << "mll_cli " << command_name << ": " << failure->status
            << std::endl;
  return failure->exit_code;
}

}  // namespace
}  // namespace mll::client

int main(int argc, char** argv) {
  const std::vector<std::string> positional =
      mll::core::tools::ParseCommandLine(argc, argv, mll::client::Help);
  // gRPC's own log lines (e.g. "E1125 ... Failed to parse [::1") repeat the
  // error mll_cli prints; GRPC_VERBOSITY (DEBUG, INFO, ERROR) turns them on.
  if (std::getenv("GRPC_VERBOSITY") == nullptr) {
    gpr_set_log_function([](gpr_log_func_args*) {});
  }
  return mll::client::Run(positional);
}

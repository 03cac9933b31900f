// mll_cli: the Multi Lunar Lander server from the command line, through the
// C++ client library. Output is JSON, one object per line.
//
//   mll_cli health
//   mll_cli list
//   mll_cli create --n_landers=5 --continuous --render_mode=rgb_array
//   mll_cli get envs/ID
//   mll_cli reset envs/ID --seed=7
//   mll_cli step envs/ID --actions=2,0,3
//   mll_cli render envs/ID --out=frame.png
//   mll_cli delete envs/ID
//   mll_cli play --policy=heuristic --episodes=3 --n_landers=4 [--name=envs/ID]
//
// Every command takes --address (default 127.0.0.1:50051). Exit codes: 0 done,
// 1 the server or the transport failed (its code and message are printed),
// 2 bad command line.
#include <chrono>
#include <cmath>
#include <cstdint>
#include <fstream>
#include <iostream>
#include <map>
#include <optional>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/flags/parse.h"
#include "absl/flags/usage.h"
#include "absl/status/status.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "config_flags.h"
#include "core_bridge.h"
#include "mll/client.h"

ABSL_FLAG(std::string, address, "127.0.0.1:50051", "Server address host:port.");
ABSL_FLAG(std::string, token, "", "Bearer token sent with every call.");
ABSL_FLAG(int, timeout_ms, 30000, "Deadline of each call in ms; 0 for none.");
ABSL_FLAG(std::string, name, "",
          "Environment name envs/ID (or give it as the argument after the "
          "command). For play: fly this env instead of creating one.");
ABSL_FLAG(std::string, seed, "",
          "reset: reseed with this unsigned integer (empty continues the "
          "stream). play: episode k is reset with seed + k (default 0); also "
          "seeds the random policy.");
ABSL_FLAG(std::string, actions, "",
          "step: comma-separated actions, one per lander (discrete) or two per "
          "lander [main, lateral] (continuous).");
ABSL_FLAG(std::string, out, "frame.png", "render: output file.");
ABSL_FLAG(std::string, format, "png", "render: png or rgb (raw bytes).");
ABSL_FLAG(std::string, policy, "heuristic", "play: heuristic or random.");
ABSL_FLAG(int, episodes, 1, "play: number of episodes, >= 1.");
ABSL_FLAG(bool, auto_reset, false,
          "create: the step after an episode ends starts a new one.");

namespace mll {
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
      "{\"observations\":", PerAgent(n, [&](int a) {
        std::vector<std::string> values;
        for (float v : data.observation(a)) values.push_back(JsonNumber(v));
        return absl::StrCat("[", absl::StrJoin(values, ","), "]");
      }),
      ",\"rewards\":",
      PerAgent(n, [&](int a) { return JsonNumber(data.rewards[a]); }),
      ",\"terminations\":",
      PerAgent(n, [&](int a) { return data.terminations[a] ? "true" : "false"; }),
      ",\"truncations\":",
      PerAgent(n, [&](int a) { return data.truncations[a] ? "true" : "false"; }),
      ",\"outcomes\":", PerAgent(n, [&](int a) {
        return Quoted(LanderOutcomeName(data.outcomes[a]));
      }),
      ",\"episode_over\":", data.episode_over ? "true" : "false",
      ",\"cycles\":", data.cycles);
  if (data.seed.has_value()) absl::StrAppend(&json, ",\"seed\":", *data.seed);
  absl::StrAppend(&json, "}");
  return json;
}

absl::StatusOr<std::string> EnvName(const std::vector<std::string>& args) {
  const std::string flag = absl::GetFlag(FLAGS_name);
  if (args.size() > 1) {
    return absl::InvalidArgumentError(absl::StrCat(
        "expected one environment name after the command; got ",
        args.size(), ": ", absl::StrJoin(args, " ")));
  }
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

Result List(const Client& client, const std::vector<std::string>&) {
  absl::StatusOr<std::vector<EnvInfo>> envs = client.ListEnvs();
  if (!envs.ok()) return Server(envs.status());
  for (const EnvInfo& env : *envs) std::cout << env.json << "\n";
  std::cout << std::flush;
  return std::nullopt;
}

Result Create(const Client& client, const std::vector<std::string>& args) {
  if (!args.empty()) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("create takes flags only; got ", absl::StrJoin(args, " "))));
  }
  absl::StatusOr<EnvConfig> config = EnvConfigFromFlags();
  if (!config.ok()) return Usage(config.status());
  RemoteEnvConfig remote = RemoteConfigFrom(*config);
  remote.auto_reset = absl::GetFlag(FLAGS_auto_reset);
  absl::StatusOr<RemoteEnv> env = client.CreateEnv(remote);
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
    const bool parsed = env->continuous()
                            ? absl::SimpleAtof(item, &real)
                            : absl::SimpleAtoi(item, &integer);
    if (!parsed) {
      return Usage(absl::InvalidArgumentError(absl::StrCat(
          "actions has \"", item, "\"; expected ",
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
  absl::StatusOr<StepData> data = env->Step(
      env->continuous() ? Actions::Continuous(continuous)
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
  absl::StatusOr<RenderedFrame> frame = env->Render(
      format_name == "png" ? FrameFormat::kPng : FrameFormat::kRgb);
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

// Flies every lander of an env through the server; prints one line per
// episode and a summary, in mll_rollout's format.
Result Play(const Client& client, const std::vector<std::string>& args) {
  if (!args.empty()) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("play takes flags only; got ", absl::StrJoin(args, " "))));
  }
  absl::StatusOr<PilotPolicy> policy =
      ParsePilotPolicy(absl::GetFlag(FLAGS_policy));
  if (!policy.ok()) return Usage(policy.status());
  const int episodes = absl::GetFlag(FLAGS_episodes);
  if (episodes < 1) {
    return Usage(absl::InvalidArgumentError(
        absl::StrCat("episodes is ", episodes, "; must be >= 1")));
  }
  absl::StatusOr<std::optional<uint64_t>> seed_flag = SeedFlag();
  if (!seed_flag.ok()) return Usage(seed_flag.status());
  const uint64_t base_seed = seed_flag->value_or(0);

  absl::StatusOr<RemoteEnv> env;
  const std::string name = absl::GetFlag(FLAGS_name);
  if (name.empty()) {
    absl::StatusOr<EnvConfig> config = EnvConfigFromFlags();
    if (!config.ok()) return Usage(config.status());
    env = client.CreateEnv(RemoteConfigFrom(*config));  // Deleted at exit.
  } else {
    env = client.Attach(name);
  }
  if (!env.ok()) return Server(env.status());
  const int n = env->n_landers();
  RemotePilot pilot(*policy, n, env->continuous(), base_seed);

  std::vector<double> return_sums(n, 0.0);
  int64_t landed = 0;
  int64_t total_steps = 0;
  int64_t agent_steps = 0;
  const auto start = std::chrono::steady_clock::now();
  for (int episode = 0; episode < episodes; ++episode) {
    const uint64_t seed = base_seed + static_cast<uint64_t>(episode);
    absl::StatusOr<StepData> data = env->Reset(seed);
    if (!data.ok()) return Server(data.status());
    int steps = 0;
    while (!data->episode_over) {
      data = env->Step(pilot.Act(*data));
      if (!data.ok()) return Server(data.status());
      ++steps;
    }
    // Outcomes, returns and lengths are reported for every agent, done or not.
    const std::vector<float>& returns = data->episode_returns;
    const std::vector<int32_t>& lengths = data->episode_lengths;
    const std::vector<LanderOutcome>& outcomes = data->outcomes;
    for (int a = 0; a < n; ++a) {
      return_sums[a] += returns[a];
      landed += outcomes[a] == LanderOutcome::kLanded;
      agent_steps += lengths[a];
    }
    total_steps += steps;
    std::cout << absl::StrCat(
                     "{\"episode\":", episode, ",\"seed\":", seed,
                     ",\"steps\":", steps, ",\"returns\":",
                     PerAgent(n, [&](int a) { return JsonNumber(returns[a]); }),
                     ",\"lengths\":",
                     PerAgent(n, [&](int a) { return lengths[a]; }),
                     ",\"outcomes\":", PerAgent(n, [&](int a) {
                       return Quoted(LanderOutcomeName(outcomes[a]));
                     }),
                     "}")
              << std::endl;
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();
  std::cout << absl::StrCat(
                   "{\"summary\":true,\"episodes\":", episodes,
                   ",\"mean_return\":", PerAgent(n, [&](int a) {
                     return JsonNumber(return_sums[a] / episodes);
                   }),
                   ",\"landing_rate\":",
                   JsonNumber(static_cast<double>(landed) / (episodes * n)),
                   ",\"mean_steps\":",
                   JsonNumber(static_cast<double>(total_steps) / episodes),
                   ",\"agent_steps\":", agent_steps,
                   ",\"agent_steps_per_second\":",
                   JsonNumber(seconds > 0 ? agent_steps / seconds : 0.0), "}")
            << std::endl;
  return std::nullopt;
}

using Command = Result (*)(const Client&, const std::vector<std::string>&);

const std::map<std::string, Command>& Commands() {
  static const auto* const kCommands = new std::map<std::string, Command>{
      {"health", Health}, {"list", List},     {"create", Create},
      {"get", Get},       {"delete", Delete}, {"reset", Reset},
      {"step", Step},     {"render", Render}, {"play", Play},
  };
  return *kCommands;
}

std::string CommandNames() {
  std::vector<std::string> names;
  for (const auto& [name, command] : Commands()) names.push_back(name);
  return absl::StrJoin(names, ", ");
}

int Run(const std::vector<char*>& positional) {
  if (positional.size() < 2) {
    std::cerr << "mll_cli: missing command; one of " << CommandNames()
              << std::endl;
    return kExitUsage;
  }
  const std::string command_name = positional[1];
  const auto command = Commands().find(command_name);
  if (command == Commands().end()) {
    std::cerr << "mll_cli: unknown command \"" << command_name
              << "\"; one of " << CommandNames() << std::endl;
    return kExitUsage;
  }
  const int timeout_ms = absl::GetFlag(FLAGS_timeout_ms);
  if (timeout_ms < 0) {
    std::cerr << "mll_cli: timeout_ms is " << timeout_ms << "; must be >= 0"
              << std::endl;
    return kExitUsage;
  }
  ClientOptions options;
  options.token = absl::GetFlag(FLAGS_token);
  options.call_timeout = std::chrono::milliseconds(timeout_ms);
  absl::StatusOr<Client> client =
      Client::Create(absl::GetFlag(FLAGS_address), options);
  if (!client.ok()) {
    std::cerr << "mll_cli: " << client.status() << std::endl;
    return kExitUsage;
  }
  const std::vector<std::string> args(positional.begin() + 2,
                                      positional.end());
  Result failure = command->second(*client, args);
  if (!failure.has_value()) return 0;
  std::cerr << "mll_cli " << command_name << ": " << failure->status
            << std::endl;
  return failure->exit_code;
}

}  // namespace
}  // namespace mll

int main(int argc, char** argv) {
  absl::SetProgramUsageMessage(
      "Talks to a Multi Lunar Lander server.\n"
      "  mll_cli health|list|create|get|delete|reset|step|render|play "
      "[envs/ID] [--flags]\nSee --helpfull for every flag.");
  return mll::Run(absl::ParseCommandLine(argc, argv));
}

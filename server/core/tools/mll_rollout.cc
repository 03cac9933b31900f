// mll_rollout: runs episodes of one environment in-process and prints one
// JSON object per episode, then a summary line. Optionally writes a PNG per
// step. Exit codes: 0 done, 1 runtime failure (e.g. a frame could not be
// written) or a flag absl cannot parse, 2 bad flags or config (the core's
// message is printed). The summary's agent_steps_per_second is wall-clock
// time over all episodes, frame writing included: bench/core measures speed.
//
//   mll_rollout --n_landers=3 --episodes=3 --seed=0 --policy=heuristic
//       --frames_dir=out/frames --render_mode=rgb_array
#include <chrono>
#include <cstdint>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <memory>
#include <string>
#include <vector>

#include "absl/flags/flag.h"
#include "absl/status/status.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "config_flags.h"
#include "mll/core/env.h"
#include "mll/core/heuristic.h"
#include "mll/core/renderer.h"
#include "program_usage.h"
#include "rng.h"

ABSL_FLAG(int, episodes, 1, "Number of episodes, >= 1.");
ABSL_FLAG(uint64_t, seed, 0,
          "Episode k is reset with seed + k; also seeds the random policy.");
ABSL_FLAG(std::string, policy, "heuristic",
          "heuristic (Gymnasium's pilot) or random.");
ABSL_FLAG(std::string, frames_dir, "",
          "If set, writes <episode>_<step>.png per step there (created if "
          "missing); implies render_mode=rgb_array.");

namespace mll::core {
namespace {

enum class Policy { kHeuristic, kRandom };

struct Options {
  EnvConfig config;
  int episodes = 1;
  uint64_t seed = 0;
  Policy policy = Policy::kHeuristic;
  std::string frames_dir;
};

absl::StatusOr<Options> OptionsFromFlags() {
  Options options;
  options.episodes = absl::GetFlag(FLAGS_episodes);
  if (options.episodes < 1) {
    return absl::InvalidArgumentError(
        absl::StrCat("episodes is ", options.episodes, "; must be >= 1"));
  }
  options.seed = absl::GetFlag(FLAGS_seed);
  const std::string policy = absl::GetFlag(FLAGS_policy);
  if (policy == "heuristic") {
    options.policy = Policy::kHeuristic;
  } else if (policy == "random") {
    options.policy = Policy::kRandom;
  } else {
    return absl::InvalidArgumentError(absl::StrCat(
        "policy is \"", policy, "\"; allowed: \"heuristic\", \"random\""));
  }
  options.frames_dir = absl::GetFlag(FLAGS_frames_dir);
  absl::StatusOr<EnvConfig> config = EnvConfigFromFlags();
  if (!config.ok()) return config.status();
  options.config = *config;
  if (!options.frames_dir.empty()) {
    options.config.render_mode = RenderMode::kRgbArray;
  }
  return options;
}

// Chooses every agent's action for one step. The random policy owns its
// generator, seeded by --seed, so that runs repeat exactly.
class Pilot {
 public:
  Pilot(Policy policy, const Env& env, uint64_t seed)
      : policy_(policy),
        continuous_(env.config().continuous),
        rng_(seed),
        discrete_(env.n_landers(), 0),
        continuous_actions_(kContinuousActionSize * env.n_landers(), 0.0f) {}

  ActionsView Act(const Env& env) {
    for (int agent = 0; agent < env.n_landers(); ++agent) {
      if (!env.is_active(agent)) continue;
      AgentAction action =
          policy_ == Policy::kHeuristic
              ? HeuristicAction(env.observation(agent), continuous_)
              : RandomAction();
      discrete_[agent] = action.discrete;
      for (int i = 0; i < kContinuousActionSize; ++i) {
        continuous_actions_[kContinuousActionSize * agent + i] =
            action.continuous[i];
      }
    }
    ActionsView view;
    if (continuous_) {
      view.continuous = continuous_actions_;
    } else {
      view.discrete = discrete_;
    }
    return view;
  }

 private:
  AgentAction RandomAction() {
    AgentAction action;
    if (continuous_) {
      for (float& value : action.continuous) {
        value = static_cast<float>(rng_.Uniform(-1.0, 1.0));
      }
    } else {
      action.discrete =
          static_cast<int32_t>(rng_.Integer(0, kDiscreteActionCount - 1));
    }
    return action;
  }

  Policy policy_;
  bool continuous_;
  internal::Rng rng_;
  std::vector<int32_t> discrete_;
  std::vector<float> continuous_actions_;
};

std::string FrameName(const std::string& dir, int episode, int step) {
  return absl::StrFormat("%s/%03d_%05d.png", dir, episode, step);
}

absl::Status WriteFrame(Env& env, const std::string& path) {
  absl::StatusOr<Frame> frame = RenderEnv(env);
  if (!frame.ok()) return frame.status();
  absl::StatusOr<std::string> png = EncodePng(*frame);
  if (!png.ok()) return png.status();
  std::ofstream file(path, std::ios::binary);
  file.write(png->data(), static_cast<std::streamsize>(png->size()));
  file.close();
  if (!file) {
    return absl::UnavailableError(
        absl::StrCat("cannot write frame file \"", path,
                     "\"; does --frames_dir exist and is it writable?"));
  }
  return absl::OkStatus();
}

// A JSON object {"lander_0": value, ...} for every agent.
template <typename ValueFn>
std::string PerAgentJson(int n_landers, ValueFn value) {
  std::vector<std::string> members;
  members.reserve(n_landers);
  for (int agent = 0; agent < n_landers; ++agent) {
    members.push_back(
        absl::StrCat("\"", AgentName(agent), "\":", value(agent)));
  }
  return absl::StrCat("{", absl::StrJoin(members, ","), "}");
}

std::string JsonNumber(double value) { return absl::StrFormat("%.6f", value); }

struct Totals {
  std::vector<double> returns;  // Per agent, summed over episodes.
  int64_t landed = 0;           // Agent-episodes that ended landed.
  int64_t steps = 0;            // World steps over all episodes.
  int64_t agent_steps = 0;      // Steps taken by agents over all episodes.
};

absl::Status Run(const Options& options) {
  absl::StatusOr<std::unique_ptr<Env>> created = Env::Create(options.config);
  if (!created.ok()) return created.status();
  Env& env = **created;
  const int n = env.n_landers();
  Pilot pilot(options.policy, env, options.seed);
  if (!options.frames_dir.empty()) {
    std::error_code error;
    std::filesystem::create_directories(options.frames_dir, error);
    if (error) {
      return absl::UnavailableError(absl::StrCat("cannot create frames_dir \"",
                                                 options.frames_dir,
                                                 "\": ", error.message()));
    }
  }
  StepResult result;
  Totals totals;
  totals.returns.assign(n, 0.0);

  const auto start = std::chrono::steady_clock::now();
  for (int episode = 0; episode < options.episodes; ++episode) {
    const uint64_t seed = options.seed + static_cast<uint64_t>(episode);
    env.Reset(seed, &result);
    int step = 0;
    while (true) {
      if (!options.frames_dir.empty()) {
        absl::Status written =
            WriteFrame(env, FrameName(options.frames_dir, episode, step));
        if (!written.ok()) return written;
      }
      if (env.episode_over()) break;
      absl::Status stepped = env.Step(pilot.Act(env), &result);
      if (!stepped.ok()) return stepped;
      ++step;
    }
    for (int agent = 0; agent < n; ++agent) {
      totals.returns[agent] += env.episode_return(agent);
      totals.landed += env.outcome(agent) == Outcome::kLanded;
      totals.agent_steps += env.episode_length(agent);
    }
    totals.steps += step;
    std::cout
        << absl::StrCat(
               "{\"episode\":", episode, ",\"seed\":", seed,
               ",\"steps\":", step, ",\"returns\":",
               PerAgentJson(
                   n, [&](int a) { return JsonNumber(env.episode_return(a)); }),
               ",\"lengths\":",
               PerAgentJson(n, [&](int a) { return env.episode_length(a); }),
               ",\"outcomes\":",
               PerAgentJson(n,
                            [&](int a) {
                              return absl::StrCat(
                                  "\"", OutcomeName(env.outcome(a)), "\"");
                            }),
               "}")
        << std::endl;
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start)
          .count();

  const double episodes = options.episodes;
  std::cout
      << absl::StrCat(
             "{\"summary\":true,\"episodes\":", options.episodes,
             ",\"mean_return\":",
             PerAgentJson(n,
                          [&](int a) {
                            return JsonNumber(totals.returns[a] / episodes);
                          }),
             ",\"landing_rate\":",
             JsonNumber(static_cast<double>(totals.landed) / (episodes * n)),
             ",\"mean_steps\":", JsonNumber(totals.steps / episodes),
             ",\"agent_steps\":", totals.agent_steps,
             ",\"agent_steps_per_second\":",
             JsonNumber(seconds > 0 ? totals.agent_steps / seconds : 0.0), "}")
      << std::endl;
  return absl::OkStatus();
}

}  // namespace
}  // namespace mll::core

int main(int argc, char** argv) {
  mll::core::tools::ParseFlagsOnly(argc, argv, "mll_rollout", [] {
    return absl::StrCat(
        "mll_rollout: runs Multi Lunar Lander episodes in-process; prints one "
        "JSON line per episode and a summary line.\n"
        "Usage: mll_rollout [--flags]\n\nFlags:\n",
        mll::core::tools::DescribeFlags(
            mll::core::tools::FlagsDefinedIn("mll_rollout.cc")),
        "\nEnvironment options:\n",
        mll::core::tools::DescribeFlags(
            mll::core::tools::FlagsDefinedIn("config_flags.cc")));
  });
  absl::StatusOr<mll::core::Options> options = mll::core::OptionsFromFlags();
  if (!options.ok()) {
    std::cerr << "mll_rollout: " << options.status().message() << std::endl;
    return 2;
  }
  absl::Status status = mll::core::Run(*options);
  if (!status.ok()) {
    std::cerr << "mll_rollout: " << status.ToString() << std::endl;
    // The core re-validates the config in Env::Create: still a usage error.
    return absl::IsInvalidArgument(status) ? 2 : 1;
  }
  return 0;
}

// Test tool: one env of a C++ VectorEnv, started from a seed or restored from
// a snapshot file (EnvSnapshot's bytes, from either client), stepped with a
// fixed action pattern, its snapshot written to a file. client_py/tests/
// test_cpp_env_snapshot.py compares those bytes with the Python client's.
//
//   env_snapshot_tool --address=HOST:PORT --n_landers=N --max_cycles=M
//                  (--seed=S | --restore=FILE) --first_step=T --steps=K
//                  --out=FILE
//
// Step t (counted from T) gives lander a the action (t + a) % 4, as the
// Python test does. Exit code 0 done, 1 a failure (printed), 2 bad arguments.
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <map>
#include <string>
#include <vector>

#include "absl/strings/numbers.h"
#include "mll/client.h"
#include "mll/vector_env.h"

namespace {

int Fail(const absl::Status& status) {
  std::fprintf(stderr, "env_snapshot_tool: %s\n", status.ToString().c_str());
  return 1;
}

}  // namespace

int main(int argc, char** argv) {
  std::map<std::string, std::string> flags;
  for (int i = 1; i < argc; ++i) {
    const std::string arg = argv[i];
    const size_t equals = arg.find('=');
    if (arg.rfind("--", 0) != 0 || equals == std::string::npos) {
      std::fprintf(stderr, "env_snapshot_tool: bad argument %s\n", argv[i]);
      return 2;
    }
    flags[arg.substr(2, equals - 2)] = arg.substr(equals + 1);
  }
  int n_landers = 0, max_cycles = 0, first_step = 0, steps = 0;
  if (!absl::SimpleAtoi(flags["n_landers"], &n_landers) ||
      !absl::SimpleAtoi(flags["max_cycles"], &max_cycles) ||
      !absl::SimpleAtoi(flags["first_step"], &first_step) ||
      !absl::SimpleAtoi(flags["steps"], &steps) || flags["out"].empty()) {
    std::fprintf(stderr,
                 "env_snapshot_tool: --n_landers, --max_cycles, --first_step, "
                 "--steps and --out are required\n");
    return 2;
  }
  absl::StatusOr<mll::client::Client> client =
      mll::client::Client::Create(flags["address"]);
  if (!client.ok()) return Fail(client.status());
  mll::client::RemoteEnvConfig config;
  config.n_landers = n_landers;
  config.max_cycles = max_cycles;
  absl::StatusOr<mll::client::VectorEnv> envs =
      mll::client::VectorEnv::Create(*client, 1, config);
  if (!envs.ok()) return Fail(envs.status());
  uint64_t seed = 0;
  if (absl::SimpleAtoi(flags["seed"], &seed)) {
    if (absl::Status status = envs->Reset(seed); !status.ok()) {
      return Fail(status);
    }
  } else {
    std::ifstream in(flags["restore"], std::ios::binary);
    const std::string snapshot((std::istreambuf_iterator<char>(in)),
                               std::istreambuf_iterator<char>());
    absl::StatusOr<std::vector<float>> restored = envs->RestoreEnv(0, snapshot);
    if (!restored.ok()) return Fail(restored.status());
  }
  std::vector<int32_t> actions(n_landers);
  for (int t = first_step; t < first_step + steps; ++t) {
    for (int a = 0; a < n_landers; ++a) actions[a] = (t + a) % 4;
    if (absl::Status status = envs->Step(actions); !status.ok()) {
      return Fail(status);
    }
  }
  absl::StatusOr<std::string> snapshot = envs->EnvSnapshot(0);
  if (!snapshot.ok()) return Fail(snapshot.status());
  std::ofstream(flags["out"], std::ios::binary) << *snapshot;
  return 0;
}

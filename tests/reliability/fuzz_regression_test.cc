// Replays the fuzzers' committed seed corpora and every crash input they
// found (fuzz/regressions/) through the same harnesses the fuzzers run, so a
// fixed crash stays fixed in every build, sanitized or not. A harness aborts
// on a crash, a wrong status code or a non-finite result.
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "gtest/gtest.h"
#include "harness.h"
#include "mll/v1/multi_lunar_lander.pb.h"

namespace mll::fuzz {
namespace {

namespace fs = std::filesystem;

// Every input file under fuzz/<kind>/<target>/ (dotfiles skipped).
std::vector<fs::path> Inputs(const std::string& target) {
  std::vector<fs::path> paths;
  for (const char* kind : {"corpus", "regressions"}) {
    const fs::path dir = fs::path(MLL_FUZZ_DIR) / kind / target;
    if (!fs::is_directory(dir)) continue;
    for (const fs::directory_entry& entry : fs::directory_iterator(dir)) {
      if (entry.is_regular_file() &&
          entry.path().filename().string().front() != '.') {
        paths.push_back(entry.path());
      }
    }
  }
  return paths;
}

std::vector<uint8_t> ReadBytes(const fs::path& path) {
  std::ifstream in(path, std::ios::binary);
  return std::vector<uint8_t>(std::istreambuf_iterator<char>(in), {});
}

// Runs every input of `target` through `harness` (which aborts on a crash
// or a broken contract).
void ReplayAll(const std::string& target,
               void (*harness)(const uint8_t*, size_t)) {
  const std::vector<fs::path> inputs = Inputs(target);
  ASSERT_GE(inputs.size(), 5u) << "the " << target << " seed corpus is missing";
  for (const fs::path& path : inputs) {
    SCOPED_TRACE(path.string());
    const std::vector<uint8_t> bytes = ReadBytes(path);
    harness(bytes.data(), bytes.size());
  }
}

TEST(FuzzRegressionTest, CoreInputsRunCleanly) {
  ReplayAll("core", RunCoreInput);
}

TEST(FuzzRegressionTest, ServiceInputsRunCleanly) {
  ReplayAll("service", RunServiceInput);
}

// Inputs the fuzzer builds byte by byte: frames are read only as far as the
// input goes (ASan checks the reads), envs made by an input are gone after it.
TEST(FuzzRegressionTest, ServiceFramesAreBoundedByTheInput) {
  std::vector<uint8_t> input;
  AppendServiceOp(service::Method::kCreateEnv, "",
                  &input);  // All defaults: 3 landers.
  v1::ResetEnvRequest reset;
  reset.set_name("@0");
  AppendServiceOp(service::Method::kResetEnv, reset.SerializeAsString(),
                  &input);
  RunServiceInput(input.data(), input.size());
  input.resize(input.size() - 1);  // A truncated last frame.
  RunServiceInput(input.data(), input.size());
  // A length far past the end: ListEnvs with page_size 1, then nothing.
  const std::vector<uint8_t> oversized = {
      static_cast<uint8_t>(service::Method::kListEnvs), 0xff, 0xff, 0x08, 0x01};
  RunServiceInput(oversized.data(), oversized.size());
}

}  // namespace
}  // namespace mll::fuzz

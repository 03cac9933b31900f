// LoadMeter's window arithmetic on readings made up here (steady load, an
// idle gap, more samples than it keeps, samples too close together), the
// cgroup v2 CPU quota on a cgroup tree made up in a temporary directory, and
// the cores this test may use.
#include "mll/service/load_meter.h"

#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>
#include <thread>

#include "gtest/gtest.h"

namespace mll::service {
namespace {

constexpr int64_t kSecond = 1'000'000'000;

// A reading at `seconds` with `cpu_seconds` of CPU and `agent_steps`.
LoadMeter::Reading At(double seconds, double cpu_seconds,
                      uint64_t agent_steps) {
  LoadMeter::Reading reading;
  reading.time_ns = static_cast<int64_t>(seconds * kSecond);
  reading.cpu_ns = static_cast<int64_t>(cpu_seconds * kSecond);
  reading.agent_steps = agent_steps;
  return reading;
}

TEST(LoadMeterTest, SinceTheStartWhenSoonerThanTheWindow) {
  LoadMeter meter(At(100, 3, 50));
  const LoadMeter::Rates rates = meter.Over(At(102, 4, 1050));
  EXPECT_DOUBLE_EQ(rates.cpu_cores, 0.5);
  EXPECT_DOUBLE_EQ(rates.agent_steps_per_s, 500);
  // No time since the start: nothing to divide by.
  EXPECT_EQ(meter.Over(At(100, 3, 50)).cpu_cores, 0);
}

TEST(LoadMeterTest, SteadyLoadOverTheLastTenSeconds) {
  LoadMeter meter(At(0, 0, 0));
  // 1.5 cores and 2,000 agent-steps/s for 30 s, then 0.25 cores and 100/s:
  // samples every second, more than the meter keeps.
  double cpu = 0;
  uint64_t steps = 0;
  for (int t = 1; t <= 40; ++t) {
    cpu += t <= 30 ? 1.5 : 0.25;
    steps += t <= 30 ? 2000 : 100;
    ASSERT_TRUE(meter.Due(At(t, 0, 0).time_ns)) << t;
    meter.Add(At(t, cpu, steps));
  }
  LoadMeter::Rates rates = meter.Over(At(40.5, cpu + 0.125, steps + 50));
  // [30.5, 40.5]: the seconds from 30 on ran at 0.25 cores.
  EXPECT_NEAR(rates.cpu_cores, 0.25, 1e-9);
  EXPECT_NEAR(rates.agent_steps_per_s, 100, 1e-6);
  rates = meter.Over(At(35, cpu - 5 * 0.25, steps - 500));
  // [25, 35]: 5 s at 1.5 cores and 5 s at 0.25 (the samples at 35..40 are
  // after `now` and not used).
  EXPECT_NEAR(rates.cpu_cores, (5 * 1.5 + 5 * 0.25) / 10, 1e-9);
  EXPECT_NEAR(rates.agent_steps_per_s, (5 * 2000 + 5 * 100) / 10.0, 1e-6);
}

// A server that nobody called for a minute has no samples from it; the CPU
// its window starts with is interpolated across the gap, so the gap counts
// as the idle time it was.
TEST(LoadMeterTest, AnIdleGapWithoutSamplesCountsAsIdle) {
  LoadMeter meter(At(0, 0, 0));
  for (int t = 1; t <= 5; ++t) meter.Add(At(t, t, 100 * t));
  // Idle from 5 s to 60 s, then busy at one core again.
  for (int t = 60; t <= 64; ++t)
    meter.Add(At(t, 5 + (t - 60), 500 + 100 * (t - 60)));
  const LoadMeter::Rates rates = meter.Over(At(65, 10, 1000));
  EXPECT_NEAR(rates.cpu_cores, 0.5, 1e-3);  // 5 busy seconds of the last 10.
  EXPECT_NEAR(rates.agent_steps_per_s, 50, 0.1);
  // GetServerInfo keeps its own reading as a sample; asked again after a
  // long idle time: 0.
  meter.Add(At(65, 10, 1000));
  const LoadMeter::Rates later = meter.Over(At(600, 10, 1000));
  EXPECT_EQ(later.cpu_cores, 0);
  EXPECT_EQ(later.agent_steps_per_s, 0);
}

TEST(LoadMeterTest, SamplesAtMostOncePerSecond) {
  LoadMeter meter(At(10, 0, 0));
  EXPECT_FALSE(meter.Due(At(10.5, 0, 0).time_ns));
  EXPECT_TRUE(meter.Due(At(11, 0, 0).time_ns));
  meter.Add(At(11, 1, 0));
  meter.Add(At(11.2, 100, 0));  // Too soon after 11: not kept.
  EXPECT_FALSE(meter.Due(At(11.9, 0, 0).time_ns));
  EXPECT_NEAR(meter.Over(At(12, 2, 0)).cpu_cores, 1.0, 1e-9);
}

class CgroupTree : public ::testing::Test {
 protected:
  void SetUp() override {
    char path[] = "/tmp/mll_cgroup_XXXXXX";
    ASSERT_NE(mkdtemp(path), nullptr);
    root_ = path;
  }
  void TearDown() override { std::filesystem::remove_all(root_); }
  void CpuMax(const std::string& cgroup, const std::string& text) {
    std::filesystem::create_directories(root_ + cgroup);
    std::ofstream(root_ + cgroup + "/cpu.max") << text << "\n";
  }
  std::string root_;
};

TEST_F(CgroupTree, TheLowestQuotaFromTheCgroupUpBinds) {
  CpuMax("", "max 100000");
  CpuMax("/kubepods", "max 100000");
  CpuMax("/kubepods/pod1", "150000 100000");
  CpuMax("/kubepods/pod1/ctr", "max 100000");
  EXPECT_EQ(CgroupCpuLimitCores(root_, "0::/kubepods/pod1/ctr\n"), 1.5);
  CpuMax("/kubepods/pod1/ctr", "50000 100000");
  EXPECT_EQ(CgroupCpuLimitCores(root_, "0::/kubepods/pod1/ctr\n"), 0.5);
  // A private cgroup namespace: the process's cgroup is the mount's root.
  CpuMax("", "200000 100000");
  EXPECT_EQ(CgroupCpuLimitCores(root_, "0::/\n"), 2.0);
}

TEST_F(CgroupTree, NoQuotaNoCgroupV2OrNoFile) {
  CpuMax("/a", "max 100000");
  EXPECT_EQ(CgroupCpuLimitCores(root_, "0::/a\n"), std::nullopt);
  EXPECT_EQ(CgroupCpuLimitCores(root_, "0::/missing/b\n"), std::nullopt);
  CpuMax("/v1", "50000 100000");
  // cgroup v1 lines only: not the v2 hierarchy's path.
  EXPECT_EQ(CgroupCpuLimitCores(root_, "4:cpu,cpuacct:/v1\n"), std::nullopt);
}

TEST(CoresAvailableTest, AtLeastAFractionAndAtMostTheMachine) {
  const double cores = CoresAvailable();
  EXPECT_GT(cores, 0);
  EXPECT_LE(cores, std::thread::hardware_concurrency());
}

}  // namespace
}  // namespace mll::service

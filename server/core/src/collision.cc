#include "collision.h"

namespace mll::core {
namespace internal {
namespace {

b2Filter MakeFilter(uint16_t category, uint16_t mask, int16_t group) {
  b2Filter filter;
  filter.categoryBits = category;
  filter.maskBits = mask;
  filter.groupIndex = group;
  return filter;
}

int16_t LanderGroup(int agent) { return static_cast<int16_t>(-(agent + 1)); }

}  // namespace

b2Filter MoonFilter() { return MakeFilter(kMoonCategory, kMoonMask, 0); }
b2Filter LanderBodyFilter(int agent) {
  return MakeFilter(kLanderCategory, kLanderMask, LanderGroup(agent));
}
b2Filter LegFilter(int agent) {
  return MakeFilter(kLegCategory, kLegMask, LanderGroup(agent));
}
b2Filter ParticleFilter() {
  return MakeFilter(kParticleCategory, kParticleMask, 0);
}

// Layout: agent + 1 in the high bits, the part in the low byte.
uintptr_t EncodeFixtureTag(Part part, int agent) {
  return (static_cast<uintptr_t>(agent + 1) << 8) |
         static_cast<uintptr_t>(part);
}

FixtureTag DecodeFixtureTag(uintptr_t pointer) {
  FixtureTag tag;
  tag.part = static_cast<Part>(pointer & 0xff);
  tag.agent = static_cast<int>(pointer >> 8) - 1;
  return tag;
}

}  // namespace internal
}  // namespace mll::core

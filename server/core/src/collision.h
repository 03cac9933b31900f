// Who collides with whom (the paper's tables I and II) and how a fixture says
// which lander and which part it belongs to.
//
// Categories: moon 0x1, lander body 0x2, leg 0x4, particle 0x8.
//   moon     collides with lander, leg, particle (and moon)
//   lander   collides with moon, lander, leg
//   leg      collides with moon, lander, leg
//   particle collides with moon only
// Every fixture of lander i carries group index -(i + 1): Box2D never lets
// fixtures of one negative group collide, so a lander never hits its own legs.
#ifndef MLL_CORE_SRC_COLLISION_H_
#define MLL_CORE_SRC_COLLISION_H_

#include <cstdint>

#include "box2d/box2d.h"

namespace mll::core {
namespace internal {

inline constexpr uint16_t kMoonCategory = 0x0001;
inline constexpr uint16_t kLanderCategory = 0x0002;
inline constexpr uint16_t kLegCategory = 0x0004;
inline constexpr uint16_t kParticleCategory = 0x0008;

inline constexpr uint16_t kMoonMask =
    kMoonCategory | kLanderCategory | kLegCategory | kParticleCategory;
inline constexpr uint16_t kLanderMask =
    kMoonCategory | kLanderCategory | kLegCategory;
inline constexpr uint16_t kLegMask =
    kMoonCategory | kLanderCategory | kLegCategory;
inline constexpr uint16_t kParticleMask = kMoonCategory;

b2Filter MoonFilter();
b2Filter LanderBodyFilter(int agent);
b2Filter LegFilter(int agent);
b2Filter ParticleFilter();

// What a fixture is, stored in b2FixtureUserData::pointer. Zero means
// untagged (never used by our worlds).
enum class Part : uint8_t {
  kMoon = 1,
  kBody = 2,
  kLeg0 = 3,  // Gymnasium's legs[0] (side i = -1), observation[6].
  kLeg1 = 4,  // legs[1] (side i = +1), observation[7].
  kParticle = 5,
};

struct FixtureTag {
  Part part = Part::kMoon;
  int agent = -1;  // Lander index for kBody, kLeg0, kLeg1; else -1.
};

uintptr_t EncodeFixtureTag(Part part, int agent);
FixtureTag DecodeFixtureTag(uintptr_t pointer);
// (b2Fixture::GetUserData() is not const in Box2D 2.4.1.)
inline FixtureTag TagOf(b2Fixture* fixture) {
  return DecodeFixtureTag(fixture->GetUserData().pointer);
}
inline bool IsLanderPart(Part part) {
  return part == Part::kBody || part == Part::kLeg0 || part == Part::kLeg1;
}

}  // namespace internal
}  // namespace mll::core

#endif  // MLL_CORE_SRC_COLLISION_H_

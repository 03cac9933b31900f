// The numbers of one Multi Lunar Lander world, named once. They reproduce
// Gymnasium's LunarLander-v3 (gymnasium/envs/box2d/lunar_lander.py, Gymnasium
// 1.x): same names, same values, so that a single lander behaves like it
// (docs/environment.md). Lengths in pixels are divided
// by kScale to get meters, as Gymnasium does.
#ifndef MLL_CORE_SRC_CONSTANTS_H_
#define MLL_CORE_SRC_CONSTANTS_H_

#include <array>

namespace mll::core {
namespace internal {

inline constexpr int kFps = 50;
inline constexpr double kScale = 30.0;  // Pixels per meter.

inline constexpr double kMainEnginePower = 13.0;
inline constexpr double kSideEnginePower = 0.6;
inline constexpr double kInitialRandom = 1000.0;  // Push force bound, N.

// Body polygon in pixels, counter-clockwise.
inline constexpr std::array<std::array<double, 2>, 6> kLanderPoly = {
    {{-14, +17}, {-17, 0}, {-17, -10}, {+17, -10}, {+17, 0}, {+14, +17}}};
inline constexpr double kLegAway = 20.0;
inline constexpr double kLegDown = 18.0;
inline constexpr double kLegW = 2.0;
inline constexpr double kLegH = 8.0;
inline constexpr double kLegSpringTorque = 40.0;

inline constexpr double kSideEngineHeight = 14.0;
inline constexpr double kSideEngineAway = 12.0;
// Gymnasium's side-engine impulse position uses 17 px along the tip instead of
// kSideEngineHeight (a quirk it documents and keeps); we keep it too.
inline constexpr double kSideEngineTipOffset = 17.0;
inline constexpr double kMainEngineYLocation = 4.0;

inline constexpr double kViewportW = 600.0;
inline constexpr double kViewportH = 400.0;
inline constexpr double kW = kViewportW / kScale;  // 20 m.
inline constexpr double kH = kViewportH / kScale;  // 13.333 m.

inline constexpr int kVelocityIterations = 6 * 30;
inline constexpr int kPositionIterations = 2 * 30;
inline constexpr double kTimeStep = 1.0 / kFps;

// Terrain: kChunks surface points, kChunks + 1 random heights.
inline constexpr int kChunks = 11;
inline constexpr double kHelipadY = kH / 4;

// Friction and density, as Gymnasium's fixture definitions (pybox2d's default
// friction is 0.2, used where Gymnasium does not set one).
inline constexpr double kDefaultFriction = 0.2;
inline constexpr double kTerrainFriction = 0.1;
inline constexpr double kBodyDensity = 5.0;
inline constexpr double kBodyFriction = 0.1;
inline constexpr double kLegDensity = 1.0;

// Engine exhaust particles (decoration only).
inline constexpr double kParticleRadius = 2.0 / kScale;
inline constexpr double kMainParticleMass = 3.5;
inline constexpr double kSideParticleMass = 0.7;
inline constexpr double kParticleFriction = 0.1;
inline constexpr double kParticleRestitution = 0.3;
inline constexpr double kParticleTtlPerFrame = 0.15;

// Wind: Gymnasium draws its index offsets with integers(-9999, 9999).
inline constexpr int kWindIndexBound = 9999;

// Reward shaping weights (Gymnasium's, plus the paper's neighbour term).
inline constexpr double kShapingDistance = 100.0;
inline constexpr double kShapingSpeed = 100.0;
inline constexpr double kShapingAngle = 100.0;
inline constexpr double kShapingLeg = 10.0;
inline constexpr double kShapingNeighbour = 30.0;
inline constexpr double kMainFuelCost = 0.30;
inline constexpr double kSideFuelCost = 0.03;

}  // namespace internal
}  // namespace mll::core

#endif  // MLL_CORE_SRC_CONSTANTS_H_

#include "mll/core/renderer.h"

#include <png.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "mll/core/env.h"

namespace mll::core {
namespace {

using ::testing::HasSubstr;

constexpr double kScale = 30.0;  // Gymnasium's pixels per meter.
constexpr double kW = 20.0;
constexpr double kH = 400.0 / kScale;
constexpr double kHelipadY = kH / 4;

using Pixel = std::array<uint8_t, 3>;

Pixel PixelAt(const Frame& frame, int x, int y) {
  const size_t i = (static_cast<size_t>(y) * frame.width + x) * 3;
  return {frame.rgb[i], frame.rgb[i + 1], frame.rgb[i + 2]};
}

Scene WorldOnly() {
  Scene scene;
  scene.width = kW;
  scene.height = kH;
  return scene;
}

// The pixel that shows world point (x, y): y up in the world, row 0 at the
// top of the frame.
Pixel WorldPixel(const Frame& frame, double x, double y) {
  const Vec2 at = WorldToFrame(WorldOnly(), {x, y});
  return PixelAt(frame, static_cast<int>(std::floor(at.x)),
                 static_cast<int>(std::floor(at.y)));
}

bool InFrame(const Vec2& world) {
  const Vec2 at = WorldToFrame(WorldOnly(), world);
  return at.x >= 0 && at.x <= kFrameWidth && at.y >= 0 && at.y <= kFrameHeight;
}

// Gymnasium's lander body polygon (pixels / SCALE) around (cx, cy).
ScenePolygon LanderBody(double cx, double cy) {
  ScenePolygon body;
  for (auto [x, y] : std::vector<std::pair<double, double>>{
           {-14, 17}, {-17, 0}, {-17, -10}, {17, -10}, {17, 0}, {14, 17}}) {
    body.vertices.push_back({cx + x / kScale, cy + y / kScale});
  }
  return body;
}

// A level terrain at the helipad height with landers at the given centres.
Scene MakeScene(const std::vector<Vec2>& lander_centres) {
  Scene scene;
  scene.width = kW;
  scene.height = kH;
  for (int i = 0; i <= 10; ++i) scene.terrain.push_back({2.0 * i, kHelipadY});
  scene.helipad_x1 = 8.0;
  scene.helipad_x2 = 12.0;
  scene.helipad_y = kHelipadY;
  for (size_t i = 0; i < lander_centres.size(); ++i) {
    SceneLander lander;
    lander.agent = static_cast<int>(i);
    lander.parts.push_back(
        LanderBody(lander_centres[i].x, lander_centres[i].y));
    scene.landers.push_back(lander);
  }
  return scene;
}

TEST(RendererTest, FrameIs600x400Rgb) {
  const Frame frame = RenderScene(MakeScene({}));
  EXPECT_EQ(frame.width, 600);
  EXPECT_EQ(frame.height, 400);
  EXPECT_EQ(frame.rgb.size(), 600u * 400u * 3u);
}

TEST(RendererTest, SkyIsBlackAndGroundIsWhite) {
  const Frame frame = RenderScene(MakeScene({}));
  EXPECT_EQ(PixelAt(frame, 60, 10), (Pixel{0, 0, 0}));  // High in the sky.
  EXPECT_EQ(PixelAt(frame, 300, 395), (Pixel{255, 255, 255}));  // Ground.
  // The terrain line is at helipad_y = H/4.
  EXPECT_EQ(WorldPixel(frame, 3.0, kHelipadY + 0.2), (Pixel{0, 0, 0}));
  EXPECT_EQ(WorldPixel(frame, 3.0, kHelipadY - 0.2), (Pixel{255, 255, 255}));
}

TEST(RendererTest, TheOutOfBoundsMarginsAreShaded) {
  const Frame frame = RenderScene(MakeScene({}));
  for (double x : {-0.5, kW + 0.5}) {
    const Pixel sky = WorldPixel(frame, x, 12.0);
    const Pixel ground = WorldPixel(frame, x, 1.0);
    EXPECT_GT(sky[0], 40) << "x = " << x;
    EXPECT_LT(ground[0], 215) << "x = " << x;
    EXPECT_GT(ground[0], sky[0]) << "x = " << x;
  }
}

TEST(RendererTest, TheViewShowsTheWholeWorldAndAMarginAboveTheSpawnRow) {
  EXPECT_TRUE(InFrame({0.0, 0.0}));
  EXPECT_TRUE(InFrame({kW, 0.0}));
  EXPECT_TRUE(InFrame({0.0, kH + kViewTopMargin}));
  EXPECT_TRUE(InFrame({-kViewMarginX, kH + kViewTopMargin}));
  EXPECT_FALSE(InFrame({kW / 2, kH + kViewTopMargin + 0.1}));
  // The same scale on both axes.
  const Vec2 origin = WorldToFrame(WorldOnly(), {0, 0});
  const Vec2 one = WorldToFrame(WorldOnly(), {1, 1});
  EXPECT_NEAR(one.x - origin.x, origin.y - one.y, 1e-9);
}

TEST(RendererTest, SkyFollowsTheTerrain) {
  Scene scene = MakeScene({});
  scene.terrain[2].y = 6.0;  // A peak at x = 4 m, 180 px up.
  const Frame frame = RenderScene(scene);
  EXPECT_EQ(WorldPixel(frame, 4.0, 5.5), (Pixel{255, 255, 255}));
  EXPECT_EQ(WorldPixel(frame, 4.0, 6.5), (Pixel{0, 0, 0}));
}

TEST(RendererTest, EachLanderIsFilledWithItsAgentColour) {
  const std::vector<Vec2> centres = {{4.0, 9.0}, {10.0, 9.0}, {16.0, 9.0}};
  const Frame frame = RenderScene(MakeScene(centres));
  for (int agent = 0; agent < 3; ++agent) {
    EXPECT_EQ(WorldPixel(frame, centres[agent].x, centres[agent].y),
              AgentColor(agent))
        << "agent " << agent;
  }
}

TEST(RendererTest, LegsAreDrawnInTheLanderColour) {
  Scene scene = MakeScene({{10.0, 9.0}});
  ScenePolygon leg;
  for (auto [x, y] : std::vector<std::pair<double, double>>{
           {12.0, 8.0}, {12.2, 8.0}, {12.2, 8.6}, {12.0, 8.6}}) {
    leg.vertices.push_back({x, y});
  }
  scene.landers[0].parts.push_back(leg);
  const Frame frame = RenderScene(scene);
  EXPECT_EQ(WorldPixel(frame, 12.1, 8.3), AgentColor(0));
}

TEST(RendererTest, WrecksAreDarker) {
  Scene scene = MakeScene({{10.0, 9.0}});
  scene.landers[0].wreck = true;
  // Below the centre, between the arms of the wreck's red cross.
  const Pixel wreck = WorldPixel(RenderScene(scene), 10.0, 8.75);
  const Pixel live = AgentColor(0);
  EXPECT_NE(wreck, live);
  for (int c = 0; c < 3; ++c) EXPECT_LT(wreck[c], live[c]) << "channel " << c;
}

TEST(RendererTest, HelipadFlagsAreYellowOnWhitePoles) {
  const Frame frame = RenderScene(MakeScene({}));
  for (double x : {8.0, 12.0}) {
    // Gymnasium: flag (x, y2), (x, y2 - 10), (x + 25, y2 - 5) px, with
    // y2 = helipad_y * SCALE + 50.
    EXPECT_EQ(WorldPixel(frame, x + 5 / kScale, kHelipadY + 45 / kScale),
              (Pixel{204, 204, 0}))
        << "flag at x = " << x;
    // The pole is light against the black sky, between ground and flag.
    const Vec2 pole = WorldToFrame(WorldOnly(), {x, kHelipadY + 20 / kScale});
    int brightest = 0;
    for (int dx = -1; dx <= 1; ++dx) {
      brightest =
          std::max<int>(brightest, PixelAt(frame, static_cast<int>(pole.x) + dx,
                                           static_cast<int>(pole.y))[0]);
    }
    EXPECT_GT(brightest, 200) << "pole at x = " << x;
  }
}

TEST(RendererTest, ParticlesFadeWithTheirTimeToLive) {
  Scene scene = MakeScene({});
  scene.particles.push_back({{5.0, 10.0}, 0.2, 1.0});   // Fresh.
  scene.particles.push_back({{15.0, 10.0}, 0.2, 0.0});  // Expiring.
  const Frame frame = RenderScene(scene);
  // Gymnasium: (max(0.2, 0.15 + ttl), max(0.2, 0.5 ttl), ...) * 255.
  const Pixel fresh = WorldPixel(frame, 5.0, 10.0);
  const Pixel old = WorldPixel(frame, 15.0, 10.0);
  EXPECT_EQ(fresh[0], 255);
  EXPECT_NEAR(fresh[1], 128, 1);
  EXPECT_NEAR(old[0], 51, 1);
  EXPECT_NEAR(old[1], 51, 1);
}

TEST(RendererTest, AgentColoursAreDistinct) {
  EXPECT_EQ(AgentColor(0), (Pixel{128, 102, 230}));
  std::set<Pixel> colours;
  for (int agent = 0; agent < kMaxLanders; ++agent) {
    const Pixel c = AgentColor(agent);
    EXPECT_NE(c, (Pixel{0, 0, 0}));
    EXPECT_NE(c, (Pixel{255, 255, 255}));
    EXPECT_NE(c, (Pixel{204, 204, 0}));
    colours.insert(c);
  }
  EXPECT_EQ(colours.size(), static_cast<size_t>(kMaxLanders));
}

TEST(RendererTest, RenderingIsRepeatableAcrossThreads) {
  const Scene scene = MakeScene({{4.0, 9.0}, {10.0, 7.0}});
  const Frame reference = RenderScene(scene);
  std::vector<Frame> frames(4);
  std::vector<std::thread> threads;
  for (Frame& frame : frames) {
    threads.emplace_back([&scene, &frame] {
      for (int i = 0; i < 20; ++i) frame = RenderScene(scene);
    });
  }
  for (std::thread& t : threads) t.join();
  for (const Frame& frame : frames) EXPECT_EQ(frame.rgb, reference.rgb);
}

std::vector<uint8_t> DecodePng(const std::string& png, int* width,
                               int* height) {
  png_image image{};
  image.version = PNG_IMAGE_VERSION;
  if (!png_image_begin_read_from_memory(&image, png.data(), png.size())) {
    ADD_FAILURE() << "libpng: " << image.message;
    return {};
  }
  image.format = PNG_FORMAT_RGB;
  std::vector<uint8_t> pixels(PNG_IMAGE_SIZE(image));
  if (!png_image_finish_read(&image, nullptr, pixels.data(), 0, nullptr)) {
    ADD_FAILURE() << "libpng: " << image.message;
    return {};
  }
  *width = static_cast<int>(image.width);
  *height = static_cast<int>(image.height);
  return pixels;
}

TEST(EncodePngTest, DecodesToTheSamePixels) {
  Scene scene = MakeScene({{4.0, 9.0}, {10.0, 7.0}, {16.0, 11.0}});
  scene.particles.push_back({{5.0, 10.0}, 0.1, 0.7});
  const Frame frame = RenderScene(scene);
  absl::StatusOr<std::string> png = EncodePng(frame);
  ASSERT_TRUE(png.ok()) << png.status();
  const std::string signature = "\x89PNG\r\n\x1a\n";
  ASSERT_GE(png->size(), signature.size());
  EXPECT_EQ(png->substr(0, signature.size()), signature);
  int width = 0, height = 0;
  EXPECT_EQ(DecodePng(*png, &width, &height), frame.rgb);
  EXPECT_EQ(width, 600);
  EXPECT_EQ(height, 400);
}

TEST(EncodePngTest, RejectsAFrameWhoseBytesDoNotMatchItsSize) {
  Frame frame;
  frame.width = 600;
  frame.height = 400;
  frame.rgb.resize(10);
  absl::StatusOr<std::string> png = EncodePng(frame);
  EXPECT_EQ(png.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_THAT(png.status().message(), HasSubstr("rgb"));
  frame.width = 0;
  EXPECT_EQ(EncodePng(frame).status().code(),
            absl::StatusCode::kInvalidArgument);
}

bool IsFlame(const Pixel& p) { return p[0] > 200 && p[1] > 90 && p[2] < 160; }

TEST(RendererTest, FlamesShowTheFiredEngines) {
  Scene scene = MakeScene({{6.0, 9.0}, {14.0, 9.0}});
  for (SceneLander& lander : scene.landers) {
    lander.position = VertexMean(lander.parts[0]);
    lander.position.y = 9.0;
  }
  scene.landers[0].main_power = 1.0;
  scene.landers[1].side_power = 1.0;
  scene.landers[1].side_direction = -1;  // Exhaust to the right (+x).
  const Frame frame = RenderScene(scene);
  // Under lander 0's body (its bottom edge is 10/30 m below the centre).
  EXPECT_TRUE(IsFlame(WorldPixel(frame, 6.0, 9.0 - 16 / kScale)));
  EXPECT_FALSE(IsFlame(WorldPixel(frame, 14.0, 9.0 - 16 / kScale)));
  // Right of lander 1's upper flank, none on its left.
  const double flank = 18 / kScale, up = 9.0 + 14 / kScale;
  EXPECT_TRUE(IsFlame(WorldPixel(frame, 14.0 + flank, up)));
  EXPECT_FALSE(IsFlame(WorldPixel(frame, 14.0 - flank, up)));
  EXPECT_FALSE(IsFlame(WorldPixel(frame, 6.0 + flank, up)));
}

int CountIn(const Frame& frame, const Vec2& world_centre, double radius,
            bool (*match)(const Pixel&)) {
  const Vec2 c = WorldToFrame(WorldOnly(), world_centre);
  const double r = radius * kFrameHeight / (kH + kViewTopMargin);
  int count = 0;
  for (int y = std::max(0, static_cast<int>(c.y - r));
       y < std::min<int>(kFrameHeight, c.y + r); ++y) {
    for (int x = std::max(0, static_cast<int>(c.x - r));
         x < std::min<int>(kFrameWidth, c.x + r); ++x) {
      count += match(PixelAt(frame, x, y));
    }
  }
  return count;
}

bool IsRed(const Pixel& p) { return p[0] > 180 && p[1] < 90 && p[2] < 90; }
bool IsGreen(const Pixel& p) { return p[1] > 160 && p[0] < 120 && p[2] < 120; }

TEST(RendererTest, RemovedLandersLeaveAMarkWhereTheirEpisodeEnded) {
  Scene scene = MakeScene({});
  scene.agents.resize(3);
  scene.agents[0].outcome = Outcome::kCrashed;
  scene.agents[0].final_parts = {LanderBody(4.0, 4.0)};
  scene.agents[1].outcome = Outcome::kLanded;
  scene.agents[1].final_parts = {LanderBody(10.0, kHelipadY + 0.5)};
  const Frame frame = RenderScene(scene);
  EXPECT_GT(CountIn(frame, {4.0, 4.0}, 0.6, IsRed), 20);  // A red cross.
  EXPECT_EQ(CountIn(frame, {4.0, 4.0}, 0.6, IsGreen), 0);
  EXPECT_GT(CountIn(frame, {10.0, kHelipadY + 0.5}, 0.6, IsGreen), 20);
  EXPECT_EQ(CountIn(frame, {10.0, kHelipadY + 0.5}, 0.6, IsRed), 0);
  // A wreck still in the world is crossed too.
  Scene wreck = MakeScene({{16.0, 9.0}});
  wreck.landers[0].wreck = true;
  EXPECT_GT(CountIn(RenderScene(wreck), {16.0, 9.0}, 0.6, IsRed), 20);
}

TEST(RendererTest, TheOverlayIsOffByDefaultAndDrawsTextWhenOn) {
  Scene scene = MakeScene({{4.0, 9.0}, {10.0, 7.0}});
  scene.agents.resize(2);
  scene.agents[1].outcome = Outcome::kLanded;
  scene.agents[1].episode_return = 123.4;
  scene.cycles = 17;
  const Frame plain = RenderScene(scene);
  EXPECT_EQ(plain.rgb, RenderScene(scene, RenderOptions()).rgb);
  RenderOptions options;
  options.overlay = true;
  options.caption = "envs/abc";
  const Frame overlay = RenderScene(scene, options);
  // Text at the bottom left, over the white ground, on dark boxes; and a
  // label above each lander.
  auto light = [](const Frame& frame, int x0, int y0, int x1, int y1) {
    int count = 0;
    for (int y = y0; y < y1; ++y) {
      for (int x = x0; x < x1; ++x) count += PixelAt(frame, x, y)[1] > 150;
    }
    return count;
  };
  auto dark = [](const Frame& frame, int x0, int y0, int x1, int y1) {
    int count = 0;
    for (int y = y0; y < y1; ++y) {
      for (int x = x0; x < x1; ++x) count += PixelAt(frame, x, y)[1] < 140;
    }
    return count;
  };
  EXPECT_EQ(dark(plain, 35, 340, 200, 400), 0);
  EXPECT_GT(dark(overlay, 35, 340, 200, 400), 1000);
  const Vec2 above = WorldToFrame(WorldOnly(), {10.0, 7.0 + 17 / kScale});
  const int x = static_cast<int>(above.x), y = static_cast<int>(above.y);
  EXPECT_GT(light(overlay, x - 8, y - 16, x + 8, y),
            light(plain, x - 8, y - 16, x + 8, y));
  // The caption changes the frame.
  options.caption = "envs/xyz";
  EXPECT_NE(RenderScene(scene, options).rgb, overlay.rgb);
}

std::unique_ptr<Env> MakeEnv(RenderMode mode, int n_landers) {
  EnvConfig config;
  config.n_landers = n_landers;
  config.render_mode = mode;
  absl::StatusOr<std::unique_ptr<Env>> env = Env::Create(config);
  EXPECT_TRUE(env.ok()) << env.status();
  return env.ok() ? std::move(*env) : nullptr;
}

ActionsView Discrete(const std::vector<int32_t>& actions) {
  ActionsView view;
  view.discrete = actions;
  return view;
}

// Fires every lander's main engine for `steps` steps.
void FireMainEngines(Env& env, int steps) {
  std::vector<int32_t> actions(env.n_landers(), 2);
  StepResult result;
  for (int i = 0; i < steps && !env.episode_over(); ++i) {
    ASSERT_TRUE(env.Step(Discrete(actions), &result).ok());
  }
}

TEST(RenderEnvTest, ParticlesExistOnlyWithARenderMode) {
  for (RenderMode mode : {RenderMode::kNone, RenderMode::kRgbArray}) {
    std::unique_ptr<Env> env = MakeEnv(mode, 2);
    ASSERT_NE(env, nullptr);
    StepResult result;
    env->Reset(7, &result);
    FireMainEngines(*env, 5);
    if (mode == RenderMode::kNone) {
      EXPECT_TRUE(env->scene().particles.empty());
    } else {
      EXPECT_FALSE(env->scene().particles.empty());
    }
  }
}

TEST(RenderEnvTest, NeedsARenderModeAndAReset) {
  std::unique_ptr<Env> plain = MakeEnv(RenderMode::kNone, 1);
  ASSERT_NE(plain, nullptr);
  StepResult result;
  plain->Reset(0, &result);
  absl::StatusOr<Frame> frame = RenderEnv(*plain);
  EXPECT_EQ(frame.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(frame.status().message(), HasSubstr("render_mode"));

  std::unique_ptr<Env> fresh = MakeEnv(RenderMode::kRgbArray, 1);
  ASSERT_NE(fresh, nullptr);
  frame = RenderEnv(*fresh);
  EXPECT_EQ(frame.status().code(), absl::StatusCode::kFailedPrecondition);
  EXPECT_THAT(frame.status().message(), HasSubstr("reset"));
}

int CountPixels(const Frame& frame, const Pixel& colour) {
  int count = 0;
  for (size_t i = 0; i < frame.rgb.size(); i += 3) {
    count += frame.rgb[i] == colour[0] && frame.rgb[i + 1] == colour[1] &&
             frame.rgb[i + 2] == colour[2];
  }
  return count;
}

TEST(RenderEnvTest, DrawsEveryLanderOfALiveEnvInItsColour) {
  std::unique_ptr<Env> env = MakeEnv(RenderMode::kRgbArray, 3);
  ASSERT_NE(env, nullptr);
  StepResult result;
  env->Reset(3, &result);
  // Right after the reset: landers spawn at the top, still in view.
  absl::StatusOr<Frame> frame = RenderEnv(*env);
  ASSERT_TRUE(frame.ok()) << frame.status();
  EXPECT_EQ(PixelAt(*frame, 300, 399), (Pixel{255, 255, 255}));
  EXPECT_GT(CountPixels(*frame, Pixel{204, 204, 0}), 100);
  const Scene scene = env->scene();
  ASSERT_EQ(scene.landers.size(), 3u);
  int checked = 0;
  for (const SceneLander& lander : scene.landers) {
    // The body is convex, so its vertex mean is inside it.
    Vec2 centre;
    const std::vector<Vec2>& body = lander.parts.at(0).vertices;
    for (const Vec2& v : body) {
      centre.x += v.x / body.size();
      centre.y += v.y / body.size();
    }
    EXPECT_EQ(WorldPixel(*frame, centre.x, centre.y), AgentColor(lander.agent))
        << "agent " << lander.agent;
    EXPECT_GT(CountPixels(*frame, AgentColor(lander.agent)), 200)
        << "agent " << lander.agent;
    ++checked;
  }
  EXPECT_EQ(checked, 3);
}

TEST(RenderEnvTest, RenderingAgesParticlesButNotTheEpisode) {
  std::unique_ptr<Env> rendered = MakeEnv(RenderMode::kRgbArray, 2);
  std::unique_ptr<Env> plain = MakeEnv(RenderMode::kNone, 2);
  ASSERT_NE(rendered, nullptr);
  ASSERT_NE(plain, nullptr);
  StepResult a, b;
  rendered->Reset(11, &a);
  plain->Reset(11, &b);
  std::vector<int32_t> actions = {2, 3};
  for (int i = 0; i < 30 && !a.episode_over; ++i) {
    ASSERT_TRUE(RenderEnv(*rendered).ok());
    ASSERT_TRUE(rendered->Step(Discrete(actions), &a).ok());
    ASSERT_TRUE(plain->Step(Discrete(actions), &b).ok());
    ASSERT_EQ(a.observations, b.observations) << "step " << i;
    ASSERT_EQ(a.rewards, b.rewards) << "step " << i;
  }
  // Particles age by 0.15 per rendered frame, so a fresh one outlives a few.
  const Scene scene = rendered->scene();
  ASSERT_FALSE(scene.particles.empty());
  for (const SceneParticle& p : scene.particles) EXPECT_GT(p.ttl, 0.0);
}

TEST(RenderEnvTest, LandersAreInFrameFromTheFirstStep) {
  for (int n : {1, 3, 8, 32}) {
    for (uint64_t seed = 0; seed < 20; ++seed) {
      std::unique_ptr<Env> env = MakeEnv(RenderMode::kNone, n);
      ASSERT_NE(env, nullptr);
      StepResult result;
      env->Reset(seed, &result);
      // The reset's frame and the next ones, engines off: the initial push
      // lifts some landers before they fall.
      const std::vector<int32_t> noop(n, 0);
      for (int step = 0; step <= 25 && !env->episode_over(); ++step) {
        for (const SceneLander& lander : env->scene().landers) {
          for (const ScenePolygon& part : lander.parts) {
            for (const Vec2& v : part.vertices) {
              ASSERT_TRUE(InFrame(v))
                  << "n " << n << " seed " << seed << " step " << step
                  << " agent " << lander.agent << " at (" << v.x << ", " << v.y
                  << ")";
            }
          }
        }
        ASSERT_TRUE(env->Step(Discrete(noop), &result).ok());
      }
    }
  }
}

TEST(RenderEnvTest, TheSceneKeepsWhereALanderWasDestroyed) {
  std::unique_ptr<Env> env = MakeEnv(RenderMode::kNone, 2);
  ASSERT_NE(env, nullptr);
  StepResult result;
  env->Reset(5, &result);
  // Lander 0 falls fast, upside down, onto the helipad.
  ASSERT_TRUE(
      env->SetLanderStateForTest(0, 10.0, kHelipadY + 0.7, M_PI, 0, -8, 0)
          .ok());
  const std::vector<int32_t> noop(2, 0);
  for (int i = 0; i < 10 && env->is_active(0); ++i) {
    ASSERT_TRUE(env->Step(Discrete(noop), &result).ok());
  }
  ASSERT_EQ(env->outcome(0), Outcome::kCrashed);
  const Scene scene = env->scene();
  ASSERT_EQ(scene.agents.size(), 2u);
  EXPECT_EQ(scene.agents[0].outcome, Outcome::kCrashed);
  ASSERT_EQ(scene.agents[0].final_parts.size(), 3u);
  const Vec2 centre = VertexMean(scene.agents[0].final_parts[0]);
  EXPECT_NEAR(centre.x, 10.0, 0.5);
  EXPECT_NEAR(centre.y, kHelipadY, 1.0);
  for (const SceneLander& lander : scene.landers) EXPECT_NE(lander.agent, 0);
  EXPECT_GT(CountIn(RenderScene(scene), centre, 0.6, IsRed), 20);
  EXPECT_EQ(scene.cycles, env->cycles());
  EXPECT_EQ(scene.agents[1].episode_return, env->episode_return(1));
}

}  // namespace
}  // namespace mll::core

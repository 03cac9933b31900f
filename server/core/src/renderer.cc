// Draws a Scene like Gymnasium's LunarLander.render() (gymnasium 1.x,
// envs/box2d/lunar_lander.py): white background, the sky above the terrain in
// black, particles coloured by their time-to-live, landers filled and
// outlined, helipad poles in white with yellow flags, and y flipped so that
// row 0 is the top of the viewport.
#include "mll/core/renderer.h"

#include <cairo.h>
#include <png.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <csetjmp>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace mll::core {
namespace {

struct Rgb {
  double r, g, b;  // 0..1 for Cairo.
};

// Gymnasium's pixels per meter (SCALE): sizes drawn in its pixels are given
// in 1/kScale m and scale with the view.
constexpr double kScale = 30.0;

// Gymnasium draws helipad flags in pixels: a 50 px pole and a 25 x 10 px flag.
constexpr double kFlagPoleHeight = 50.0 / kScale;
constexpr double kFlagLength = 25.0 / kScale;
constexpr double kFlagHeight = 10.0 / kScale;
constexpr double kPixel = 1.0 / kScale;

// Gymnasium's lander fill colour, kept for lander_0; its hue (252 degrees),
// saturation and value are shared by every agent's colour.
constexpr std::array<uint8_t, 3> kLander0Color = {128, 102, 230};
constexpr double kLanderHueDegrees = 252.0;
constexpr double kLanderSaturation = 102.0 / 230.0;  // 1 - min/max.
constexpr double kLanderValue = 230.0 / 255.0;
// Gymnasium's outline (77, 77, 128) is roughly 0.6 of the fill.
constexpr double kOutlineShade = 0.6;
// Wrecks (damaged landers kept in the world) are drawn darker.
constexpr double kWreckShade = 0.45;

constexpr std::array<uint8_t, 3> kFlagColor = {204, 204, 0};

// Outlines are 1.5 px wide: with antialiasing, a 1 px line between pixel
// centres would blur into two grey half-pixels.
constexpr double kOutlineWidth = 1.5 * kPixel;
constexpr Rgb kOutOfBoundsShade = {0.45, 0.45, 0.5};
constexpr double kOutOfBoundsAlpha = 0.45;

// Flames, in Gymnasium's pixels in the lander's frame: the main engine's
// under the body's bottom edge (y = -10), the side engines' at the height
// Gymnasium applies their impulse (14) from the body's flank.
constexpr double kMainFlameY = -10.0;
constexpr double kMainFlameLength = 26.0;
constexpr double kMainFlameHalfWidth = 6.0;
constexpr double kSideFlameX = 14.5;
constexpr double kSideFlameY = 14.0;
constexpr double kSideFlameLength = 14.0;
constexpr double kSideFlameHalfWidth = 3.5;
constexpr Rgb kFlameOuter = {1.0, 0.45, 0.1};
constexpr Rgb kFlameInner = {1.0, 0.93, 0.55};
constexpr double kFlameCore = 0.6;  // The core's size relative to the flame.

// Marks of removed landers.
constexpr double kGhostAlpha = 0.3;
constexpr Rgb kCheckColor = {0.2, 0.85, 0.3};
constexpr Rgb kWreckGrey = {0.3, 0.3, 0.3};
constexpr Rgb kCrossColor = {0.95, 0.15, 0.1};
constexpr double kCrossRadius = 8.0 * kPixel;

// The overlay, in device pixels.
constexpr double kOverlayFontSize = 12.0;
constexpr double kOverlayLineHeight = 14.0;
constexpr int kOverlayRows = 8;
constexpr double kOverlayColumnWidth = 148.0;

Rgb ToCairo(const std::array<uint8_t, 3>& c, double shade = 1.0) {
  return {c[0] * shade / 255.0, c[1] * shade / 255.0, c[2] * shade / 255.0};
}

// Reverses the 5 low bits, so that consecutive agents get hues far apart
// (0, 16, 8, 24, ... in 32 steps around the wheel).
int BitReverse5(int v) {
  int r = 0;
  for (int bit = 0; bit < 5; ++bit) r |= ((v >> bit) & 1) << (4 - bit);
  return r;
}

std::array<uint8_t, 3> HsvToRgb(double hue_degrees, double s, double v) {
  const double h = std::fmod(hue_degrees, 360.0) / 60.0;
  const double c = v * s;
  const double x = c * (1.0 - std::fabs(std::fmod(h, 2.0) - 1.0));
  const double m = v - c;
  // Which channels get the chroma c and the second component x in each 60
  // degree sector of the hue circle (the third channel is 0); sector 5 also
  // takes any hue outside [0, 300).
  constexpr int kSectorChannels[6][2] = {{0, 1}, {1, 0}, {1, 2},
                                         {2, 1}, {2, 0}, {0, 2}};
  int sector = static_cast<int>(h);
  if (sector < 0 || sector > 4) sector = 5;
  double rgb[3] = {0, 0, 0};
  rgb[kSectorChannels[sector][0]] = c;
  rgb[kSectorChannels[sector][1]] = x;
  auto to_byte = [m](double u) {
    return static_cast<uint8_t>(std::lround((u + m) * 255.0));
  };
  return {to_byte(rgb[0]), to_byte(rgb[1]), to_byte(rgb[2])};
}

// One ARGB32 surface per thread, reused across frames: creating a 600x400
// surface costs about as much as drawing it.
class ThreadCanvas {
 public:
  ThreadCanvas()
      : surface_(cairo_image_surface_create(CAIRO_FORMAT_RGB24, kFrameWidth,
                                            kFrameHeight)),
        cr_(cairo_create(surface_)) {}
  ~ThreadCanvas() {
    cairo_destroy(cr_);
    cairo_surface_destroy(surface_);
  }
  ThreadCanvas(const ThreadCanvas&) = delete;
  ThreadCanvas& operator=(const ThreadCanvas&) = delete;

  cairo_surface_t* surface() const { return surface_; }
  cairo_t* cr() const { return cr_; }

 private:
  cairo_surface_t* surface_;
  cairo_t* cr_;
};

void SetColor(cairo_t* cr, const Rgb& c, double alpha = 1.0) {
  cairo_set_source_rgba(cr, c.r, c.g, c.b, alpha);
}

void PolygonPath(cairo_t* cr, const std::vector<Vec2>& vertices) {
  if (vertices.empty()) return;
  cairo_move_to(cr, vertices[0].x, vertices[0].y);
  for (size_t i = 1; i < vertices.size(); ++i) {
    cairo_line_to(cr, vertices[i].x, vertices[i].y);
  }
  cairo_close_path(cr);
}

// All parts of a lander as one path: one fill and one stroke per lander
// instead of three each, which halves the antialiased drawing time.
void PartsPath(cairo_t* cr, const std::vector<ScenePolygon>& parts) {
  for (const ScenePolygon& part : parts) PolygonPath(cr, part.vertices);
}

// `polygon` (convex, counter-clockwise, as every Box2D polygon) with each
// edge moved `d` inwards: its outline is the band between the two.
std::vector<Vec2> Inset(const std::vector<Vec2>& polygon, double d) {
  const size_t n = polygon.size();
  std::vector<Vec2> inset;
  if (n < 3) return inset;
  inset.reserve(n);
  // Edge i runs from vertex i to i + 1; its inward (left) unit normal.
  auto normal = [&](size_t i) {
    const Vec2& a = polygon[i];
    const Vec2& b = polygon[(i + 1) % n];
    const double dx = b.x - a.x, dy = b.y - a.y;
    const double length = std::hypot(dx, dy);
    return length > 0 ? Vec2{-dy / length, dx / length} : Vec2{0, 0};
  };
  for (size_t i = 0; i < n; ++i) {
    // Vertex i joins edges i - 1 and i: move it along the bisector so that
    // both edges move by d.
    const Vec2 n0 = normal((i + n - 1) % n);
    const Vec2 n1 = normal(i);
    const double cosine = 1.0 + n0.x * n1.x + n0.y * n1.y;
    if (cosine < 1e-6) return {};
    inset.push_back({polygon[i].x + d * (n0.x + n1.x) / cosine,
                     polygon[i].y + d * (n0.y + n1.y) / cosine});
  }
  return inset;
}

// The union of Gymnasium's sky_polys: everything between the terrain line
// and the top of the view, as one path (no seams between chunks). The line
// runs on level beyond the world's edges, into the shaded margins.
void DrawSky(cairo_t* cr, const Scene& scene) {
  if (scene.terrain.empty()) return;
  const double top = scene.height + kViewTopMargin + kPixel;
  const double left = -kViewMarginX - kPixel;
  const double right = scene.width + kViewMarginX + kPixel;
  cairo_move_to(cr, left, top);
  cairo_line_to(cr, left, scene.terrain.front().y);
  for (const Vec2& p : scene.terrain) cairo_line_to(cr, p.x, p.y);
  cairo_line_to(cr, right, scene.terrain.back().y);
  cairo_line_to(cr, right, top);
  cairo_close_path(cr);
  SetColor(cr, {0, 0, 0});
  cairo_fill(cr);
}

// Grey over the strips beyond x = 0 and x = W: a lander there is out of
// bounds.
void DrawOutOfBounds(cairo_t* cr, const Scene& scene) {
  const double top = scene.height + kViewTopMargin + kPixel;
  cairo_rectangle(cr, -kViewMarginX - kPixel, -kPixel, kViewMarginX + kPixel,
                  top + kPixel);
  cairo_rectangle(cr, scene.width, -kPixel, kViewMarginX + kPixel,
                  top + kPixel);
  SetColor(cr, kOutOfBoundsShade, kOutOfBoundsAlpha);
  cairo_fill(cr);
}

// Gymnasium's particle colour: (max(0.2, 0.15 + ttl), max(0.2, 0.5 ttl),
// max(0.2, 0.5 ttl)). Particles of one colour are filled as one path.
void DrawParticles(cairo_t* cr, const Scene& scene) {
  if (scene.particles.empty()) return;
  std::vector<const SceneParticle*> sorted;
  sorted.reserve(scene.particles.size());
  for (const SceneParticle& p : scene.particles) sorted.push_back(&p);
  std::sort(sorted.begin(), sorted.end(),
            [](const SceneParticle* a, const SceneParticle* b) {
              return a->ttl < b->ttl;
            });
  auto colour = [](double ttl) -> Rgb {
    const double gb = std::clamp(0.5 * ttl, 0.2, 1.0);
    return {std::clamp(0.15 + ttl, 0.2, 1.0), gb, gb};
  };
  size_t i = 0;
  while (i < sorted.size()) {
    const Rgb c = colour(sorted[i]->ttl);
    size_t j = i;
    for (; j < sorted.size(); ++j) {
      const Rgb d = colour(sorted[j]->ttl);
      if (d.r != c.r || d.g != c.g) break;
      // A particle's disc is about 3 px across: drawn as a square, it looks
      // the same and costs a fraction of an arc's curves.
      const SceneParticle& p = *sorted[j];
      cairo_rectangle(cr, p.position.x - p.radius, p.position.y - p.radius,
                      2 * p.radius, 2 * p.radius);
    }
    SetColor(cr, c);
    cairo_fill(cr);
    i = j;
  }
}

// Flames in the lander's own frame, in Gymnasium's pixels (1/SCALE m):
// the main engine under the body, growing with its power, and the side
// engine firing sideways from the upper flank (the exhaust of engine
// direction d leaves towards -d). Adds them to the current path, scaled by
// `size` (1 for the flame, less for its bright core).
void FlamePath(cairo_t* cr, const SceneLander& lander, double size) {
  if (lander.main_power <= 0.0 && lander.side_power <= 0.0) return;
  cairo_save(cr);
  cairo_translate(cr, lander.position.x, lander.position.y);
  cairo_rotate(cr, lander.angle);
  cairo_scale(cr, kPixel, kPixel);
  auto tongue = [cr, size](double length, double half_width) {
    // Along -y from the origin.
    length *= size;
    half_width *= size;
    cairo_move_to(cr, -half_width, 0.0);
    cairo_curve_to(cr, -half_width, -0.5 * length, -0.2 * half_width,
                   -0.8 * length, 0.0, -length);
    cairo_curve_to(cr, 0.2 * half_width, -0.8 * length, half_width,
                   -0.5 * length, half_width, 0.0);
    cairo_close_path(cr);
  };
  if (lander.main_power > 0.0) {
    cairo_save(cr);
    cairo_translate(cr, 0.0, kMainFlameY);
    tongue(kMainFlameLength * lander.main_power, kMainFlameHalfWidth);
    cairo_restore(cr);
  }
  if (lander.side_power > 0.0 && lander.side_direction != 0) {
    cairo_save(cr);
    const double d = lander.side_direction;
    cairo_translate(cr, -d * kSideFlameX, kSideFlameY);
    cairo_rotate(cr, -d * M_PI / 2);  // -y turned towards -d x.
    tongue(kSideFlameLength * lander.side_power, kSideFlameHalfWidth);
    cairo_restore(cr);
  }
  cairo_restore(cr);
}

// Every lander's flames: two fills in all (flame, then core).
void DrawFlames(cairo_t* cr, const Scene& scene) {
  for (const SceneLander& lander : scene.landers) FlamePath(cr, lander, 1.0);
  SetColor(cr, kFlameOuter);
  cairo_fill(cr);
  for (const SceneLander& lander : scene.landers) {
    FlamePath(cr, lander, kFlameCore);
  }
  SetColor(cr, kFlameInner);
  cairo_fill(cr);
}

// Where landers were removed: a landed one leaves a faint ghost with a
// green check mark; a destroyed one a dark wreck (crossed by DrawCrosses).
void DrawMarks(cairo_t* cr, const Scene& scene) {
  for (size_t agent = 0; agent < scene.agents.size(); ++agent) {
    const SceneAgent& status = scene.agents[agent];
    if (status.final_parts.empty()) continue;
    const Rgb colour = ToCairo(AgentColor(static_cast<int>(agent)));
    PartsPath(cr, status.final_parts);
    if (status.outcome == Outcome::kLanded) {
      const Vec2 centre = VertexMean(status.final_parts.front());
      SetColor(cr, colour, kGhostAlpha);
      cairo_fill_preserve(cr);
      SetColor(cr, colour);
      cairo_stroke(cr);
      cairo_move_to(cr, centre.x - 6 * kPixel, centre.y);
      cairo_line_to(cr, centre.x - 2 * kPixel, centre.y - 5 * kPixel);
      cairo_line_to(cr, centre.x + 7 * kPixel, centre.y + 6 * kPixel);
      cairo_set_line_width(cr, 3 * kPixel);
      SetColor(cr, kCheckColor);
      cairo_stroke(cr);
      cairo_set_line_width(cr, kOutlineWidth);
    } else {
      SetColor(cr, kWreckGrey);
      cairo_fill_preserve(cr);
      SetColor(cr, colour, 0.8);
      cairo_stroke(cr);
    }
  }
}

void DrawLanders(cairo_t* cr, const Scene& scene) {
  DrawFlames(cr, scene);
  for (const SceneLander& lander : scene.landers) {
    const std::array<uint8_t, 3> color = AgentColor(lander.agent);
    const double shade = lander.wreck ? kWreckShade : 1.0;
    // The outline colour over the whole part, then the fill colour inset:
    // two fills cost half of a fill and a stroke.
    PartsPath(cr, lander.parts);
    SetColor(cr, ToCairo(color, shade * kOutlineShade));
    cairo_fill(cr);
    for (const ScenePolygon& part : lander.parts) {
      PolygonPath(cr, Inset(part.vertices, kOutlineWidth));
    }
    SetColor(cr, ToCairo(color, shade));
    cairo_fill(cr);
  }
}

// A red cross on every destroyed lander, wrecks in the world and marks of
// removed ones alike, as one stroke.
void DrawCrosses(cairo_t* cr, const Scene& scene) {
  std::vector<Vec2> centres;
  for (const SceneAgent& status : scene.agents) {
    if (!status.final_parts.empty() && status.outcome != Outcome::kLanded) {
      centres.push_back(VertexMean(status.final_parts.front()));
    }
  }
  for (const SceneLander& lander : scene.landers) {
    if (lander.wreck && !lander.parts.empty()) {
      centres.push_back(VertexMean(lander.parts.front()));
    }
  }
  if (centres.empty()) return;
  const double r = kCrossRadius;
  for (const Vec2& at : centres) {
    cairo_move_to(cr, at.x - r, at.y - r);
    cairo_line_to(cr, at.x + r, at.y + r);
    cairo_move_to(cr, at.x - r, at.y + r);
    cairo_line_to(cr, at.x + r, at.y - r);
  }
  cairo_set_line_width(cr, 3 * kPixel);
  SetColor(cr, kCrossColor);
  cairo_stroke(cr);
  cairo_set_line_width(cr, kOutlineWidth);
}

void DrawFlags(cairo_t* cr, const Scene& scene) {
  for (double x : {scene.helipad_x1, scene.helipad_x2}) {
    const double y1 = scene.helipad_y;
    const double y2 = y1 + kFlagPoleHeight;
    // pygame's 1 px line covers the pixel column right of x.
    cairo_rectangle(cr, x, y1, kPixel, y2 - y1);
    SetColor(cr, {1, 1, 1});
    cairo_fill(cr);
    cairo_move_to(cr, x, y2);
    cairo_line_to(cr, x, y2 - kFlagHeight);
    cairo_line_to(cr, x + kFlagLength, y2 - kFlagHeight / 2);
    cairo_close_path(cr);
    SetColor(cr, ToCairo(kFlagColor));
    cairo_fill(cr);
  }
}

// Text at device position (x, y) (its baseline's left end) on a dark box,
// so that it reads over sky and ground alike. cairo_show_text draws from
// Cairo's glyph cache; stroking a halo around text paths cost 5 ms a frame.
void DrawText(cairo_t* cr, double x, double y, const std::string& text,
              const Rgb& colour) {
  cairo_text_extents_t extents;
  cairo_text_extents(cr, text.c_str(), &extents);
  cairo_rectangle(cr, x - 2, y - kOverlayFontSize + 1, extents.x_advance + 4,
                  kOverlayLineHeight);
  SetColor(cr, {0, 0, 0}, 0.6);
  cairo_fill(cr);
  cairo_move_to(cr, x, y);
  SetColor(cr, colour);
  cairo_show_text(cr, text.c_str());
}

std::string FormatReturn(double value) {
  char text[32];
  std::snprintf(text, sizeof(text), "%+.1f", value);
  return text;
}

// The overlay, in device pixels: the caption and step at the top left, a
// table of the agents (id, return, outcome) below it, and each lander's id
// above it (or above the place where it was removed).
void DrawOverlay(cairo_t* cr, const Scene& scene,
                 const RenderOptions& options) {
  cairo_save(cr);
  cairo_identity_matrix(cr);
  cairo_select_font_face(cr, "DejaVu Sans Mono", CAIRO_FONT_SLANT_NORMAL,
                         CAIRO_FONT_WEIGHT_BOLD);
  cairo_set_font_size(cr, kOverlayFontSize);
  // At the bottom left, over the ground, where landers seldom are: the
  // caption and step on the last line, the agents' table above it.
  const double bottom = kFrameHeight - 5;
  std::string head = options.caption.empty()
                         ? std::string()
                         : absl::StrCat(options.caption, "  ");
  absl::StrAppend(&head, "step ", scene.cycles);
  DrawText(cr, 6, bottom, head, {1, 1, 1});

  // Columns of up to kOverlayRows agents each, lander 0 at the top left.
  const int n = static_cast<int>(scene.agents.size());
  const int rows = std::min(n, kOverlayRows);
  for (int agent = 0; agent < n; ++agent) {
    const SceneAgent& status = scene.agents[agent];
    const int column = agent / kOverlayRows;
    const int row = agent % kOverlayRows;
    const double x = 6 + column * kOverlayColumnWidth;
    const double line = bottom - kOverlayLineHeight * (rows - row) - 2;
    std::string text =
        absl::StrCat(agent, " ", FormatReturn(status.episode_return));
    if (status.outcome != Outcome::kNone) {
      absl::StrAppend(&text, " ", OutcomeName(status.outcome));
    }
    DrawText(cr, x, line, text, ToCairo(AgentColor(agent)));
  }

  // Ids beside the landers, and on the marks of removed ones.
  auto label = [&](int agent, const Vec2& world_top) {
    const Vec2 at = WorldToFrame(scene, world_top);
    const std::string id = absl::StrCat(agent);
    cairo_text_extents_t extents;
    cairo_text_extents(cr, id.c_str(), &extents);
    const double x = std::clamp(at.x - extents.x_advance / 2, 1.0,
                                kFrameWidth - extents.x_advance - 1);
    const double y = std::clamp(at.y - 4, kOverlayFontSize, kFrameHeight - 2.0);
    DrawText(cr, x, y, id, ToCairo(AgentColor(agent)));
  };
  auto top_of = [](const std::vector<ScenePolygon>& parts) {
    Vec2 top = {0.0, -1e9};
    double sum_x = 0;
    int count = 0;
    for (const ScenePolygon& part : parts) {
      for (const Vec2& v : part.vertices) {
        top.y = std::max(top.y, v.y);
        sum_x += v.x;
        ++count;
      }
    }
    top.x = count > 0 ? sum_x / count : 0.0;
    return top;
  };
  for (const SceneLander& lander : scene.landers) {
    label(lander.agent, top_of(lander.parts));
  }
  for (size_t agent = 0; agent < scene.agents.size(); ++agent) {
    if (scene.agents[agent].final_parts.empty()) continue;
    label(static_cast<int>(agent), top_of(scene.agents[agent].final_parts));
  }
  cairo_restore(cr);
}

// Cairo's RGB24 pixels are native-endian 0x00RRGGBB words; the frame wants
// packed R, G, B bytes.
void CopyToRgb(cairo_surface_t* surface, uint8_t* out) {
  cairo_surface_flush(surface);
  const uint8_t* data = cairo_image_surface_get_data(surface);
  const int stride = cairo_image_surface_get_stride(surface);
  for (int y = 0; y < kFrameHeight; ++y) {
    const uint8_t* row = data + static_cast<size_t>(y) * stride;
    for (int x = 0; x < kFrameWidth; ++x) {
      uint32_t pixel;
      std::memcpy(&pixel, row + 4 * x, sizeof(pixel));
      out[0] = static_cast<uint8_t>(pixel >> 16);
      out[1] = static_cast<uint8_t>(pixel >> 8);
      out[2] = static_cast<uint8_t>(pixel);
      out += 3;
    }
  }
}

// libpng reports errors by longjmp; this is the sink for its output.
void AppendPngBytes(png_structp png, png_bytep data, png_size_t length) {
  auto* out = static_cast<std::string*>(png_get_io_ptr(png));
  out->append(reinterpret_cast<const char*>(data), length);
}

}  // namespace

std::array<uint8_t, 3> AgentColor(int agent) {
  if (agent == 0) return kLander0Color;
  // 32 hues 11.25 degrees apart at Gymnasium's saturation and value: at least
  // about 24 steps apart in one channel, so no two agents share a colour.
  const double hue = kLanderHueDegrees + 360.0 * BitReverse5(agent & 31) / 32.0;
  return HsvToRgb(hue, kLanderSaturation, kLanderValue);
}

Vec2 VertexMean(const ScenePolygon& polygon) {
  Vec2 c;
  for (const Vec2& v : polygon.vertices) {
    c.x += v.x / polygon.vertices.size();
    c.y += v.y / polygon.vertices.size();
  }
  return c;
}

Vec2 WorldToFrame(const Scene& scene, const Vec2& world) {
  const double scale = kFrameHeight / (scene.height + kViewTopMargin);
  return {(world.x + kViewMarginX) * scale, kFrameHeight - world.y * scale};
}

Frame RenderScene(const Scene& scene, const RenderOptions& options) {
  thread_local ThreadCanvas canvas;
  cairo_t* cr = canvas.cr();

  cairo_save(cr);
  SetColor(cr, {1, 1, 1});
  cairo_paint(cr);

  // World meters to pixels, y up (Gymnasium flips the surface at the end).
  const double scale = kFrameHeight / (scene.height + kViewTopMargin);
  cairo_translate(cr, kViewMarginX * scale, kFrameHeight);
  cairo_scale(cr, scale, -scale);
  cairo_set_line_width(cr, kOutlineWidth);
  cairo_set_line_join(cr, CAIRO_LINE_JOIN_ROUND);
  // Everything antialiased (as Gymnasium's gfxdraw.aapolygon) but the
  // particles, a few pixels each, which pygame draws without it too. Cairo's
  // FAST antialiasing samples fewer points per pixel than its DEFAULT: the
  // edges look the same at this scale and a frame costs half as much
  // (docs/benchmarks.md, Core).
  cairo_set_antialias(cr, CAIRO_ANTIALIAS_FAST);
  DrawSky(cr, scene);
  DrawOutOfBounds(cr, scene);
  DrawMarks(cr, scene);
  cairo_set_antialias(cr, CAIRO_ANTIALIAS_NONE);
  DrawParticles(cr, scene);
  cairo_set_antialias(cr, CAIRO_ANTIALIAS_FAST);
  DrawLanders(cr, scene);
  DrawCrosses(cr, scene);
  DrawFlags(cr, scene);
  if (options.overlay) DrawOverlay(cr, scene, options);
  cairo_restore(cr);

  Frame frame;
  frame.width = kFrameWidth;
  frame.height = kFrameHeight;
  frame.rgb.resize(static_cast<size_t>(kFrameWidth) * kFrameHeight * 3);
  CopyToRgb(canvas.surface(), frame.rgb.data());
  return frame;
}

absl::StatusOr<Frame> RenderEnv(Env& env, const RenderOptions& options) {
  if (env.config().render_mode == RenderMode::kNone) {
    return absl::FailedPreconditionError(
        "render_mode is \"none\"; create the env with render_mode "
        "\"rgb_array\" to render it");
  }
  if (!env.episode_started()) {
    return absl::FailedPreconditionError(
        "the env has not been reset; call Reset before rendering");
  }
  env.AgeParticlesForFrame();
  return RenderScene(env.scene(), options);
}

absl::StatusOr<std::string> EncodePng(const Frame& frame) {
  if (frame.width <= 0 || frame.height <= 0) {
    return absl::InvalidArgumentError(
        absl::StrCat("frame size is ", frame.width, "x", frame.height,
                     "; width and height must be >= 1"));
  }
  const size_t row_bytes = static_cast<size_t>(frame.width) * 3;
  if (frame.rgb.size() != row_bytes * frame.height) {
    return absl::InvalidArgumentError(absl::StrCat(
        "frame.rgb has ", frame.rgb.size(), " bytes; a ", frame.width, "x",
        frame.height, " RGB frame needs ", row_bytes * frame.height));
  }

  png_structp png =
      png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
  if (png == nullptr) {
    return absl::ResourceExhaustedError("png_create_write_struct failed");
  }
  png_infop info = png_create_info_struct(png);
  if (info == nullptr) {
    png_destroy_write_struct(&png, nullptr);
    return absl::ResourceExhaustedError("png_create_info_struct failed");
  }
  std::string out;
  out.reserve(64 * 1024);
  // Everything that can longjmp lives between setjmp and the destroy below;
  // no object with a destructor is created in between.
  std::vector<png_bytep> rows(frame.height);
  for (int y = 0; y < frame.height; ++y) {
    rows[y] = const_cast<png_bytep>(frame.rgb.data() + row_bytes * y);
  }
  if (setjmp(png_jmpbuf(png))) {
    png_destroy_write_struct(&png, &info);
    return absl::InternalError("libpng failed to encode the frame");
  }
  png_set_write_fn(png, &out, AppendPngBytes, nullptr);
  png_set_IHDR(png, info, frame.width, frame.height, 8, PNG_COLOR_TYPE_RGB,
               PNG_INTERLACE_NONE, PNG_COMPRESSION_TYPE_DEFAULT,
               PNG_FILTER_TYPE_DEFAULT);
  // Frames are large flat areas: zlib's fastest level without row filters
  // encodes in about a seventh of the time of libpng's defaults at a similar
  // size (docs/benchmarks.md, Core).
  png_set_compression_level(png, 1);
  png_set_filter(png, PNG_FILTER_TYPE_BASE, PNG_FILTER_NONE);
  png_set_rows(png, info, rows.data());
  png_write_png(png, info, PNG_TRANSFORM_IDENTITY, nullptr);
  png_destroy_write_struct(&png, &info);
  return out;
}

}  // namespace mll::core

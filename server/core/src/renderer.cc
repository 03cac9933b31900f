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
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "absl/status/status.h"
#include "absl/strings/str_cat.h"

namespace mll {
namespace {

// Pixels per meter, as Gymnasium's SCALE.
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

struct Rgb {
  double r, g, b;  // 0..1 for Cairo.
};

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
  double r = 0, g = 0, b = 0;
  switch (static_cast<int>(h)) {
    case 0: r = c, g = x; break;
    case 1: r = x, g = c; break;
    case 2: g = c, b = x; break;
    case 3: g = x, b = c; break;
    case 4: r = x, b = c; break;
    default: r = c, b = x; break;
  }
  auto to_byte = [m](double u) {
    return static_cast<uint8_t>(std::lround((u + m) * 255.0));
  };
  return {to_byte(r), to_byte(g), to_byte(b)};
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

void SetColor(cairo_t* cr, const Rgb& c) {
  cairo_set_source_rgb(cr, c.r, c.g, c.b);
}

void PolygonPath(cairo_t* cr, const std::vector<Vec2>& vertices) {
  if (vertices.empty()) return;
  cairo_move_to(cr, vertices[0].x, vertices[0].y);
  for (size_t i = 1; i < vertices.size(); ++i) {
    cairo_line_to(cr, vertices[i].x, vertices[i].y);
  }
  cairo_close_path(cr);
}

// The union of Gymnasium's sky_polys: everything between the terrain line
// and the top of the viewport, as one path (no seams between chunks).
void DrawSky(cairo_t* cr, const Scene& scene) {
  if (scene.terrain.empty()) return;
  cairo_move_to(cr, scene.terrain.front().x, scene.height);
  for (const Vec2& p : scene.terrain) cairo_line_to(cr, p.x, p.y);
  cairo_line_to(cr, scene.terrain.back().x, scene.height);
  cairo_close_path(cr);
  SetColor(cr, {0, 0, 0});
  cairo_fill(cr);
}

// Gymnasium's particle colour: (max(0.2, 0.15 + ttl), max(0.2, 0.5 ttl),
// max(0.2, 0.5 ttl)).
void DrawParticles(cairo_t* cr, const Scene& scene) {
  for (const SceneParticle& p : scene.particles) {
    const double r = std::clamp(0.15 + p.ttl, 0.2, 1.0);
    const double gb = std::clamp(0.5 * p.ttl, 0.2, 1.0);
    cairo_new_sub_path(cr);
    cairo_arc(cr, p.position.x, p.position.y, p.radius, 0.0, 2.0 * M_PI);
    SetColor(cr, {r, gb, gb});
    cairo_fill(cr);
  }
}

void DrawLanders(cairo_t* cr, const Scene& scene) {
  for (const SceneLander& lander : scene.landers) {
    const std::array<uint8_t, 3> color = AgentColor(lander.agent);
    const double shade = lander.wreck ? kWreckShade : 1.0;
    const Rgb fill = ToCairo(color, shade);
    const Rgb outline = ToCairo(color, shade * kOutlineShade);
    for (const ScenePolygon& part : lander.parts) {
      PolygonPath(cr, part.vertices);
      SetColor(cr, fill);
      cairo_fill_preserve(cr);
      SetColor(cr, outline);
      cairo_stroke(cr);
    }
  }
}

void DrawFlags(cairo_t* cr, const Scene& scene) {
  for (double x : {scene.helipad_x1, scene.helipad_x2}) {
    const double y1 = scene.helipad_y;
    const double y2 = y1 + kFlagPoleHeight;
    // pygame's 1 px line covers the pixel column right of x; a stroked
    // line centred on x would smear over two columns in grey.
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

Frame RenderScene(const Scene& scene) {
  thread_local ThreadCanvas canvas;
  cairo_t* cr = canvas.cr();

  cairo_identity_matrix(cr);
  SetColor(cr, {1, 1, 1});
  cairo_paint(cr);

  // World meters to pixels, y up (Gymnasium flips the surface at the end).
  cairo_translate(cr, 0.0, kFrameHeight);
  cairo_scale(cr, kScale, -kScale);
  cairo_set_line_width(cr, kPixel);
  // Only the sky (one large polygon: a smooth terrain line) is antialiased.
  // Antialiased landers, as Gymnasium's gfxdraw.aapolygon, cost about 10 us
  // per part with its outline: 1.9 ms for 32 landers instead of 0.8 ms
  // (docs/benchmarks.md, Core), over the 1 ms budget. Gymnasium draws
  // particles without antialiasing too (pygame.draw.circle).
  cairo_set_antialias(cr, CAIRO_ANTIALIAS_DEFAULT);
  DrawSky(cr, scene);
  cairo_set_antialias(cr, CAIRO_ANTIALIAS_NONE);
  DrawParticles(cr, scene);
  DrawLanders(cr, scene);
  DrawFlags(cr, scene);

  Frame frame;
  frame.width = kFrameWidth;
  frame.height = kFrameHeight;
  frame.rgb.resize(static_cast<size_t>(kFrameWidth) * kFrameHeight * 3);
  CopyToRgb(canvas.surface(), frame.rgb.data());
  return frame;
}

absl::StatusOr<Frame> RenderEnv(Env& env) {
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
  return RenderScene(env.scene());
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

}  // namespace mll

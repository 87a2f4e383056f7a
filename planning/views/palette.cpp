#include "planning/views/palette.hpp"

#include <algorithm>
#include <cmath>

#include "foundation/error.hpp"

namespace crepuscular::planning {

Palette parse_palette(const std::string& text) {
  if (text == "default") return Palette::kDefault;
  if (text == "colorblind" || text == "colourblind") return Palette::kColorblind;
  throw Error("unknown palette \"" + text + "\" (expected default or colorblind)");
}

Rgb mix(const Rgb& a, const Rgb& b, double t) {
  Rgb r;
  for (int c = 0; c < 3; ++c)
    r[size_t(c)] = uint8_t(std::lround(a[size_t(c)] + t * (b[size_t(c)] - a[size_t(c)])));
  return r;
}

std::array<Rgb, 3> class_colours(Palette palette) {
  if (palette == Palette::kColorblind) {
    // Blue (safe) to yellow (dangerous), told apart by every common colour vision deficiency.
    const Rgb blue{0, 114, 178}, yellow{240, 228, 66};
    return {blue, mix(blue, yellow, 0.5), yellow};
  }
  return {Rgb{0, 200, 0}, Rgb{255, 220, 0}, Rgb{230, 0, 0}};
}

Rgb leeway_colour(Palette palette, double leeway) {
  const auto c = class_colours(palette);
  const double t = std::clamp(leeway, 0.0, 1.0);
  return t >= 0.5 ? mix(c[1], c[0], (t - 0.5) * 2.0) : mix(c[2], c[1], t * 2.0);
}

}  // namespace crepuscular::planning

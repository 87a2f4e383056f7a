// Colours of the path safety classes, shared by the slice views and the overlay: the default
// green / yellow / red, and a colour-blind palette (blue to yellow).
#pragma once

#include <array>
#include <cstdint>
#include <string>

namespace crepuscular::planning {

enum class Palette { kDefault, kColorblind };

// "default", "colorblind" (or "colourblind"); throws Error otherwise.
Palette parse_palette(const std::string& text);

using Rgb = std::array<uint8_t, 3>;
// Colours (RGB) of the palette for safe, medium, dangerous.
std::array<Rgb, 3> class_colours(Palette palette);
// Colour of a leeway in [0, 1]: dangerous colour at 0, medium at 0.5, safe at 1 (linear between).
Rgb leeway_colour(Palette palette, double leeway);
// a + t (b - a), rounded per channel.
Rgb mix(const Rgb& a, const Rgb& b, double t);

}  // namespace crepuscular::planning

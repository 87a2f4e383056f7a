// Names of the enums that the commands take as flags, for enum_names() (commands.hpp). Defined in
// enum_names.cpp, so a command needs no module header for them.
#pragma once

#include <map>
#include <string>

namespace crepuscular::planning {
enum class Device;
enum class Mode;
enum class Palette;
enum class SlicePlaneKind;
}  // namespace crepuscular::planning
namespace crepuscular::overlay {
enum class GuidanceLayer;
}  // namespace crepuscular::overlay

namespace crepuscular::apps {

const std::map<std::string, planning::Device>& device_names();    // auto, cpu, cuda
const std::map<std::string, planning::Mode>& mode_names();        // exact, fast
const std::map<std::string, planning::Palette>& palette_names();  // default, colo(u)rblind
const std::map<std::string, planning::SlicePlaneKind>& plane_names();
// rays, volume, entry, tumor, needle, status, and their keys 1-6.
const std::map<std::string, overlay::GuidanceLayer>& guidance_layer_names();

}  // namespace crepuscular::apps

// Names of the enums that the commands take as flags.
#include "apps/enum_names.hpp"

#include "apps/commands.hpp"
#include "foundation/error.hpp"
#include "overlay/guidance.hpp"
#include "planning/safety/path_safety.hpp"
#include "planning/views/palette.hpp"
#include "planning/views/slices.hpp"

namespace crepuscular::apps {

const std::map<std::string, planning::Device>& device_names() {
  static const std::map<std::string, planning::Device> names = {{"auto", planning::Device::kAuto},
                                                                {"cpu", planning::Device::kCpu},
                                                                {"cuda", planning::Device::kCuda}};
  return names;
}

const std::map<std::string, planning::Mode>& mode_names() {
  static const std::map<std::string, planning::Mode> names = {{"exact", planning::Mode::kExact},
                                                              {"fast", planning::Mode::kFast}};
  return names;
}

const std::map<std::string, planning::Palette>& palette_names() {
  static const std::map<std::string, planning::Palette> names = {
      {"default", planning::Palette::kDefault},
      {"colorblind", planning::Palette::kColorblind},
      {"colourblind", planning::Palette::kColorblind}};
  return names;
}

const std::map<std::string, planning::SlicePlaneKind>& plane_names() {
  static const std::map<std::string, planning::SlicePlaneKind> names = {
      {"axial", planning::SlicePlaneKind::kAxial},
      {"coronal", planning::SlicePlaneKind::kCoronal},
      {"sagittal", planning::SlicePlaneKind::kSagittal},
      {"oblique", planning::SlicePlaneKind::kOblique}};
  return names;
}

const std::map<std::string, overlay::GuidanceLayer>& guidance_layer_names() {
  static const std::map<std::string, overlay::GuidanceLayer> names = [] {
    std::map<std::string, overlay::GuidanceLayer> m;
    for (int i = 0; i < overlay::kGuidanceLayerCount; ++i) {
      const auto layer = static_cast<overlay::GuidanceLayer>(i);
      m[overlay::guidance_layer_name(layer)] = m[std::to_string(i + 1)] = layer;
    }
    return m;
  }();
  return names;
}

CLI::Validator safety_class_list() {
  return CLI::Validator(
      [](std::string& text) -> std::string {
        try {
          planning::parse_hidden_classes(text);
        } catch (const Error& e) {
          return e.what();
        }
        return {};
      },
      "CLASSES");
}

}  // namespace crepuscular::apps

// `crepuscular phantom`: writes the built-in phantom abdomen (CT, labels, tumor, vulnerability
// table), the default demo data.
#include <spdlog/spdlog.h>

#include <Eigen/Core>
#include <array>
#include <chrono>
#include <cmath>
#include <map>
#include <memory>
#include <sstream>
#include <string>

#include "apps/commands.hpp"
#include "planning/phantom.hpp"

namespace crepuscular::apps {

namespace {

constexpr double kPi = 3.14159265358979323846;

void log_summary(const planning::Phantom& ph) {
  const planning::ImageGeometry& g = ph.labels.geometry();
  spdlog::info("phantom: {}x{}x{} voxels of {} mm, origin ({:.1f}, {:.1f}, {:.1f}) LPS mm",
               g.dims[0], g.dims[1], g.dims[2], g.spacing.x(), g.origin.x(), g.origin.y(),
               g.origin.z());

  int64_t tumor = 0;
  Eigen::Vector3d centroid = Eigen::Vector3d::Zero();
  std::array<int64_t, 256> counts{};
  for (int64_t k = 0; k < g.dims[2]; ++k) {
    for (int64_t j = 0; j < g.dims[1]; ++j) {
      for (int64_t i = 0; i < g.dims[0]; ++i) {
        const int64_t n = g.offset(i, j, k);
        ++counts[ph.labels[n]];
        if (ph.tumor[n]) {
          ++tumor;
          centroid += g.index_to_physical(i, j, k);
        }
      }
    }
  }
  if (tumor > 0) centroid /= double(tumor);
  const double volume = double(tumor) * g.voxel_volume_mm3();
  spdlog::info(
      "phantom: tumor {} voxels, {:.0f} mm3, equivalent diameter {:.1f} mm, centroid ({:.1f}, "
      "{:.1f}, {:.1f}) LPS mm",
      tumor, volume, std::cbrt(6.0 * volume / kPi), centroid.x(), centroid.y(), centroid.z());

  std::map<int, std::string> names = {{0, "air"}};
  for (const auto& l : ph.vulnerability.at("labels")) {
    names[l.at("value").get<int>()] = l.at("name").get<std::string>();
  }
  std::ostringstream line;
  for (int v = 0; v < 256; ++v) {
    if (counts[size_t(v)] == 0) continue;
    const auto it = names.find(v);
    line << (line.tellp() > 0 ? ", " : "") << v << " "
         << (it != names.end() ? it->second : std::string("?")) << " " << counts[size_t(v)];
  }
  spdlog::info("phantom: voxels per label: {}", line.str());
}

}  // namespace

void add_phantom_command(CLI::App& app) {
  auto out = std::make_shared<std::string>();
  auto options = std::make_shared<planning::PhantomOptions>();
  CLI::App* cmd = app.add_subcommand(
      "phantom",
      "Generate the built-in phantom, the default demo data: a procedural abdomen in LPS mm\n"
      "(about 360 x 260 x 240 mm, centred on (0,0,0)) with skin and fat, the muscle wall, back\n"
      "muscles and psoas, ribs and spine, aorta and vena cava, lungs above the diaphragm, a liver\n"
      "in the patient's right upper abdomen with a random branching vessel tree, kidneys, spleen,\n"
      "gallbladder, bowel loops with gas, and a 25 mm tumor in the lateral right liver lobe that\n"
      "has both safe (lateral) and unsafe (vessels, vena cava, ribs, spine) straight approaches.\n"
      "\n"
      "Writes into DIR (created if missing):\n"
      "  ct.nii.gz           CT values in HU (int16), with mild noise\n"
      "  labels.nii.gz       label map (uint8): 0 air, 1 fat, 2 muscle, 3 bone, 4 aorta,\n"
      "                      5 vena cava, 6 liver (tumor included), 7 liver vessels, 8 kidneys,\n"
      "                      9 lungs, 10 bowel, 11 spleen, 12 gallbladder\n"
      "  tumor.nii.gz        tumor mask (uint8, 0/1)\n"
      "  vulnerability.json  the vulnerability table of these labels (same as --preset phantom)\n"
      "\n"
      "The same --spacing and --seed always give the same files; the geometry is defined in mm,\n"
      "so it looks the same at any spacing. Next step:\n"
      "  crepuscular plan --labels DIR/labels.nii.gz --tumor DIR/tumor.nii.gz --preset phantom");
  cmd->add_option("--out", *out, "Output folder (DIR)")->required();
  cmd->add_option("--spacing", options->spacing_mm,
                  "Isotropic voxel size in mm, 0.3 to 10 (1 mm: ~22 M voxels)")
      ->capture_default_str();
  cmd->add_option("--seed", options->seed,
                  "Random seed: changes the liver vessel tree, the bowel and the CT noise")
      ->capture_default_str()
      ->check(CLI::NonNegativeNumber);
  cmd->callback([out, options] {
    const auto t0 = std::chrono::steady_clock::now();
    const planning::Phantom phantom = planning::make_phantom(*options);
    const auto t1 = std::chrono::steady_clock::now();
    planning::write_phantom(phantom, *out);
    const auto t2 = std::chrono::steady_clock::now();
    log_summary(phantom);
    const auto seconds = [](auto a, auto b) {
      return std::chrono::duration<double>(b - a).count();
    };
    spdlog::info(
        "phantom: wrote ct.nii.gz, labels.nii.gz, tumor.nii.gz, vulnerability.json to {} "
        "(seed {}; generated in {:.2f} s, written in {:.2f} s)",
        *out, options->seed, seconds(t0, t1), seconds(t1, t2));
  });
}

}  // namespace crepuscular::apps

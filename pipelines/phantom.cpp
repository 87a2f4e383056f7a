// The phantom job and its summary.
#include "pipelines/phantom.hpp"

#include <fmt/format.h>

#include <Eigen/Core>
#include <array>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <map>
#include <sstream>
#include <vector>
#include <algorithm>
#include <nlohmann/json.hpp>

#include "foundation/log.hpp"
#include "planning/imaging/volume_io.hpp"

namespace crepuscular::pipelines {

namespace {

constexpr double kPi = 3.14159265358979323846;

std::string label_counts(const planning::Phantom& ph, const std::array<int64_t, 256>& counts) {
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
  return line.str();
}

}  // namespace

std::vector<std::string> phantom_summary(const planning::Phantom& ph) {
  const planning::ImageGeometry& g = ph.labels.geometry();
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
  return {fmt::format("phantom: {}x{}x{} voxels of {} mm, origin ({:.1f}, {:.1f}, {:.1f}) LPS mm",
                      g.dims[0], g.dims[1], g.dims[2], g.spacing.x(), g.origin.x(), g.origin.y(),
                      g.origin.z()),
          fmt::format("phantom: tumor {} voxels, {:.0f} mm3, equivalent diameter {:.1f} mm, "
                      "centroid ({:.1f}, {:.1f}, {:.1f}) LPS mm",
                      tumor, volume, std::cbrt(6.0 * volume / kPi), centroid.x(), centroid.y(),
                      centroid.z()),
          "phantom: voxels per label: " + label_counts(ph, counts)};
}

void run_phantom(const planning::PhantomOptions& options, const std::string& out_dir) {
  const auto t0 = std::chrono::steady_clock::now();
  const planning::Phantom phantom = planning::make_phantom(options);
  const auto t1 = std::chrono::steady_clock::now();
  planning::write_phantom(phantom, out_dir);
  const auto t2 = std::chrono::steady_clock::now();
  for (const std::string& line : phantom_summary(phantom)) spdlog::info("{}", line);
  const auto seconds = [](auto a, auto b) { return std::chrono::duration<double>(b - a).count(); };
  spdlog::info(
      "phantom: wrote ct.nii.gz, labels.nii.gz, tumor.nii.gz, vulnerability.json to {} "
      "(seed {}; generated in {:.2f} s, written in {:.2f} s)",
      out_dir, options.seed, seconds(t0, t1), seconds(t1, t2));
}

void run_breathing_phantom(const planning::PhantomOptions& options, int phases,
                           const std::string& out_dir, bool four_d) {
  const auto t0 = std::chrono::steady_clock::now();
  spdlog::info("phantom: {} breathing phases, {} mm cranio-caudal at the diaphragm's dome",
               phases, options.amplitude_mm);
  const nlohmann::json doc = planning::write_breathing_phantom(
      options, phases, out_dir, [&](int k, const planning::Phantom& ph) {
        if (k == 0) {
          for (const std::string& line : phantom_summary(ph)) spdlog::info("{}", line);
        }
        spdlog::info("phantom: phase {:02d} of {} (inhale {:.2f}) written", k, phases,
                     planning::breathing_inhale(k, phases));
      });
  const auto& list = doc.at("phases");
  const auto c0 = list.front().at("tumor_centroid_lps_mm").get<std::vector<double>>();
  double farthest = 0.0;
  for (const auto& p : list) {
    const auto c = p.at("tumor_centroid_lps_mm").get<std::vector<double>>();
    farthest = std::max(farthest, std::hypot(c[0] - c0[0], c[1] - c0[1], c[2] - c0[2]));
  }
  spdlog::info("phantom: the tumor moves up to {:.1f} mm from end-exhale", farthest);
  if (four_d) {
    for (const char* kind : {"ct", "labels", "tumor"}) {
      std::vector<planning::Volume<float>> frames;
      for (const auto& p : list) {
        frames.push_back(planning::read_volume<float>(
            (std::filesystem::path(out_dir) / p.at(kind).get<std::string>()).string()));
      }
      const std::string file = std::string(kind) + "_4d.nii.gz";
      planning::write_volume_frames(frames, (std::filesystem::path(out_dir) / file).string());
      spdlog::info("phantom: wrote {} ({} phases along the 4th axis)", file, phases);
    }
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  spdlog::info("phantom: wrote phases.json, vulnerability.json and phase00..phase{:02d} to {} "
               "({:.1f} s)", phases - 1, out_dir, seconds);
}

}  // namespace crepuscular::pipelines

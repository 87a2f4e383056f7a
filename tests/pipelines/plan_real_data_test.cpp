// The plan job on a real CT and its TotalSegmentator label map (tests/data, Apache-2.0): a virtual
// 2 cm tumor in the liver, fast mode against the exact reference, and a thin-slab crop of the scan
// whose unknown region is reported and never safe.
#include <gtest/gtest.h>

#include <cmath>
#include <nlohmann/json.hpp>

#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "planning/safety/safety_classes.hpp"
#include "planning/safety/unknown.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::pipelines {
namespace {

using planning::Volume;

const std::string kData = std::string(CREPUSCULAR_TEST_DATA) + "/totalsegmentator-ct-3mm/";
constexpr int kLiver = 5;  // TotalSegmentator 'total': liver

// A ball of radius `r_mm` in the liver: centred on the liver voxel whose ball of r + 6 mm is all
// liver and that lies lowest in the scan (far from the cut top of the liver).
Volume<uint8_t> virtual_tumor(const Volume<int32_t>& labels, double r_mm) {
  const planning::ImageGeometry& g = labels.geometry();
  const double reach = r_mm + 6.0;
  const int n = int(std::ceil(reach / g.spacing.minCoeff()));
  Eigen::Vector3d best = Eigen::Vector3d::Zero();
  double best_z = INFINITY;
  for (int64_t k = n; k < g.dims[2] - n; ++k)
    for (int64_t j = n; j < g.dims[1] - n; ++j)
      for (int64_t i = n; i < g.dims[0] - n; ++i) {
        if (labels(i, j, k) != kLiver) continue;
        const Eigen::Vector3d c = g.index_to_physical(i, j, k);
        if (c.z() >= best_z) continue;
        bool inside = true;
        for (int dk = -n; dk <= n && inside; ++dk)
          for (int dj = -n; dj <= n && inside; ++dj)
            for (int di = -n; di <= n && inside; ++di) {
              const Eigen::Vector3d q = g.index_to_physical(i + di, j + dj, k + dk);
              if ((q - c).norm() <= reach && labels(i + di, j + dj, k + dk) != kLiver) inside = false;
            }
        if (inside) {
          best = c;
          best_z = c.z();
        }
      }
  EXPECT_TRUE(std::isfinite(best_z)) << "no liver voxel holds a ball of " << reach << " mm";
  Volume<uint8_t> tumor(g, 0);
  for (int64_t k = 0; k < g.dims[2]; ++k)
    for (int64_t j = 0; j < g.dims[1]; ++j)
      for (int64_t i = 0; i < g.dims[0]; ++i)
        tumor(i, j, k) = (g.index_to_physical(i, j, k) - best).norm() <= r_mm;
  return tumor;
}

// Slices k0 .. k0 + n - 1 of a volume, with their geometry.
template <typename T>
Volume<T> slab(const Volume<T>& v, int64_t k0, int64_t n) {
  planning::ImageGeometry g = v.geometry();
  g.origin = g.index_to_physical(0, 0, k0);
  g.dims[2] = n;
  Volume<T> out(g);
  for (int64_t k = 0; k < n; ++k)
    for (int64_t j = 0; j < g.dims[1]; ++j)
      for (int64_t i = 0; i < g.dims[0]; ++i) out(i, j, k) = v(i, j, k0 + k);
  return out;
}

// The slice index of the tumor's centre.
int64_t tumor_centre_slice(const Volume<uint8_t>& tumor) {
  int64_t sum = 0, count = 0;
  for (int64_t k = 0; k < tumor.dims()[2]; ++k)
    for (int64_t j = 0; j < tumor.dims()[1]; ++j)
      for (int64_t i = 0; i < tumor.dims()[0]; ++i)
        if (tumor(i, j, k)) {
          sum += k;
          ++count;
        }
  return count ? sum / count : 0;
}

// A plan folder as slices, evaluate and guidance read it (load_plan: NIfTI readers hand NaN back
// as 0, so the voxel states of roi.nii.gz decide which voxels have a value).
planning::PlanData load(const std::string& dir) {
  planning::PlanLoadOptions o;
  o.area_safety = false;
  return planning::load_plan(dir, o);
}

class PlanOnRealScan : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    labels_ = new Volume<int32_t>(planning::read_label_map(kData + "example_seg_fast_force_split.nii.gz"));
    tumor_ = new Volume<uint8_t>(virtual_tumor(*labels_, 10.0));
  }
  static void TearDownTestSuite() {
    delete labels_;
    delete tumor_;
  }

  PlanRequest request(const test::TemporaryFolder& dir, const std::string& labels,
                      const std::string& out) const {
    PlanRequest r;
    r.labels = {labels + ":totalsegmentator"};
    r.tumor = dir.file("tumor.nii.gz");
    r.path_safety.radius_mm = 45.0;
    r.path_safety.device = planning::Device::kCpu;
    r.area_safety.enabled = false;
    r.out_dir = dir.file(out);
    return r;
  }

  static Volume<int32_t>* labels_;
  static Volume<uint8_t>* tumor_;
};
Volume<int32_t>* PlanOnRealScan::labels_ = nullptr;
Volume<uint8_t>* PlanOnRealScan::tumor_ = nullptr;

// The requirement: fast mode gives exact mode's safety class on >= 99.5 % of the voxels.
TEST_F(PlanOnRealScan, FastModeAgreesWithExactOnTheVirtualLiverTumor) {
  test::TemporaryFolder dir;
  planning::write_volume(*tumor_, dir.file("tumor.nii.gz"));
  PlanRequest exact = request(dir, kData + "example_seg_fast_force_split.nii.gz", "exact");
  exact.path_safety.values = kernels::kSvv | kernels::kIsbv;
  const nlohmann::json pe = run_plan(exact);
  PlanRequest fast = exact;
  fast.path_safety.mode = planning::Mode::kFast;
  fast.out_dir = dir.file("fast");
  const nlohmann::json pf = run_plan(fast);
  const planning::PlanData exact_plan = load(dir.file("exact"));
  const planning::PlanData fast_plan = load(dir.file("fast"));

  // The whole scan covers this region: nothing unknown.
  EXPECT_EQ(pe["scan_coverage"]["unknown_voxels"].get<int64_t>(), 0);
  // About a 2 cm tumor: 4/3 pi 10^3 mm^3 = 4189 mm^3 at 27 mm^3 per voxel.
  EXPECT_NEAR(pe["tumor"]["voxels"].get<double>(), 4189.0 / 27.0, 20.0);
  for (const std::string value : {"svv", "isbv"}) {
    const Volume<float>& a = exact_plan.path_safety.at(value);
    const Volume<float>& b = fast_plan.path_safety.at(value);
    const planning::SafetyClasses classes =
        planning::default_classes(value == "svv" ? kernels::kSvv : kernels::kIsbv, a);
    int64_t same = 0, n = 0;
    for (size_t v = 0; v < a.values().size(); ++v) {
      if (!std::isfinite(a.values()[v])) continue;
      ++n;
      same += classes.classify(a.values()[v]) == classes.classify(b.values()[v]);
    }
    ASSERT_GT(n, 10000);
    const double agreement = double(same) / double(n);
    std::printf("real scan, %s: fast vs exact class agreement %.4f over %lld voxels\n",
                value.c_str(), agreement, static_cast<long long>(n));
    EXPECT_GE(agreement, 0.995) << value;
  }
}

TEST_F(PlanOnRealScan, ThinSlabCropReportsUnknownAndNeverSafe) {
  test::TemporaryFolder dir;
  planning::write_volume(*tumor_, dir.file("tumor.nii.gz"));
  // Seven slices (21 mm) through the tumor centre: the 45 mm region reaches far beyond them.
  const int64_t k_mid = tumor_centre_slice(*tumor_);
  planning::write_volume(slab(*labels_, k_mid - 3, 7), dir.file("slab_labels.nii.gz"));
  const PlanRequest req = request(dir, dir.file("slab_labels.nii.gz"), "plan");
  const nlohmann::json plan = run_plan(req);

  const nlohmann::json& c = plan["scan_coverage"];
  EXPECT_GT(c["unknown_share"].get<double>(), 0.5);
  EXPECT_GT(c["roi_beyond_scan_mm"]["superior"].get<double>(), 30.0);
  EXPECT_GT(c["roi_beyond_scan_mm"]["inferior"].get<double>(), 30.0);
  EXPECT_EQ(c["roi_beyond_scan_mm"]["left"].get<double>(), 0.0);
  EXPECT_GT(c["tumor_voxels_at_scan_edge"].get<int64_t>(), 0);  // the slab cuts the tumor

  const planning::PlanData loaded = load(dir.file("plan"));
  const Volume<uint8_t>& region = loaded.region;
  ASSERT_FALSE(region.empty());
  const planning::ImageGeometry slab_g = planning::read_label_map(dir.file("slab_labels.nii.gz")).geometry();
  const double z_lo = slab_g.index_to_physical(0, 0, 0).z() - 1.5;
  const double z_hi = slab_g.index_to_physical(0, 0, 6).z() + 1.5;
  int64_t unknown = 0, computed = 0;
  for (const std::string value : {"svv", "isbv", "ivbv", "bvv"}) {
    const Volume<float>& v = loaded.path_safety.at(value);
    const planning::SafetyClasses& classes = loaded.classes.at(value);
    for (int64_t k = 0; k < v.dims()[2]; ++k)
      for (int64_t j = 0; j < v.dims()[1]; ++j)
        for (int64_t i = 0; i < v.dims()[0]; ++i) {
          const float x = v(i, j, k);
          const double z = region.geometry().index_to_physical(i, j, k).z();
          const uint8_t s = region(i, j, k);
          if (s == planning::kRegionUnknown) {
            ++unknown;
            // Independent truth: the voxel centre lies outside the slab's slices.
            EXPECT_TRUE(z < z_lo || z > z_hi) << "unknown voxel inside the scan at z " << z;
            EXPECT_TRUE(std::isnan(x)) << value << " " << i << "," << j << "," << k << " = " << x;
            EXPECT_NE(classes.classify(x), planning::SafetyClass::kSafe);
          } else if (s == planning::kRegionComputed) {
            ++computed;
            EXPECT_TRUE(z >= z_lo && z <= z_hi) << "computed voxel outside the scan at z " << z;
            EXPECT_TRUE(std::isfinite(x));
          }
        }
  }
  EXPECT_EQ(unknown, 4 * c["unknown_voxels"].get<int64_t>());
  EXPECT_GT(computed, 0);
}

TEST_F(PlanOnRealScan, CropToScanLeavesTheOutsideOut) {
  test::TemporaryFolder dir;
  planning::write_volume(*tumor_, dir.file("tumor.nii.gz"));
  planning::write_volume(slab(*labels_, tumor_centre_slice(*tumor_) - 6, 13),
                         dir.file("slab_labels.nii.gz"));
  PlanRequest req = request(dir, dir.file("slab_labels.nii.gz"), "plan");
  req.path_safety.values = kernels::kSvv;
  req.crop_to_scan = true;
  const nlohmann::json plan = run_plan(req);
  EXPECT_EQ(plan["scan_coverage"]["unknown_voxels"].get<int64_t>(), 0);
  EXPECT_GT(plan["scan_coverage"]["cropped_voxels"].get<int64_t>(), 0);
  const Volume<uint8_t> region = planning::read_volume<uint8_t>(dir.file("plan/roi.nii.gz"));
  for (uint8_t s : region.values()) EXPECT_NE(s, planning::kRegionUnknown);
}

TEST_F(PlanOnRealScan, PresetTogetherWithTableIsRefused) {
  test::TemporaryFolder dir;
  planning::write_volume(*tumor_, dir.file("tumor.nii.gz"));
  PlanRequest req = request(dir, kData + "example_seg_fast_force_split.nii.gz", "plan");
  req.preset = "totalsegmentator";
  req.vulnerability = kData + "totalsegmentator_v2_total_classmap.json";
  test::expect_error_containing([&] { run_plan(req); }, "either a vulnerability table or a preset");
  EXPECT_FALSE(std::filesystem::exists(dir.file("plan")));
}

}  // namespace
}  // namespace crepuscular::pipelines

namespace crepuscular::pipelines {
namespace {

// The tumor as a label of the label map that also gives the blocking (here the gallbladder,
// label 4, level 2 in the 'total' preset): the target structure does not block its own paths.
TEST(PlanTumorAsLabel, TheTumorLabelDoesNotBlock) {
  test::TemporaryFolder dir;
  const std::string labels = kData + "example_seg_fast_force_split.nii.gz";
  PlanRequest r;
  r.labels = {labels + ":totalsegmentator"};
  r.tumor = labels + ":4";
  r.path_safety.radius_mm = 15.0;
  r.path_safety.values = kernels::kSvv;
  r.path_safety.device = planning::Device::kCpu;
  r.area_safety.enabled = false;
  r.out_dir = dir.file("plan");
  const nlohmann::json plan = run_plan(r);
  EXPECT_EQ(plan["tumor_source"]["label"].get<int>(), 4);
  EXPECT_EQ(plan["tumor_source"]["lesion"]["lesions_in_mask"].get<int>(), 1);
  const auto& c = plan["tumor_source"]["lesion"]["centroid_lps_mm"];
  const Eigen::Vector3d centroid(c[0].get<double>(), c[1].get<double>(), c[2].get<double>());
  const Volume<float> blocking = planning::read_volume<float>(dir.file("plan/blocking.nii.gz"));
  const Eigen::Vector3d ijk = blocking.geometry().physical_to_index(centroid);
  const float b = blocking(std::lround(ijk.x()), std::lround(ijk.y()), std::lround(ijk.z()));
  EXPECT_LT(b, 1e-3) << "the gallbladder (level 2, 0.1 per mm) blocks its own paths";
  // The planned lesion is kept in the plan folder: what slices, evaluate and guide outline.
  const Volume<uint8_t> kept = planning::read_mask(dir.file("plan/tumor.nii.gz"));
  int64_t n = 0;
  for (uint8_t v : kept.values()) n += v;
  EXPECT_EQ(n, plan["tumor_source"]["lesion"]["voxels"].get<int64_t>());
}

}  // namespace
}  // namespace crepuscular::pipelines

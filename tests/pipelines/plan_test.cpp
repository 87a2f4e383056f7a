// The plan job end to end: files written, their geometry and content, and bad input that must
// leave no output behind (through the library and through the `crepuscular` command).
#include "pipelines/plan.hpp"

#include <gtest/gtest.h>
#include <sys/wait.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <chrono>
#include <fstream>

#include "foundation/error.hpp"
#include "foundation/json_fields.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/plan_folder/plan_folder.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/errors.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using pipelines::PlanRequest;
using pipelines::run_plan;
using test::expect_error_containing;
using test::run_cli;

class PlanTest : public ::testing::Test {
 protected:
  void SetUp() override {
    // The mini plan (test::write_mini_plan_inputs) with a rotated direction.
    test::MiniPlanOptions o;
    o.grid.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0, 0, 1)).toRotationMatrix();
    inputs_ = test::write_mini_plan_inputs(dir_, o);
    labels_ = inputs_.labels;
    tumor_ = inputs_.tumor;
    table_ = inputs_.vulnerability;
  }

  PlanRequest request(const std::string& out) const {
    PlanRequest r = inputs_.request((dir_ / out).string());
    r.margin.fwhm_mm = 2.0;
    return r;
  }

  // Files and folders left in dir_ apart from the inputs.
  std::vector<std::string> leftovers() const {
    std::vector<std::string> names;
    for (const auto& e : fs::directory_iterator(dir_)) {
      const std::string n = e.path().filename().string();
      if (n != "labels.nii.gz" && n != "tumor.nii.gz" && n != "table.json") names.push_back(n);
    }
    return names;
  }

  test::TemporaryFolder dir_;
  test::MiniPlanInputs inputs_;
  std::string labels_, tumor_, table_;
};

// plan.json names the plan's own files: an output path that leads out of the folder (a swapped
// or edited path putting another plan's values under this plan's name) is refused by name.
TEST_F(PlanTest, PlanJsonOutputsOutsideTheFolderAreRefused) {
  PlanRequest r = request("plan");
  r.path_safety.values = kernels::kSvv;
  r.area_safety.enabled = false;
  run_plan(r);
  EXPECT_NO_THROW(load_plan((dir_ / "plan").string()));
  const std::string json_path = (dir_ / "plan" / "plan.json").string();
  nlohmann::json j = read_json_file(json_path, "the plan");
  for (const std::string swapped : {"../other/path_safety_svv.nii.gz", "/tmp/path_safety_svv.nii.gz"}) {
    j["outputs"]["svv"] = swapped;
    std::ofstream(json_path) << j.dump(2);
    expect_error_containing([&] { load_plan((dir_ / "plan").string()); },
                            {"plan.json", swapped, "inside the plan folder"});
  }
}

// A CT 2 m away from the label map (another patient, another frame) left the whole region unknown
// with rc 0; it is refused, naming both inputs, and nothing is written.
TEST_F(PlanTest, CtThatDoesNotOverlapTheLabelMapIsRefused) {
  ImageGeometry far = inputs_.grid;
  far.origin += Eigen::Vector3d(2000, 0, 0);
  write_volume(Volume<float>(far, 40.0f), (dir_ / "far_ct.nii.gz").string());
  PlanRequest r = request("plan");
  r.ct = (dir_ / "far_ct.nii.gz").string();
  expect_error_containing([&] { run_plan(r); }, {"far_ct.nii.gz", "does not overlap", "labels.nii.gz"});
  EXPECT_FALSE(fs::exists(dir_ / "plan"));
}

// The label map given as the tumor (every voxel > 0.5) planned for minutes into one all-safe
// region; it is refused with its share of the scan, and nothing is written.
TEST_F(PlanTest, TumorFillingTheScanIsRefusedWithItsShare) {
  PlanRequest r = request("plan");
  r.tumor = labels_;
  expect_error_containing([&] { run_plan(r); },
                          {"labels.nii.gz", "the tumor is 111 mL, 100 % of the scan (111 mL)",
                           "not the label map or an inverted mask"});
  // 24^3 voxels of 2 mm: 110.6 mL. A lesion of 30 % of it (the first 7 of 24 slices, whole) too.
  Volume<uint8_t> slab(inputs_.grid, 0);
  for (int64_t k = 0; k < 7; ++k)
    for (int64_t j = 0; j < 24; ++j)
      for (int64_t i = 0; i < 24; ++i) slab(i, j, k) = 1;
  write_volume(slab, (dir_ / "slab.nii.gz").string());
  r.tumor = (dir_ / "slab.nii.gz").string();
  expect_error_containing([&] { run_plan(r); }, {"slab.nii.gz", "29 % of the scan"});
  EXPECT_FALSE(fs::exists(dir_ / "plan"));
}

// A region of interest of 5 mm around the centre of a tumor 10 mm in radius computed only tumor
// voxels, and area safety called every vertex safe; it is refused with the distances.
TEST_F(PlanTest, RegionOfInterestInsideTheTumorIsRefused) {
  Volume<uint8_t> ball(inputs_.grid, 0);
  const Eigen::Vector3d c = inputs_.grid.index_to_physical(Eigen::Vector3d(11.5, 11.5, 11.5));
  for (int64_t k = 0; k < 24; ++k)
    for (int64_t j = 0; j < 24; ++j)
      for (int64_t i = 0; i < 24; ++i) ball(i, j, k) = (ball.index_to_physical(i, j, k) - c).norm() <= 10.0;
  write_volume(ball, (dir_ / "ball.nii.gz").string());
  PlanRequest r = request("plan");
  r.tumor = (dir_ / "ball.nii.gz").string();
  r.path_safety.radius_mm = 5.0;
  expect_error_containing([&] { run_plan(r); },
                          {"region of interest: a radius of 5.0 mm lies inside the tumor",
                           "give a radius larger than"});
  EXPECT_FALSE(fs::exists(dir_ / "plan"));
  // Reaching beyond its surface, the same tumor plans.
  r.path_safety.radius_mm = 16.0;
  r.path_safety.values = kernels::kSvv;
  EXPECT_NO_THROW(run_plan(r));
}

TEST_F(PlanTest, WritesEveryValueOnTheOutputGridWithNanOutsideTheBall) {
  const nlohmann::json plan = run_plan(request("plan"));
  for (const char* f : {"blocking.nii.gz", "roi.nii.gz", "path_safety_svv.nii.gz", "path_safety_isbv.nii.gz",
                        "path_safety_ivbv.nii.gz", "path_safety_bvv.nii.gz", "plan.json"}) {
    EXPECT_TRUE(fs::exists(dir_ / "plan" / f)) << f;
  }
  const Volume<float> svv = read_volume<float>((dir_ / "plan/path_safety_svv.nii.gz").string(), VolumeReadOptions::path_safety_file());
  const auto& g = svv.geometry();
  // 2 ceil(R/h) + 1 = 2 * 8 + 1 voxels at h = 2 mm, axes of the label map.
  EXPECT_EQ(g.dims, (Index3{17, 17, 17}));
  EXPECT_NEAR(g.spacing.x(), 2.0, 1e-6);
  const Volume<int32_t> labels = read_label_map(labels_);
  EXPECT_LT((g.direction - labels.geometry().direction).cwiseAbs().maxCoeff(), 1e-5);
  // The centre voxel lies on the tumor centroid, voxel (11, 11, 11) of the inputs.
  const Eigen::Vector3d c = labels.geometry().index_to_physical(11, 11, 11);
  EXPECT_LT((svv.index_to_physical(8, 8, 8) - c).norm(), 1e-3);
  const Volume<uint8_t> roi = read_mask((dir_ / "plan/roi.nii.gz").string());
  EXPECT_EQ(roi(0, 0, 0), 0);
  EXPECT_EQ(roi(8, 8, 8), 1);
  EXPECT_EQ(roi(0, 8, 8), 1);  // 8 voxels from the centre: on the ball's surface
  EXPECT_FALSE(std::isnan(svv(8, 8, 8)));
  // Outside the ball the file holds NaN. ITK's NIfTI reader turns NaN into 0, so look with
  // nibabel where it is installed.
  const std::string py = "/usr/bin/python3 -c \"import nibabel, numpy; d = nibabel.load('" +
                         (dir_ / "plan/path_safety_svv.nii.gz").string() +
                         "').get_fdata(); raise SystemExit(0 if numpy.isnan(d[0,0,0]) and not "
                         "numpy.isnan(d[8,8,8]) else 3)\" 2>/dev/null";
  const int rc = std::system(py.c_str());
  if (WEXITSTATUS(rc) != 1) {  // 1: python or nibabel missing
    EXPECT_EQ(WEXITSTATUS(rc), 0) << "NaN outside the ball";
  }
  // Toward the vessel side (+i) paths cross impassable blocking: SVV is lower there than on the
  // free side (-i) at the same distance.
  EXPECT_LT(svv(15, 8, 8), svv(1, 8, 8));
  EXPECT_EQ(svv(1, 8, 8), 100.0f);
  EXPECT_EQ(plan["parameters"]["values"].size(), 4u);
  EXPECT_EQ(plan["inputs"]["tumor"]["md5"].get<std::string>().size(), 32u);
  EXPECT_EQ(plan["tumor"]["voxels"].get<int>(), 27);
  EXPECT_GT(plan["timings"]["total_s"].get<double>(), 0.0);
  EXPECT_TRUE(plan["classes"].contains("bvv"));
  // Each value's classes for 3D Slicer: voxel for voxel its volume's classes by plan.json's
  // thresholds, every voxel of the region in one segment; no voxel unknown (one scan grid).
  int64_t region_voxels = 0;
  for (const uint8_t s : roi.values()) region_voxels += s != 0 ? 1 : 0;
  for (const char* v : {"svv", "isbv", "ivbv", "bvv"}) {
    EXPECT_TRUE(
        fs::exists(dir_ / "plan" / ("path_safety_" + std::string(v) + "_classes.seg.nrrd")));
    const std::array<int64_t, 4> n =
        test::expect_classes_segmentation_matches_plan(dir_ / "plan", v);
    EXPECT_EQ(n[0] + n[1] + n[2] + n[3], region_voxels) << v;
    EXPECT_GT(n[0], 0) << v;  // the free side (-i) is safe for every value
    EXPECT_EQ(n[3], 0) << v;
  }
  EXPECT_EQ(leftovers(), std::vector<std::string>{"plan"});
}

TEST_F(PlanTest, ChecksumIsMd5OfTheFile) {
  std::ofstream(dir_ / "abc.txt") << "abc";
  // MD5("abc"), RFC 1321 test suite.
  EXPECT_EQ(file_checksum((dir_ / "abc.txt").string()), "900150983cd24fb0d6963f7d28e17f72");
  // Kept for the file as it is, taken again once it changes: other bytes of the same size (with
  // a later time), then other bytes of another size.
  const auto written = fs::last_write_time(dir_ / "abc.txt");
  std::ofstream(dir_ / "abc.txt") << "abd";
  fs::last_write_time(dir_ / "abc.txt", written + std::chrono::seconds(2));
  EXPECT_EQ(file_checksum((dir_ / "abc.txt").string()), "4911e516e5aa21d327512e0c8b197616");
  std::ofstream(dir_ / "abc.txt") << "message digest";
  EXPECT_EQ(file_checksum((dir_ / "abc.txt").string()), "f96b697d7cb7938d525a2f31aaf161d0");
}

TEST_F(PlanTest, FailedRunLeavesNoOutputAndKeepsTheEarlierPlan) {
  run_plan(request("plan"));
  const auto before = fs::last_write_time(dir_ / "plan" / "plan.json");
  // Empty tumor mask: refused after the staging folder was made.
  Volume<uint8_t> empty(read_mask(tumor_).geometry(), 0);
  write_volume(empty, (dir_ / "empty.nii.gz").string());
  PlanRequest r = request("plan");
  r.tumor = (dir_ / "empty.nii.gz").string();
  EXPECT_THROW(run_plan(r), Error);
  EXPECT_EQ(fs::last_write_time(dir_ / "plan" / "plan.json"), before);
  fs::remove(dir_ / "empty.nii.gz");
  EXPECT_EQ(leftovers(), std::vector<std::string>{"plan"});
  // A fresh output folder is not created at all.
  r.out_dir = (dir_ / "other").string();
  r.tumor = (dir_ / "missing.nii.gz").string();
  EXPECT_THROW(run_plan(r), Error);
  EXPECT_FALSE(fs::exists(dir_ / "other"));
}

TEST_F(PlanTest, UnknownLabelIsRefusedNamingTheLabel) {
  Volume<int32_t> labels = read_label_map(labels_);
  labels(3, 3, 3) = 7;
  write_volume(labels, labels_);
  expect_error_containing([&] { run_plan(request("plan")); }, "7");
  EXPECT_TRUE(leftovers().empty());
}

TEST_F(PlanTest, CommandLineReportsBadInputAndWritesNothing) {
  std::string err;
  const std::string out = (dir_ / "cli").string();
  // Truncated tumor file.
  const std::string bad = (dir_ / "bad.nii.gz").string();
  std::ofstream(bad) << "not a volume";
  EXPECT_EQ(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " + bad +
                        " --out " + out,
                    &err, test::Capture::kStderr),
            1);
  EXPECT_EQ(err.rfind("error: ", 0), 0u) << err;
  EXPECT_NE(err.find("bad.nii.gz"), std::string::npos) << err;
  EXPECT_FALSE(fs::exists(out));
  // Negative spacing.
  EXPECT_NE(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " +
                        tumor_ + " --spacing -1 --out " + out,
                    &err, test::Capture::kStderr),
            0);
  EXPECT_NE(err.find("spacing"), std::string::npos) << err;
  EXPECT_FALSE(fs::exists(out));
  // A working run through the command line.
  EXPECT_EQ(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " +
                        tumor_ + " --radius 10 --value svv,bvv --device cpu --out " + out,
                    &err, test::Capture::kStderr),
            0)
      << err;
  EXPECT_TRUE(fs::exists(dir_ / "cli" / "path_safety_bvv.nii.gz"));
  EXPECT_FALSE(fs::exists(dir_ / "cli" / "path_safety_isbv.nii.gz"));
  // Run again into its own plan folder: replaced.
  EXPECT_EQ(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " +
                        tumor_ + " --radius 10 --value svv --device cpu --out " + out,
                    &err, test::Capture::kStderr),
            0)
      << err;
  EXPECT_FALSE(fs::exists(dir_ / "cli" / "path_safety_bvv.nii.gz"));
  // A thread count OpenMP cannot start is an option error, before any work.
  EXPECT_NE(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " +
                        tumor_ + " --threads 100000 --out " + out,
                    &err, test::Capture::kStderr),
            0);
  EXPECT_EQ(err.rfind("error: --threads", 0), 0u) << err;
  // Numbers out of their sensible range, NaN among them, are refused by the option that names
  // them, with short bounds (CLI11's own ranges printed 1.79769e+308 in full and let NaN pass).
  for (const std::string option : {"--spacing 1e9", "--spacing nan", "--radius 1e308",
                                   "--margin -1", "--threads 2.5", "--tumor-spacing inf"}) {
    EXPECT_NE(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " +
                          tumor_ + " " + option + " --out " + out,
                      &err, test::Capture::kStderr),
              0)
        << option;
    const std::string name = option.substr(0, option.find(' '));
    EXPECT_EQ(err.rfind("error: " + name + ":", 0), 0u) << option << ": " << err;
    EXPECT_EQ(err.find("000000"), std::string::npos) << option << ": " << err;
    EXPECT_LT(err.size(), 200u) << err;
  }
  // --out naming the folder of the run's own inputs: refused at once, nothing touched.
  const auto before = std::distance(fs::directory_iterator(dir_), fs::directory_iterator());
  EXPECT_EQ(run_cli("plan --labels " + labels_ + " --vulnerability " + table_ + " --tumor " +
                        tumor_ + " --radius 10 --value svv --device cpu --out " + dir_.string(),
                    &err, test::Capture::kStderr),
            1);
  EXPECT_EQ(err.rfind("error: ", 0), 0u) << err;
  EXPECT_NE(err.find("holds the input --"), std::string::npos) << err;
  EXPECT_EQ(std::distance(fs::directory_iterator(dir_), fs::directory_iterator()), before);
  EXPECT_TRUE(fs::exists(labels_));
  EXPECT_TRUE(fs::exists(tumor_));
}

}  // namespace
}  // namespace crepuscular::planning

// Slice images: the colour of a voxel of known class at its pixel, the area safety contour at its
// known place and width, the orientation of every plane against a phantom marked at L, P and S
// (stored with a flipped direction matrix, so index order cannot stand in for anatomy), and the
// command end to end.
#include "planning/views/slices.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include <nlohmann/json.hpp>

#include "foundation/error.hpp"
#include "pipelines/plan.hpp"
#include "planning/imaging/volume_io.hpp"
#include "planning/safety/unknown.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/grids.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace fs = std::filesystem;

namespace crepuscular::planning {
namespace {

using Rgb = std::array<uint8_t, 3>;
using pipelines::run_plan;
using test::centred_cube_grid;
using test::run_cli;

void expect_colour(const Rgb& got, const std::array<double, 3>& want, double tol,
                   const std::string& what) {
  for (int c = 0; c < 3; ++c) {
    EXPECT_NEAR(double(got[size_t(c)]), want[size_t(c)], tol)
        << what << ": channel " << c << " got (" << int(got[0]) << "," << int(got[1]) << ","
        << int(got[2]) << ")";
  }
}

std::array<double, 3> grey(double g) { return {g, g, g}; }

Rgb pixel(const SliceView& v, const Eigen::Vector3d& p) {
  const Eigen::Vector2d px = v.pixel_of(p);
  const int x = int(std::lround(px.x())), y = int(std::lround(px.y()));
  EXPECT_TRUE(x >= 0 && y >= 0 && x < v.view_width && y < v.view_height) << px.transpose();
  return v.image.at(x, y);
}

TEST(SlicesTest, WindowMapsSoftTissueRange) {
  // W400 / L40: -160 HU black, 240 HU white, 40 HU mid-grey.
  EXPECT_EQ(window_grey(-160, 400, 40), 0);
  EXPECT_EQ(window_grey(240, 400, 40), 255);
  EXPECT_EQ(window_grey(40, 400, 40), 128);  // 127.5 rounded
  EXPECT_EQ(window_grey(-1000, 400, 40), 0);
}

TEST(SlicesTest, VoxelOfKnownClassHasItsBlendedColour) {
  const Eigen::Vector3d c(10, -20, 30);
  const Volume<float> ct(centred_cube_grid(40, 2.0, c), 40.0f);  // grey 128 everywhere
  // Path safety grid of 4 mm voxels: svv 95 (safe) at one voxel, 70 (medium), 10 (dangerous).
  const ImageGeometry pg = centred_cube_grid(11, 4.0, c);
  Volume<float> svv(pg, std::numeric_limits<float>::quiet_NaN());
  svv(5, 5, 5) = 95;
  svv(7, 5, 5) = 70;
  svv(5, 3, 5) = 10;
  SliceScene scene;
  scene.ct = &ct;
  scene.path_safety = &svv;
  scene.value_name = "svv";
  scene.classes.higher_is_safer = true;
  scene.classes.safe = 90;
  scene.classes.dangerous = 50;
  SliceOptions o;
  o.pixel_mm = 0.5;
  const SliceView v = render_slice(scene, make_slice_plane(SlicePlaneKind::kAxial, c), o);
  const auto blend = [](const Rgb& colour) {
    return std::array<double, 3>{0.6 * 128 + 0.4 * colour[0], 0.6 * 128 + 0.4 * colour[1],
                                 0.6 * 128 + 0.4 * colour[2]};
  };
  expect_colour(pixel(v, pg.index_to_physical(5, 5, 5)), blend({0, 200, 0}), 1.0, "safe voxel");
  expect_colour(pixel(v, pg.index_to_physical(7, 5, 5)), blend({255, 220, 0}), 1.0, "medium voxel");
  expect_colour(pixel(v, pg.index_to_physical(5, 3, 5)), blend({230, 0, 0}), 1.0,
                "dangerous voxel");
  // A voxel 1.5 mm from the safe voxel's centre is still inside it (nearest voxel, 4 mm).
  expect_colour(pixel(v, pg.index_to_physical(5, 5, 5) + Eigen::Vector3d(1.5, -1.5, 0)),
                blend({0, 200, 0}), 1.0, "inside the safe voxel");
  // NaN (outside the region of interest): the CT alone.
  expect_colour(pixel(v, pg.index_to_physical(3, 7, 5)), grey(128), 0.0, "not computed");

  // Hidden class: CT only. Colour-blind palette: safe is blue.
  o.hidden = parse_hidden_classes("safe");
  const SliceView hidden = render_slice(scene, make_slice_plane(SlicePlaneKind::kAxial, c), o);
  expect_colour(pixel(hidden, pg.index_to_physical(5, 5, 5)), grey(128), 0.0, "hidden safe");
  expect_colour(pixel(hidden, pg.index_to_physical(5, 3, 5)), blend({230, 0, 0}), 1.0, "dangerous");
  o.hidden = {false, false, false};
  o.palette = Palette::kColorblind;
  const SliceView cb = render_slice(scene, make_slice_plane(SlicePlaneKind::kAxial, c), o);
  expect_colour(pixel(cb, pg.index_to_physical(5, 5, 5)), blend({0, 114, 178}), 1.0, "blue safe");
  expect_colour(pixel(cb, pg.index_to_physical(5, 3, 5)), blend({240, 228, 66}), 1.0,
                "yellow dangerous");
}

TEST(SlicesTest, UnknownVoxelsAreHatchedNeverAClassColourAlsoBeyondTheCt) {
  const Eigen::Vector3d c(10, -20, 30);
  const Volume<float> ct(centred_cube_grid(40, 2.0, c), 40.0f);  // grey 128, z in c +- 40 mm
  // Plan grid of 4 mm voxels, z in c +- 62 mm: computed and safe up to c.z + 10 mm, unknown
  // above (also beyond the CT); one unknown voxel even holds a finite safe value.
  const ImageGeometry pg = centred_cube_grid(31, 4.0, c);
  Volume<float> svv(pg, 95.0f);
  Volume<uint8_t> state(pg, kRegionComputed);
  for (int k = 0; k < 31; ++k)
    for (int j = 0; j < 31; ++j)
      for (int i = 0; i < 31; ++i) {
        if (pg.index_to_physical(i, j, k).z() > c.z() + 10) {
          state(i, j, k) = kRegionUnknown;
          if (!(i == 20 && k == 20)) svv(i, j, k) = std::numeric_limits<float>::quiet_NaN();
        }
      }
  SliceScene scene;
  scene.ct = &ct;
  scene.path_safety = &svv;
  scene.value_name = "svv";
  scene.classes.higher_is_safer = true;
  scene.classes.safe = 90;
  scene.classes.dangerous = 50;
  scene.region_state = &state;
  SliceOptions o;
  o.pixel_mm = 0.5;
  const SlicePlane plane = make_slice_plane(SlicePlaneKind::kCoronal, c);
  const SliceView v = render_slice(scene, plane, o);
  EXPECT_GT(v.unknown_pixels, 0);
  const std::array<double, 3> safe{0.6 * 128 + 0.4 * 0, 0.6 * 128 + 0.4 * 200, 0.6 * 128};
  expect_colour(pixel(v, c + Eigen::Vector3d(0, 0, -20)), safe, 1.0, "computed safe voxel");
  // Rows inside the CT (z + 20, 24: over grey 128) and beyond it (z + 50, 54: over black; the
  // view grew to show them): along each row, and along a diagonal, hatch grey where
  // unknown_hatch_pixel says, the background elsewhere, nothing else (no class colour).
  const Rgb hatch{kUnknownHatchGrey, kUnknownHatchGrey, kUnknownHatchGrey};
  for (const double dz : {20.0, 24.0, 50.0, 54.0}) {
    const uint8_t bg = dz < 40 ? 128 : 0;
    const Rgb background{bg, bg, bg};
    const Eigen::Vector2d start = v.pixel_of(c + Eigen::Vector3d(20, 0, dz));
    const int x0 = int(std::lround(start.x())), y0 = int(std::lround(start.y()));
    ASSERT_TRUE(x0 >= 0 && y0 >= 0 && x0 + 24 < v.view_width && y0 + 8 < v.view_height) << dz;
    int lines = 0, gaps = 0;
    for (int t = 0; t < 24; ++t) {
      for (const auto& [x, y] : {std::pair<int, int>{x0 + t, y0}, {x0 + t / 3, y0 + t / 3}}) {
        const Rgb got = v.image.at(x, y);
        const bool on = unknown_hatch_pixel(x, y);
        EXPECT_EQ(got, on ? hatch : background)
            << "z + " << dz << " pixel " << x << "," << y << " got " << int(got[0]) << ","
            << int(got[1]) << "," << int(got[2]);
        (on ? lines : gaps)++;
      }
    }
    EXPECT_GT(lines, 4) << dz;
    EXPECT_GT(gaps, 4) << dz;
  }
  // The unknown voxel with a finite safe value is hatched too, not green.
  const Eigen::Vector2d q = v.pixel_of(pg.index_to_physical(20, 15, 20));
  for (int dy = -3; dy <= 3; ++dy)
    for (int dx = -3; dx <= 3; ++dx) {
      const int x = int(std::lround(q.x())) + dx, y = int(std::lround(q.y())) + dy;
      const Rgb mid_grey{128, 128, 128};
      EXPECT_EQ(v.image.at(x, y), unknown_hatch_pixel(x, y) ? hatch : mid_grey);
    }

  // Without the states: no unknown pixel, and the view ends with the CT.
  scene.region_state = nullptr;
  const SliceView plain = render_slice(scene, plane, o);
  EXPECT_EQ(plain.unknown_pixels, 0);
  EXPECT_LT(plain.view_height, v.view_height);
}

// A closed box mesh [-20, 20]^3 around c (12 outward triangles); every vertex safe with `leeway`.
AreaSafetyGeometry box_area(const Eigen::Vector3d& c, float leeway) {
  AreaSafetyGeometry a;
  a.ellipsoid.centre = c;
  for (int i = 0; i < 8; ++i) {
    const Eigen::Vector3d s((i & 1) ? 1 : -1, (i & 2) ? 1 : -1, (i & 4) ? 1 : -1);
    a.vertices.push_back(c + 20 * s);
    a.base.push_back(c + 5 * s);
    a.normals.push_back(s.normalized());
    a.safe.push_back(leeway > 0);
    a.region.push_back(leeway > 0 ? 0 : -1);
    a.leeway.push_back(leeway);
  }
  // Faces as quads of corner indices (outward), split into two triangles each.
  const int quads[6][4] = {{0, 2, 3, 1}, {4, 5, 7, 6}, {0, 1, 5, 4},
                           {2, 6, 7, 3}, {0, 4, 6, 2}, {1, 3, 7, 5}};
  for (const auto& q : quads) {
    a.triangles.push_back({q[0], q[1], q[2]});
    a.triangles.push_back({q[0], q[2], q[3]});
  }
  return a;
}

TEST(SlicesTest, AreaSafetyContourLiesWhereThePlaneCutsTheMeshWithLeewayWidthAndColour) {
  const Eigen::Vector3d c(0, 0, 0);
  const Volume<float> ct(centred_cube_grid(50, 2.0, c), 40.0f);
  SliceScene scene;
  scene.ct = &ct;
  SliceOptions o;
  o.pixel_mm = 0.5;
  for (const auto kind :
       {SlicePlaneKind::kAxial, SlicePlaneKind::kCoronal, SlicePlaneKind::kSagittal}) {
    const SlicePlane plane = make_slice_plane(kind, c + Eigen::Vector3d(1, 2, 3));
    // Leeway 1: a 10 mm band outside each face at distance 20 from c.
    AreaSafetyGeometry full = box_area(c, 1.0f);
    scene.area = &full;
    SliceView v = render_slice(scene, plane, o);
    EXPECT_GE(v.contour_segments, 4) << plane_name(kind);
    const Eigen::Vector3d r = plane.right;
    const Rgb green{0, 200, 0};
    const std::array<double, 3> g{0, 200, 0};
    expect_colour(pixel(v, c + 25 * r), g, 1.0, std::string(plane_name(kind)) + " band +right");
    expect_colour(pixel(v, c - 25 * r), g, 1.0, std::string(plane_name(kind)) + " band -right");
    expect_colour(pixel(v, c + 15 * r), grey(128), 0.0, "inside the contour");
    expect_colour(pixel(v, c + 35 * r), grey(128), 0.0, "beyond the band");
    (void)green;
    // Leeway 0.5: half as wide (5 mm), the medium colour.
    AreaSafetyGeometry half = box_area(c, 0.5f);
    scene.area = &half;
    v = render_slice(scene, plane, o);
    expect_colour(pixel(v, c + 22.5 * plane.down), {255, 220, 0}, 1.0, "half band");
    expect_colour(pixel(v, c + 27.5 * plane.down), grey(128), 0.0, "beyond the half band");
    EXPECT_EQ(leeway_colour(Palette::kDefault, 0.5), (Rgb{255, 220, 0}));
    EXPECT_EQ(leeway_colour(Palette::kDefault, 1.0), green);
  }
}

// CT of air, 200 mm wide around c, with one bright 6 mm cube at `marker`, stored with direction
// diag(-1, -1, 1) (as many NIfTI files are): index axes run R and A.
Volume<float> marked_ct(const Eigen::Vector3d& c, const Eigen::Vector3d& marker) {
  ImageGeometry g;
  g.dims = {100, 100, 100};
  g.spacing = Eigen::Vector3d::Constant(2.0);
  g.direction = Eigen::Vector3d(-1, -1, 1).asDiagonal();
  g.origin = c - g.direction * Eigen::Vector3d::Constant(99.0);
  Volume<float> ct(g, -1000.0f);
  for (int k = 0; k < 100; ++k)
    for (int j = 0; j < 100; ++j)
      for (int i = 0; i < 100; ++i) {
        if ((g.index_to_physical(i, j, k) - marker).cwiseAbs().maxCoeff() <= 3.0)
          ct(i, j, k) = 1000.0f;
      }
  return ct;
}

// Centroid of white pixels away from the letters and scale bar at the edges; count in *n.
Eigen::Vector2d white_centroid(const SliceView& v, int* n) {
  Eigen::Vector2d sum(0, 0);
  *n = 0;
  for (int y = 45; y < v.view_height - 45; ++y)
    for (int x = 45; x < v.view_width - 45; ++x) {
      const Rgb p = v.image.at(x, y);
      if (p[0] > 250 && p[1] > 250 && p[2] > 250) {
        sum += Eigen::Vector2d(x, y);
        ++*n;
      }
    }
  return *n ? Eigen::Vector2d(sum / *n) : sum;
}

TEST(SlicesTest, EveryPlaneShowsTheMarkedPhantomInRadiologicalOrientation) {
  const Eigen::Vector3d c(5, -7, 11);
  const Eigen::Vector3d L(1, 0, 0), P(0, 1, 0), S(0, 0, 1);
  SliceOptions o;
  o.pixel_mm = 1.0;
  struct Case {
    SlicePlaneKind kind;
    Eigen::Vector3d marker_dir;
    int dx, dy;  // expected side: +1 right / bottom, -1 left / top, 0 centred; 9: not in plane
  };
  const Case cases[] = {
      {SlicePlaneKind::kAxial, L, +1, 0},    {SlicePlaneKind::kAxial, P, 0, +1},
      {SlicePlaneKind::kAxial, S, 9, 9},     {SlicePlaneKind::kCoronal, L, +1, 0},
      {SlicePlaneKind::kCoronal, S, 0, -1},  {SlicePlaneKind::kCoronal, P, 9, 9},
      {SlicePlaneKind::kSagittal, P, +1, 0}, {SlicePlaneKind::kSagittal, S, 0, -1},
      {SlicePlaneKind::kSagittal, L, 9, 9},
  };
  for (const auto& k : cases) {
    const Volume<float> ct = marked_ct(c, c + 40 * k.marker_dir);
    SliceScene scene;
    scene.ct = &ct;
    const SliceView v = render_slice(scene, make_slice_plane(k.kind, c), o);
    int n = 0;
    const Eigen::Vector2d m = white_centroid(v, &n);
    const Eigen::Vector2d centre = v.pixel_of(c);
    const std::string what =
        std::string(plane_name(k.kind)) + " marker " + orientation_letters(k.marker_dir);
    if (k.dx == 9) {
      EXPECT_EQ(n, 0) << what << " should be out of plane";
      continue;
    }
    ASSERT_GT(n, 10) << what;
    for (int a = 0; a < 2; ++a) {
      const int side = a == 0 ? k.dx : k.dy;
      const double d = m[a] - centre[a];
      if (side == 0)
        EXPECT_NEAR(d, 0.0, 2.0) << what << " axis " << a;
      else
        EXPECT_NEAR(d, side * 40.0, 2.0) << what << " axis " << a;
    }
  }
  // Letters at the edges: axial R left, L right, A top, P bottom; coronal S top; sagittal A left.
  const SlicePlane ax = make_slice_plane(SlicePlaneKind::kAxial, c);
  EXPECT_EQ(orientation_letters(-ax.right), "R");
  EXPECT_EQ(orientation_letters(ax.right), "L");
  EXPECT_EQ(orientation_letters(-ax.down), "A");
  EXPECT_EQ(orientation_letters(ax.down), "P");
  const SlicePlane co = make_slice_plane(SlicePlaneKind::kCoronal, c);
  EXPECT_EQ(orientation_letters(-co.down), "S");
  EXPECT_EQ(orientation_letters(co.right), "L");
  const SlicePlane sa = make_slice_plane(SlicePlaneKind::kSagittal, c);
  EXPECT_EQ(orientation_letters(-sa.right), "A");
  EXPECT_EQ(orientation_letters(-sa.down), "S");
}

TEST(SlicesTest, ObliquePlaneContainsTheMainAxis) {
  const Eigen::Vector3d c(0, 0, 0);
  const Eigen::Vector3d m = Eigen::Vector3d(1, 1, 0.2).normalized();  // left, posterior, up
  const SlicePlane plane = make_slice_plane(SlicePlaneKind::kOblique, c, m);
  EXPECT_NEAR(plane.normal().dot(m), 0.0, 1e-12);
  EXPECT_NEAR(plane.right.dot(plane.down), 0.0, 1e-12);
  // Closest to axial (m lies mostly in it): L still to the right, P still down.
  EXPECT_GT(plane.right.x(), 0.9);
  EXPECT_GT(plane.down.y(), 0.9);
  const Eigen::Vector3d marker = c + 40 * m;
  const Volume<float> ct = marked_ct(c, marker);
  SliceScene scene;
  scene.ct = &ct;
  SliceOptions o;
  o.pixel_mm = 1.0;
  const SliceView v = render_slice(scene, plane, o);
  int n = 0;
  const Eigen::Vector2d got = white_centroid(v, &n);
  ASSERT_GT(n, 10);
  EXPECT_LT((got - v.pixel_of(marker)).norm(), 2.0);
  // The marker lies left-posterior: right of and below the centre, as the letters say.
  EXPECT_GT(got.x() - v.pixel_of(c).x(), 20.0);
  EXPECT_GT(got.y() - v.pixel_of(c).y(), 20.0);
  EXPECT_NE(orientation_letters(plane.right).find('L'), std::string::npos);
  EXPECT_THROW(make_slice_plane(SlicePlaneKind::kOblique, c), Error);
}

TEST(SlicesTest, ParsersRefuseUnknownNames) {
  EXPECT_EQ(parse_planes("sagittal, axial").size(), 2u);
  EXPECT_THROW(parse_planes("transverse"), Error);
  EXPECT_THROW(parse_palette("rainbow"), Error);
  EXPECT_THROW(parse_hidden_classes("risky"), Error);
  EXPECT_EQ(parse_hidden_classes("medium,dangerous"), (std::array<bool, 3>{false, true, true}));
}

TEST(SlicesTest, CommandWritesOneImagePerPlaneAndRefusesBadInput) {
  // The mini plan centred on (3, -4, 5), with a CT of 40 HU.
  const test::TemporaryFolder dir;
  test::MiniPlanOptions o;
  o.grid = centred_cube_grid(24, 2.0, Eigen::Vector3d(3, -4, 5));
  o.ct = true;
  const test::MiniPlanInputs inputs = test::write_mini_plan_inputs(dir, o);
  run_plan(inputs.request((dir / "plan").string()));

  const std::string base = "slices --plan " + (dir / "plan").string() + " --ct " + inputs.ct;
  ASSERT_EQ(run_cli(base + " --out " + (dir / "s").string()), 0);
  for (const char* f : {"axial.png", "coronal.png", "sagittal.png", "slices.json"}) {
    EXPECT_TRUE(fs::exists(dir / "s" / f)) << f;
  }
  std::ifstream png(dir / "s" / "axial.png", std::ios::binary);
  char sig[8] = {};
  png.read(sig, 8);
  EXPECT_EQ(std::string(sig + 1, 3), "PNG");
  nlohmann::json j;
  std::ifstream(dir / "s" / "slices.json") >> j;
  EXPECT_EQ(j["value"], "svv");
  EXPECT_EQ(j["views"].size(), 3u);
  // The vessel column is cut by the axial plane through the tumor centre: outlined and named.
  bool vessel = false;
  for (const auto& s : j["views"][0]["structures"]) vessel |= s == "vessel";
  EXPECT_TRUE(vessel) << j["views"][0].dump();
  EXPECT_FALSE(j.contains("warnings")) << j.dump();
  // A CT of another scan (another grid, overlapping the plan) is drawn, with a warning in the log
  // and in slices.json naming both grids.
  {
    planning::ImageGeometry other = centred_cube_grid(20, 2.5, Eigen::Vector3d(13, -4, 5));
    write_volume(Volume<float>(other, 40.0f), (dir / "other_ct.nii.gz").string());
    std::string said;
    ASSERT_EQ(run_cli("slices --plan " + (dir / "plan").string() + " --ct " +
                          (dir / "other_ct.nii.gz").string() + " --out " + (dir / "o").string(),
                      &said),
              0)
        << said;
    EXPECT_NE(said.find("other_ct.nii.gz: the CT is not on the grid of the plan's label map"),
              std::string::npos)
        << said;
    EXPECT_NE(said.find("20 x 20 x 20 voxels of 2.5"), std::string::npos) << said;
    nlohmann::json o;
    std::ifstream(dir / "o" / "slices.json") >> o;
    ASSERT_TRUE(o.contains("warnings")) << o.dump();
    EXPECT_NE(o["warnings"][0].get<std::string>().find("it may be another scan"), std::string::npos);
  }

  // Bad input leaves no output folder: an unknown plane, and oblique without area safety.
  EXPECT_NE(run_cli(base + " --planes axial,transverse --out " + (dir / "bad").string()), 0);
  EXPECT_NE(run_cli(base + " --value isbv --region 7 --out " + (dir / "bad").string()), 0);
  EXPECT_FALSE(fs::exists(dir / "bad"));
  // A CT 2 m away from the plan gave black images with rc 0: refused, naming the CT.
  planning::ImageGeometry far = centred_cube_grid(24, 2.0, Eigen::Vector3d(2003, -4, 5));
  write_volume(Volume<float>(far, 40.0f), (dir / "far_ct.nii.gz").string());
  std::string err;
  EXPECT_EQ(run_cli("slices --plan " + (dir / "plan").string() + " --ct " +
                        (dir / "far_ct.nii.gz").string() + " --out " + (dir / "bad").string(),
                    &err, test::Capture::kStderr),
            1);
  EXPECT_NE(err.find("far_ct.nii.gz: the CT does not overlap"), std::string::npos) << err;
  EXPECT_FALSE(fs::exists(dir / "bad"));
  // Slices options that cannot be honoured are refused, not replaced.
  EXPECT_NE(run_cli(base + " --window nan --out " + (dir / "bad").string()), 0);
  EXPECT_NE(run_cli(base + " --pixel 0 --out " + (dir / "bad").string()), 0);
  // Each refused by its own name (an unknown class was blamed on no option, and --pixel 1e308
  // printed its 309 digits into a 1-pixel image).
  EXPECT_NE(run_cli(base + " --hide foo --out " + (dir / "bad").string(), &err,
                    test::Capture::kStderr),
            0);
  EXPECT_EQ(err.rfind("error: --hide:", 0), 0u) << err;
  EXPECT_NE(err.find("\"foo\""), std::string::npos) << err;
  EXPECT_NE(run_cli(base + " --pixel 1e308 --out " + (dir / "bad").string(), &err,
                    test::Capture::kStderr),
            0);
  EXPECT_EQ(err.rfind("error: --pixel:", 0), 0u) << err;
  EXPECT_LT(err.size(), 200u) << err;
  EXPECT_FALSE(fs::exists(dir / "bad"));
}

}  // namespace
}  // namespace crepuscular::planning

// `crepuscular render` through the command line, with no display at all (EGL): the picture of the
// mini plan at the size asked for, the same as the view drawn in process, and refusals that name
// the problem and write nothing.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "pipelines/plan.hpp"
#include "pipelines/render.hpp"
#include "tests/support/cli.hpp"
#include "tests/support/plans.hpp"
#include "tests/support/temporary_folder.hpp"

namespace crepuscular::pipelines {
namespace {

namespace fs = std::filesystem;

class RenderTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    folder_ = new test::TemporaryFolder();
    test::MiniPlanOptions mo;
    mo.ct = true;
    const test::MiniPlanInputs in = test::write_mini_plan_inputs(folder_->path(), mo);
    run_plan(in.request((folder_->path() / "plan").string()));
  }
  static void TearDownTestSuite() { delete folder_; }
  static std::string path(const std::string& name) { return (folder_->path() / name).string(); }
  static test::TemporaryFolder* folder_;
};
test::TemporaryFolder* RenderTest::folder_ = nullptr;

TEST_F(RenderTest, WritesThePictureTheViewDrawsAtTheSizeAskedFor) {
  // Both pictures on Mesa's renderer (the command inherits the setting).
  setenv("LIBGL_ALWAYS_SOFTWARE", "1", 1);
  std::string out;
  // The CT comes from plan.json; no display is needed.
  ASSERT_EQ(test::run_cli("render --plan " + path("plan") + " --view 30,20 --size 320x240 " +
                              "--hide \"\" --out " + path("left.png") + " 2>&1",
                          &out),
            0)
      << out;
  const cv::Mat written = cv::imread(path("left.png"), cv::IMREAD_COLOR);
  ASSERT_EQ(written.cols, 320);
  ASSERT_EQ(written.rows, 240);
  // The same view drawn here: the same pixels.
  const ViewInputs in = load_view_inputs(path("plan"), "", "", {}, "");
  overlay::PlanView3D view(in.plan, in.ct.empty() ? nullptr : &in.ct, {});
  const cv::Mat drawn = render_plan_view(view, overlay::parse_view_angles("30,20"), 320, 240);
  cv::Mat diff;
  cv::absdiff(drawn, written, diff);
  EXPECT_LE(cv::countNonZero(diff.reshape(1) > 2), 0.001 * diff.total() * 3);
  // Something of the plan shows: pixels well above the background.
  cv::Mat grey;
  cv::cvtColor(written, grey, cv::COLOR_BGR2GRAY);
  EXPECT_GT(cv::countNonZero(grey > 80), 500);
}

TEST_F(RenderTest, RefusesNamingTheProblemAndWritesNothing) {
  const std::pair<std::string, std::string> cases[] = {
      {"--view sideways", "view 'sideways'"},
      {"--hide safe,bogus", "'bogus'"},
      {"--value xyz", "\"xyz\""},
      {"--size 10x10", "size 10x10"},
  };
  for (const auto& [flags, message] : cases) {
    std::string out;
    EXPECT_NE(test::run_cli("render --plan " + path("plan") + " " + flags + " --out " +
                                path("bad.png") + " 2>&1",
                            &out),
              0)
        << flags;
    EXPECT_NE(out.find("error:"), std::string::npos) << out;
    EXPECT_NE(out.find(message), std::string::npos) << out;
    EXPECT_FALSE(fs::exists(path("bad.png"))) << flags;
  }
}

}  // namespace
}  // namespace crepuscular::pipelines

// OpenGL for overlay tests: a renderer where this machine can make a context, a skip where not.
#pragma once

#include <memory>
#include <opencv2/core.hpp>

#include "calibration/camera_model.hpp"
#include "overlay/renderer.hpp"

namespace crepuscular::test {

// A renderer of `camera`, or nullptr (the reason on stderr) when no OpenGL 3.3 core context can be
// made here; the test then skips: `if (!renderer) GTEST_SKIP() << "no OpenGL 3.3 core context";`.
std::unique_ptr<overlay::OverlayRenderer> make_renderer(
    const calibration::CameraModel& camera, const overlay::RendererOptions& options = {});

// A BGR video frame of uniform noise, the same for the same seed: a background on which every
// drawn pixel shows.
cv::Mat noise_frame(int width, int height, unsigned seed);

}  // namespace crepuscular::test

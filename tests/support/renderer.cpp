#include "tests/support/renderer.hpp"

#include <iostream>

#include "foundation/error.hpp"

namespace crepuscular::test {

std::unique_ptr<overlay::OverlayRenderer> make_renderer(const calibration::CameraModel& camera,
                                                        const overlay::RendererOptions& options) {
  try {
    return std::make_unique<overlay::OverlayRenderer>(camera, options);
  } catch (const Error& e) {
    std::cerr << "no OpenGL context (" << (options.visible ? "window" : "headless")
              << "): " << e.what() << "\n";
    return nullptr;
  }
}

cv::Mat noise_frame(int width, int height, unsigned seed) {
  cv::Mat frame(height, width, CV_8UC3);
  cv::RNG rng(seed);
  rng.fill(frame, cv::RNG::UNIFORM, 0, 256);
  return frame;
}

}  // namespace crepuscular::test

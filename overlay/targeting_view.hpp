// The targeting view drawn as a picture-in-picture (overlay layer "target"): looking down the
// needle at the plane through the tumor centroid. The polar map of path safety around the needle's
// crossing (where each tilt of the needle would meet the plane, coloured by the class of that
// path; grey: unknown), the tumor's outline filled translucently, its centre, and a white cross
// where the extended needle meets the plane; an arrow at the edge when the crossing is outside.
#pragma once

#include <Eigen/Core>
#include <vector>

#include <opencv2/core.hpp>

#include "planning/trajectories/targeting.hpp"
#include "planning/views/palette.hpp"

namespace crepuscular::overlay {

// Colour (BGR) of the needle's crossing: no other pixel of the view has it.
const cv::Scalar kTargetingCrossColour(255, 255, 255);

// The view as an opaque BGRA image of geometry.size_px square. An invalid geometry (needle
// pointing away) gives the frame with its reason. `uncertainty`: points (CT) of the 95 % ellipse
// where the needle's line crosses the plane (LineUncertainty::ellipse_at_tumor), drawn around
// the cross; none: not drawn.
cv::Mat render_targeting_view(const planning::TargetingGeometry& geometry,
                              planning::Palette palette,
                              const std::vector<Eigen::Vector3d>& uncertainty = {});

// Outlines of a point cloud drawn as discs of radius_px (pixels, OpenCV convention), e.g. the
// tumor's surface voxels: the outer contours of their union, in the same pixel coordinates.
std::vector<std::vector<cv::Point2f>> point_cloud_outlines(
    const std::vector<Eigen::Vector2d>& points_px, double radius_px);

}  // namespace crepuscular::overlay

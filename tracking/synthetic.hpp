// Synthetic camera frames with ground truth: marker boards at scripted poses rendered through the
// camera model (distortion included) onto a background, with noise, blur, lighting, occlusions,
// dropped and corrupt frames. Tag corners land where CameraModel::project puts them: every pixel
// is traced back through the exact inverse of the distortion and edge pixels are supersampled on
// a 55-point Fibonacci lattice (box filter), so edges are anti-aliased and placed to ~1/50 px.
#pragma once

#include <Eigen/Geometry>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "calibration/camera_model.hpp"
#include "tracking/board.hpp"
#include "tracking/frame_source.hpp"

namespace crepuscular::tracking {

struct PoseKeyframe {
  double time_s = 0;
  Eigen::Isometry3d T_cam_board = Eigen::Isometry3d::Identity();
};

struct SceneBoard {
  Board board;
  // Sorted by time. Between keyframes: translation linear, rotation slerp; before the first and
  // after the last keyframe the board stays at that pose.
  std::vector<PoseKeyframe> keyframes;
  bool plate = true;           // draw a white plate under the tags (planar boards in z = 0 only)
  double plate_margin_mm = 10;  // plate border beyond the tags' white rings
};

// A triangle mesh that moves with a board (vertices in that board's frame, mm): the patient's
// skin and the table under it, a needle's shaft and hub. Drawn shaded (Lambert, two-sided, a light
// above the camera) and z-buffered against the boards; a board in front of a mesh hides it.
struct SceneMesh {
  std::string name;
  std::string board;  // the board it is attached to
  std::vector<Eigen::Vector3f> vertices;      // board frame, mm
  std::vector<Eigen::Vector3f> colours;       // per vertex, BGR 0..255 (lit by the shading)
  std::vector<Eigen::Vector3i> triangles;     // vertex indices
};

struct OcclusionBox {
  cv::Rect2d rect_px;
  int64_t first_frame = 0, last_frame = 0;  // inclusive
  double grey = 60;
};

struct SyntheticScene {
  calibration::CameraModel camera;  // default: 1280 x 720, f = 1000 px, centred, no distortion
  std::string background = "gradient";  // "plain", "gradient" or "noise"
  double background_grey = 128;         // plain: this level; gradient/noise: the mean level
  double background_contrast = 60;      // gradient/noise: peak-to-peak amplitude (grey levels)
  std::vector<SceneBoard> boards;
  std::vector<SceneMesh> meshes;  // drawn under the boards' tags, z-buffered
  double fps = 30;
  int64_t frame_count = 90;
  double noise_sigma = 0;  // Gaussian pixel noise (grey levels), new per frame
  double blur_sigma = 0;   // Gaussian blur (px)
  double gain = 1, offset = 0;  // lighting: value = gain * value + offset
  double black = 25, white = 230;  // ink and paper levels before lighting
  std::vector<OcclusionBox> occlusions;
  std::vector<int64_t> dropped_frames;  // never delivered (the frame index skips them)
  std::vector<int64_t> corrupt_frames;  // delivered as a truncated JPEG: empty image + problem
  uint64_t seed = 1;                    // noise and background texture
  int supersampling = 7;  // edge pixels get about this squared samples (the next Fibonacci
                          // number: 7 -> 55); 1 = no anti-aliasing; 1 to 32

  SyntheticScene();
  // Throws Error naming `what` when the scene is unusable.
  void validate(const std::string& what) const;
};

// T_cam_board of a scene board at time t (seconds).
Eigen::Isometry3d pose_at(const SceneBoard& board, double time_s);

// Scene JSON (all fields optional except boards and poses; units mm, degrees, seconds):
// {"camera": {"width": 1280, "height": 720, "fx": 1000, "fy": 1000, "cx": 639.5, "cy": 359.5,
//             "distortion": [k1, k2, p1, p2, k3]}   or "camera": "camera.yaml" (OpenCV YAML),
//   ("distortion_model": "equidistant" with "distortion": [k1, k2, k3, k4] for a fisheye lens),
//  "background": {"type": "gradient" | "plain" | "noise", "grey": 128, "contrast": 60},
//  "boards": "boards.json"  or  [ board objects as in boards.json ],
//  "poses": {"patient": [{"t": 0, "translation_mm": [x, y, z], "rotvec_deg": [rx, ry, rz]}
//                        or ... "quaternion": [w, x, y, z]}, ...],   (T_cam_board keyframes)
//  "plate": true, "fps": 30, "frames": 90, "noise_sigma": 0, "blur_sigma": 0, "gain": 1,
//  "offset": 0, "black": 25, "white": 230, "seed": 1, "supersampling": 7,
//  "occlusions": [{"rect_px": [x, y, w, h], "frames": [first, last], "grey": 60}],
//  "dropped_frames": [..], "corrupt_frames": [..],
//  "meshes": [{"name": "body", "board": "patient", "vertices_mm": [x0, y0, z0, x1, ...],
//              "triangles": [i0, j0, k0, ...], "colours": [b0, g0, r0, ...]}]
//            or "meshes": "meshes.json" (a file holding that array)}
// Paths are relative to the scene file. Errors name the file and the field.
SyntheticScene read_scene(const std::string& path);

// The built-in guidance scene (`crepuscular synth` without --scene): the patient board (2 x 3
// tags of 40 mm, 4 CT fiducials at its corners) at 50 to 58 cm, and the needle board (2 x 2 tags
// of 20 mm) whose needle tip moves toward kTumorTargetInPatient over 3 s at 30 fps.
SyntheticScene builtin_scene();

// Centre of the phantom's tumor in the patient board frame (mm), where the built-in scene aims the
// needle: 90 mm below the board's plane and beside it, as if the board lay on the skin next to the
// entry point. The registration of the guidance work maps the phantom's CT tumor centroid here.
inline const Eigen::Vector3d kTumorTargetInPatient(110.0, 20.0, 90.0);
// Needle tip in the needle board frame (mm): the needle leaves the board centre along +z (into the
// board, away from the camera) and ends 150 mm beyond it.
inline const Eigen::Vector3d kNeedleTipInNeedle(0.0, 0.0, 150.0);

// A breathing patient (`synth --breathing`): the board's keyframes become one per frame, its pose
// raised along its own -z (toward a camera it faces: off the skin) by rise_mm * sin^2(pi t / T),
// T = 60 / breaths_per_minute (end-exhale at 0 s); meshes on the board rise with it. Throws Error
// naming the board when the scene has none of that name or the rate is not 1 to 60 a minute.
void add_breathing(SyntheticScene& scene, const std::string& board, double breaths_per_minute,
                   double rise_mm);
// The rise of that motion at time t (mm) and the breath's fraction then (0 end-exhale, 0.5
// end-inhale).
double breathing_rise_mm(double time_s, double breaths_per_minute, double rise_mm);
double breathing_cycle_fraction(double time_s, double breaths_per_minute);

// Renders the frames of a scene.
class SyntheticRenderer {
 public:
  explicit SyntheticRenderer(SyntheticScene scene);
  ~SyntheticRenderer();
  const SyntheticScene& scene() const { return scene_; }
  double time_of(int64_t frame) const { return double(frame) / scene_.fps; }
  int64_t timestamp_ns_of(int64_t frame) const;
  // The frame's image (BGR 8-bit, noise, blur, lighting and occlusions applied) and the true pose
  // of every board.
  cv::Mat render(int64_t frame, std::vector<TruePose>* truth = nullptr) const;
  // The meshes alone at a frame, before camera effects: mask (CV_8U, 255 where a mesh covers the
  // pixel centre) and depth (CV_32F, camera z in mm, +inf elsewhere); either may be null.
  void render_meshes(int64_t frame, cv::Mat* mask, cv::Mat* depth) const;

 private:
  struct Impl;
  SyntheticScene scene_;
  std::unique_ptr<Impl> impl_;
};

// A FrameSource over a scene: frames 0 .. frame_count-1 without the dropped ones; corrupt frames
// carry their truncated JPEG in Frame::encoded, an empty image and a problem.
std::unique_ptr<FrameSource> make_synthetic_source(SyntheticScene scene,
                                                   const std::string& description);
// "synthetic:SCENE.json" or "synthetic:builtin".
std::unique_ptr<FrameSource> open_synthetic_source(const std::string& scene_path);

}  // namespace crepuscular::tracking

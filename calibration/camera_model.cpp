#include "calibration/camera_model.hpp"

#include "planning/area_safety.hpp"

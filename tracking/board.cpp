#include "tracking/board.hpp"

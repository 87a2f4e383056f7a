#include "recordings/recording.hpp"

// The one exception type of the project: a user-facing error whose message names the file, the
// field, what was found and what was expected. Header-only so every module may throw it.
#pragma once

#include <stdexcept>
#include <string>

namespace crepuscular {

class Error : public std::runtime_error {
 public:
  explicit Error(const std::string& message) : std::runtime_error(message) {}
};

}  // namespace crepuscular

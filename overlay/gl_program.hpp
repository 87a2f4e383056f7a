// A GLSL program from vertex and fragment shader sources, for the overlay's drawing steps. Call
// with the OpenGL context current.
#pragma once

#include <string>

namespace crepuscular::overlay {

// Compiles and links; returns the program name (a GLuint). Throws Error starting with `who`
// ("overlay renderer", "volume rendering") and carrying the driver's log when either step fails.
unsigned int link_gl_program(const char* vertex, const char* fragment, const std::string& who);

}  // namespace crepuscular::overlay

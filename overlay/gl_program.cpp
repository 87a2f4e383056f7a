#include "overlay/gl_program.hpp"

#define GL_GLEXT_PROTOTYPES 1
#include <GL/glcorearb.h>

#include "foundation/error.hpp"

namespace crepuscular::overlay {

namespace {

GLuint compile(GLenum type, const char* source, const std::string& who) {
  const GLuint shader = glCreateShader(type);
  glShaderSource(shader, 1, &source, nullptr);
  glCompileShader(shader);
  GLint ok = 0;
  glGetShaderiv(shader, GL_COMPILE_STATUS, &ok);
  if (!ok) {
    char log[2048];
    glGetShaderInfoLog(shader, sizeof(log), nullptr, log);
    glDeleteShader(shader);
    throw Error(who + ": shader compilation failed: " + log);
  }
  return shader;
}

}  // namespace

unsigned int link_gl_program(const char* vertex, const char* fragment, const std::string& who) {
  const GLuint vs = compile(GL_VERTEX_SHADER, vertex, who);
  GLuint fs = 0;
  try {
    fs = compile(GL_FRAGMENT_SHADER, fragment, who);
  } catch (...) {
    glDeleteShader(vs);
    throw;
  }
  const GLuint program = glCreateProgram();
  glAttachShader(program, vs);
  glAttachShader(program, fs);
  glLinkProgram(program);
  glDeleteShader(vs);
  glDeleteShader(fs);
  GLint ok = 0;
  glGetProgramiv(program, GL_LINK_STATUS, &ok);
  if (!ok) {
    char log[2048];
    glGetProgramInfoLog(program, sizeof(log), nullptr, log);
    glDeleteProgram(program);
    throw Error(who + ": shader link failed: " + log);
  }
  return program;
}

}  // namespace crepuscular::overlay

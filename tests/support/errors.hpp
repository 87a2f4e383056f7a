// Expectations on the project's errors (crepuscular::Error): that a call throws one, and that its
// message names what it should (the file, the field, the value).
#pragma once

#include <gtest/gtest.h>

#include <exception>
#include <initializer_list>
#include <string>
#include <utility>

#include "foundation/error.hpp"

namespace crepuscular::test {

// Expects `f()` to throw crepuscular::Error whose message contains every one of `parts`; no throw,
// or another exception type, is a test failure.
template <typename F>
void expect_error_containing(F&& f, std::initializer_list<std::string> parts) {
  try {
    f();
    ADD_FAILURE() << "expected crepuscular::Error";
  } catch (const Error& e) {
    for (const std::string& part : parts) {
      EXPECT_NE(std::string(e.what()).find(part), std::string::npos)
          << "message \"" << e.what() << "\" lacks \"" << part << "\"";
    }
  } catch (const std::exception& e) {
    ADD_FAILURE() << "expected crepuscular::Error, got another exception: " << e.what();
  }
}

template <typename F>
void expect_error_containing(F&& f, const std::string& part) {
  expect_error_containing(std::forward<F>(f), {part});
}

}  // namespace crepuscular::test

// spdlog, as every file of ours that logs includes it. Include this instead of
// <spdlog/spdlog.h>.
//
// Compile time: spdlog formats each message through fmt::detail::vformat_to<char>, fmt's whole
// formatting engine (integers, floating point, padding). fmt 9's headers do not declare that
// libfmt already holds it, so every file that logged compiled its own copy at -O3 (about 2 s and
// 90 KB of code a file). Declared here as instantiated elsewhere, the files call libfmt's copy:
// the same code, compiled once when fmt was built. foundation/CMakeLists.txt defines
// CREPUSCULAR_FMT_ENGINE_IN_LIBFMT where a program built so links (clang names the function
// differently from the GCC that built Debian's libfmt, so a clang build compiles its own copies).
// fmt 10 and later declare it themselves; a header-only fmt has no library to call.
#pragma once

#include <spdlog/spdlog.h>

#if defined(CREPUSCULAR_FMT_ENGINE_IN_LIBFMT) && defined(SPDLOG_FMT_EXTERNAL) && \
    !defined(FMT_HEADER_ONLY) && FMT_VERSION >= 90000 && FMT_VERSION < 100000
FMT_BEGIN_NAMESPACE
namespace detail {
extern template FMT_API void vformat_to<char>(buffer<char>&, basic_string_view<char>,
                                              basic_format_args<FMT_BUFFER_CONTEXT(char)>,
                                              locale_ref);
}  // namespace detail
FMT_END_NAMESPACE
#endif

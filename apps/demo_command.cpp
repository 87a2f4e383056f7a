// `crepuscular demo` (placeholder).
#include "apps/commands.hpp"

namespace crepuscular::apps {
void add_demo_command(CLI::App& app) { app.add_subcommand("demo", "(not yet)"); }
}  // namespace crepuscular::apps

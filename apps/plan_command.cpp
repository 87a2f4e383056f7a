// `crepuscular plan` (placeholder).
#include "apps/commands.hpp"

namespace crepuscular::apps {
void add_plan_command(CLI::App& app) { app.add_subcommand("plan", "(not yet)"); }
}  // namespace crepuscular::apps

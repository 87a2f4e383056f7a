// `crepuscular phantom` (placeholder).
#include "apps/commands.hpp"

namespace crepuscular::apps {
void add_phantom_command(CLI::App& app) { app.add_subcommand("phantom", "(not yet)"); }
}  // namespace crepuscular::apps

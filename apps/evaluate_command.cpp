// The `crepuscular evaluate` command (being built).
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_evaluate_command(CLI::App& app) { (void)app; }

}  // namespace crepuscular::apps

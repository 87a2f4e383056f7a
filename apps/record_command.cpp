// The `crepuscular record` command (being built).
#include "apps/commands.hpp"

namespace crepuscular::apps {

void add_record_command(CLI::App& app) { (void)app; }

}  // namespace crepuscular::apps

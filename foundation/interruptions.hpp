// What an interrupted run (Ctrl-C, SIGTERM) leaves behind: nothing. Output in progress (staged
// folders, temporary files) registers itself here; on SIGINT or SIGTERM a watcher thread removes
// it and ends the process (exit status 130 or 143), unless a job asked to be told instead
// (graceful stop: guidance and recording finish their files), in which case a second signal ends
// it the hard way.
#pragma once

#include <atomic>
#include <string>

namespace crepuscular {

// Call first thing in main, before any thread starts: blocks SIGINT and SIGTERM in every thread
// and starts the watcher. Without it, signals keep their default action.
void watch_interruptions();

// Paths removed (recursively) when the process is interrupted; unregister when they are
// committed or gone.
void register_partial_output(const std::string& path);
void unregister_partial_output(const std::string& path);

// From now on, a first SIGINT or SIGTERM sets the returned flag (cleared here) instead of ending
// the process.
const std::atomic<bool>* stop_flag_on_interruption();

}  // namespace crepuscular

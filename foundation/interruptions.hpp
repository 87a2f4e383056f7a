// What an interrupted run (Ctrl-C, SIGTERM, SIGHUP) leaves behind: nothing. Output in progress
// (staged folders, temporary files) registers itself here; on SIGINT, SIGTERM or SIGHUP a watcher
// thread removes it, prints an `error:` line and ends the process (exit status 128 + the signal),
// unless a job asked to be told instead (graceful stop: guidance and recording finish their
// files), in which case a second signal ends it the hard way. SIGXFSZ (file size limit) and
// SIGPIPE are ignored, so that the write fails (EFBIG, EPIPE) and the writer's error path reports
// it and removes its output (output_files.hpp).
#pragma once

#include <atomic>
#include <string>

namespace crepuscular {

// Call first thing in main, before any thread starts: blocks SIGINT, SIGTERM and SIGHUP in every
// thread, ignores SIGXFSZ and SIGPIPE, and starts the watcher. Without it, signals keep their
// default action.
void watch_interruptions();

// Paths removed (recursively) when the process is interrupted; unregister when they are
// committed or gone.
void register_partial_output(const std::string& path);
void unregister_partial_output(const std::string& path);

// From now on, a first SIGINT, SIGTERM or SIGHUP sets the returned flag (cleared here) instead of ending
// the process.
const std::atomic<bool>* stop_flag_on_interruption();

}  // namespace crepuscular

#!/usr/bin/env bash
# OpenIGTLink out, as a user runs it: `crepuscular guide` replays the demo's recording headless
# with --igtl-server while the reference library's ReceiveClient example (tests/igtl) reads every
# message; guide's summary line reports the time from each frame's poses (right after tracking)
# to their TRANSFORMs on the socket. STALLED=1 adds a second client that connects and never
# reads: guidance must keep its frame rate. Needs `bash scripts/demo.sh` (demo/) and build/.
set -euo pipefail
cd "$(dirname "$0")/.."
port=$(python3 -c "import socket; s = socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
(
  sleep 0.5
  exec build/tests/igtl/igtl_example_receive_client 127.0.0.1 "$port" > /dev/null 2>&1
) &
if [ "${STALLED:-0}" = 1 ]; then
  python3 - "$port" <<'PY' &
import socket, sys, time
time.sleep(0.5)
s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
time.sleep(20)  # connected, never reading
PY
fi
build/apps/crepuscular guide --plan demo/plan --camera demo/setup/camera.yaml \
  --registration demo/setup/registration.yaml --needle demo/setup/needle.yaml \
  --source "recording:demo/recording?realtime=1" --headless --snapshot-every 100000 \
  --snapshot-at "0:$out/first.png" --igtl-server "$port" 2>&1 | grep -E "OpenIGTLink|frames in"

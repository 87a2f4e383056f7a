// Recordings (DESIGN.md section 8): a folder of frames, their capture timestamps, camera.yaml and
// session.json. Written frame by frame so that a killed recorder leaves a replayable folder.
#pragma once

"""The names in a recon recording: its entity paths and timelines.

Shared by the logger (:mod:`viewer.rerun_log`, which writes them) and the layout
(:mod:`viewer.blueprint`, which shows them); neither owns the other's names. Everything
lives under ``world`` (RIGHT_HAND_Y_DOWN: the camera, its images and depths, the trajectory,
dropped frames, mesh, points), ``tracking`` (a TextLog) and ``medea/<stage>/<term>``. Frames
are on the "frame" sequence timeline (and "time", seconds, when a timestamp is given);
MEDeA's losses on "epoch".
More: docs/outputs.md#what-a-recording-holds
"""

CAMERA = "world/camera"
RGB = f"{CAMERA}/rgb"
PRIOR_DEPTH = f"{CAMERA}/prior_depth"
ADJUSTED_DEPTH = f"{CAMERA}/adjusted_depth"
REFINED_DEPTH = f"{CAMERA}/refined_depth"
CONFIDENCE = f"{CAMERA}/confidence"
TRAJECTORY = "world/trajectory"
DROPPED = "world/dropped"
TRACKING = "tracking"
MESH = "world/mesh"
POINTS = "world/points"
LOSSES = "medea"

FRAME_TIMELINE = "frame"
TIME_TIMELINE = "time"
EPOCH_TIMELINE = "epoch"

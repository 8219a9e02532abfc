"""The names in a recon recording: its entity paths and timelines.

Shared by the logger (:mod:`viewer.rerun_log`, which writes them) and the layout
(:mod:`viewer.blueprint`, which shows them); neither owns the other's names.

Entity layout::

    world                         ViewCoordinates RIGHT_HAND_Y_DOWN (static)
    world/camera                  Transform3D (camera-to-world) + Pinhole (camera_xyz RDF), at
                                  every frame (a streamed estimate: again once the poses are final)
    world/camera/rgb              Image
    world/camera/prior_depth      DepthImage (meter=1)
    world/camera/adjusted_depth   DepthImage (meter=1)
    world/camera/refined_depth    DepthImage (meter=1)
    world/camera/confidence       Image (8-bit grey, 255 = every view agrees)
    world/trajectory/<piece>      LineStrips3D of the camera centres so far (in frame order),
                                  in pieces of TRAJECTORY_PIECE frames (see trajectory_piece)
    world/dropped                 Points3D: centres of frames the quality gate dropped (red)
    tracking                      TextLog: each frame's tracking state (keyframe, tracked,
                                  relocalised, recovered, interpolated, dropped)
    world/mesh                    Mesh3D: static, or one update per ``index`` on "frame"
    world/points                  Points3D (static)
    medea/<stage>/<term>          Scalars on the "epoch" timeline, and the same per-epoch
                                  values as a static BarChart (shown on every timeline)

Frames are on the "frame" sequence timeline (and "time", a duration in seconds, when a
timestamp is given; the logger remembers each frame's timestamp, so everything logged
later for that frame carries it too).
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

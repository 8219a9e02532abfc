"""Camera pose files: what every reader and writer shares (``base``: PoseData, one-line
errors naming the file and line, parsing helpers), the formats (``trajectories``: TUM,
KITTI, per-frame matrices, ...; ``colmap``: COLMAP sparse models) and which pose belongs to
which frame (``matching``). Poses are camera-to-world 4x4, OpenCV camera axes, metres.
"""

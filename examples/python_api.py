"""The pipeline from Python: one typed config, one call, arrays back (and files on disk).

    python examples/python_api.py my_video.mp4 out/ [poses.txt|estimate] [depth_maps/]

With a folder of depth maps (one per frame, matched by name) they are the depth prior;
without, FastDepth predicts it.
"""

import sys
from pathlib import Path

from medea_core import MedeaConfig
from recon.fusion import FusionOptions
from recon.pipeline import PipelineConfig, format_summary, run_pipeline

video, output = Path(sys.argv[1]), Path(sys.argv[2])
config = PipelineConfig(
    input=video,
    output=output,
    stride=2,  # every 2nd frame
    width=640,  # working width in pixels
    fov=65.0,  # horizontal field of view when intrinsics are unknown
    poses=sys.argv[3] if len(sys.argv) > 3 else "estimate",  # or a pose file
    prior="folder" if len(sys.argv) > 4 else "fastdepth",
    prior_path=Path(sys.argv[4]) if len(sys.argv) > 4 else None,
    medea=MedeaConfig.fast(),  # or MedeaConfig() for the paper's settings
    fusion=FusionOptions(voxel_size=None, point_cloud=True),  # None: chosen from the depth range
    rerun="save",  # writes OUTPUT/recording.rrd
)
result = run_pipeline(config)  # a PipelineResult, or a StreamResult when the run streams (same fields)
print(format_summary(result))

# Everything is also available in memory:
depth = result.depth  # (N, H, W) metres, the final depth (a streamed run: its depth frames, read back)
poses = result.poses  # (N, 4, 4) camera-to-world, OpenCV axes
mesh = result.fusion.mesh  # open3d.geometry.TriangleMesh
print(f"{len(depth)} depth maps {depth.shape[1:]}, mesh with {len(mesh.triangles)} triangles")

#!/usr/bin/env bash
# Video (or image folder, or RGB-D dataset folder) to mesh with the `recon` command line.
#
#   examples/run_video.sh my_video.mp4 out/
#
# Writes out/mesh.ply, out/mesh.glb, out/trajectory.txt, out/intrinsics.json, out/depth/,
# out/report.json and out/recording.rrd; then `recon view out/` opens the recording.
set -euo pipefail
INPUT=${1:?usage: $0 INPUT OUTPUT_FOLDER}
OUT=${2:?usage: $0 INPUT OUTPUT_FOLDER}
RECON=${RECON:-recon}   # or: RECON="python -m recon.cli"

# Every 2nd frame at 640 px wide, a 65-degree horizontal field of view (phone main camera;
# pass --intrinsics fx,fy,cx,cy when known), FastDepth prior, estimated poses, MEDeA
# (fast preset), TSDF fusion with an automatic voxel size, Rerun recording saved.
$RECON run "$INPUT" -o "$OUT" --stride 2 --width 640 --fov 65 --rerun save

# The same input with a pose file (TUM, COLMAP, nerfstudio transforms.json, ...) instead:
#   $RECON run "$INPUT" -o "$OUT" --poses poses.txt --intrinsics 525,525,319.5,239.5
# An RGB-D dataset with its own depth and ground-truth poses (TUM, 7-Scenes, ScanNet):
#   $RECON run rgbd_dataset_freiburg1_desk/ -o "$OUT" --prior sensor --poses gt
echo "open the result with: $RECON view $OUT"

"""A top-down slice through the 7-Scenes meshes: sensor depth against prior, MEDeA and the
MVS refinement (issue 19's picture of wavy walls and straight ones).

    python benchmarks/mesh_slice.py [--dataset 7scenes-redkitchen] [--step 4] [--height 0.45]

Fuses, with the ground-truth poses (the refinement: the polished poses it ran with, as
`recon run` does), the FastDepth prior, MEDeA-S (fast) and the refined depth of every
`step`-th frame, samples points on each mesh and on the sensor-depth mesh, and draws those
within +-2.5 cm of one height (`--height`: a fraction of the sensor mesh's vertical extent,
measured along the cameras' mean "down" axis) as seen from above: sensor in black, the
depth being judged in colour, one panel each, a 1 m scale bar. Writes
docs/images/mesh_slice_7scenes.png and prints the share of each depth's slice points within
5 cm of the sensor's slice.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from priors import MAX_DEPTH, VARIANTS, medea_config  # noqa: E402
from report import DATA  # noqa: E402
from report_runs import refined_run  # noqa: E402

from recon.core.medea import adjust_sequence  # noqa: E402
from recon.fusion import FusionOptions, auto_voxel_size, fuse  # noqa: E402
from recon.io.datasets import open_dataset  # noqa: E402
from recon.poses.given.polish import polish_poses  # noqa: E402
from recon.priors import make_prior  # noqa: E402

OUT = ROOT / "docs" / "images" / "mesh_slice_7scenes.png"
BAND = 0.025  # metres either side of the slice height
PIXEL = 0.01  # metres per pixel of the drawing
COLOURS = {"prior (FastDepth)": (40, 110, 230), "MEDeA-S": (30, 160, 60), "MVS refinement": (210, 60, 40)}


def slice_points(mesh, down: np.ndarray, height: float, count: int = 600_000) -> np.ndarray:
    """Points (M, 3) sampled on the mesh within BAND of `height` along `down`."""
    points = np.asarray(mesh.sample_points_uniformly(count).points)
    return points[np.abs(points @ down - height) < BAND]


def plane_axes(down: np.ndarray) -> np.ndarray:
    """(2, 3) orthonormal axes of the horizontal plane (perpendicular to `down`)."""
    a = np.cross(down, [1.0, 0.0, 0.0] if abs(down[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    return np.stack([a, np.cross(down, a)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--dataset", default="7scenes-redkitchen")
    parser.add_argument("--step", type=int, default=4)
    parser.add_argument("--height", type=float, default=0.45)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    torch.set_num_threads(2)
    from scipy.spatial import cKDTree

    dataset = open_dataset(DATA / args.dataset).with_valid_poses().select(stride=args.step)
    rgb, gt = dataset.load_rgb_batch(), dataset.load_depth_batch()
    poses, intrinsics = np.asarray(dataset.poses, np.float64), np.asarray(dataset.intrinsics, np.float64)
    print(f"{args.dataset}: {len(rgb)} frames")
    prior = make_prior("fastdepth", features=True, progress=False)(rgb, intrinsics)
    medea = adjust_sequence(rgb, prior.depth, poses, tuple(intrinsics), prior.features,
                            medea_config("fast", VARIANTS["S8"][1]), progress=False).depth.numpy()
    polished = polish_poses(rgb, prior.depth, poses, tuple(intrinsics), progress=False)
    run = refined_run(rgb, prior, gt, polished.poses, intrinsics, polished.lens_k1, quick=False)
    voxel = auto_voxel_size(float(np.median(gt[(gt > 0) & (gt <= MAX_DEPTH)])))
    options = FusionOptions(voxel_size=voxel, max_depth=MAX_DEPTH, progress=False)
    sensor = fuse(gt, None, poses, intrinsics, options).mesh
    meshes = {"prior (FastDepth)": fuse(prior.depth, None, poses, intrinsics, options).mesh,
              "MEDeA-S": fuse(medea, None, poses, intrinsics, options).mesh,
              "MVS refinement": fuse(run["refined"], None, run["poses"], intrinsics, options,
                                     confidence=run["confidence"]).mesh}

    down = poses[:, :3, 1].mean(0)
    down /= np.linalg.norm(down)
    along = np.asarray(sensor.vertices) @ down
    lo, hi = np.percentile(along, [2, 98])
    height = lo + args.height * (hi - lo)
    axes = plane_axes(down)
    reference = slice_points(sensor, down, height)
    ref_2d = reference @ axes.T
    corner = ref_2d.min(0) - 0.3
    size = np.ceil((ref_2d.max(0) + 0.3 - corner) / PIXEL).astype(int)
    tree = cKDTree(ref_2d)
    panels = []
    for name, mesh in meshes.items():
        pts = slice_points(mesh, down, height) @ axes.T
        close = float(np.mean(tree.query(pts)[0] < 0.05)) if len(pts) else 0.0
        print(f"{name}: {len(pts)} slice points, {100 * close:.1f} % within 5 cm of the sensor's slice")
        panel = np.full((size[1], size[0], 3), 255, np.uint8)
        for points, colour in ((pts, COLOURS[name]), (ref_2d, (0, 0, 0))):
            px = ((points - corner) / PIXEL).astype(int)
            ok = (px[:, 0] >= 0) & (px[:, 0] < size[0]) & (px[:, 1] >= 0) & (px[:, 1] < size[1])
            panel[px[ok, 1], px[ok, 0]] = colour[::-1]
        # Two short lines: one long title ran off the panel.
        for row, text in enumerate((name, f"{100 * close:.0f}% within 5 cm")):
            cv2.putText(panel, text, (10, 26 + 26 * row), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 2, cv2.LINE_AA)
        bar = int(1.0 / PIXEL)
        cv2.line(panel, (10, size[1] - 15), (10 + bar, size[1] - 15), (0, 0, 0), 3)
        cv2.putText(panel, "1 m", (10 + bar // 2 - 15, size[1] - 25), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1)
        panels.append(cv2.copyMakeBorder(panel, 2, 2, 2, 2, cv2.BORDER_CONSTANT, value=(160, 160, 160)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    tmp = args.out.with_suffix(".tmp.png")
    cv2.imwrite(str(tmp), np.concatenate(panels, axis=1))
    tmp.replace(args.out)
    print(f"wrote {args.out} (black: sensor depth's mesh; slice at {height:.2f} m along the cameras' down axis)")


if __name__ == "__main__":
    main()

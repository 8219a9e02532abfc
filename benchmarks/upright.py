"""How upright the GLB of a run stands: its floors' and table tops' normals against glTF's +y.

For each output folder it measures the horizontal surfaces of ``mesh.glb`` as a viewer
shows them, by two methods of its own (not the estimator's in recon.fusion.upright). The
first is the area-weighted mean normal of the triangles within ``--window`` degrees of
vertical. The second finds the planes: of the
surface's points whose local normal is within ``--window`` degrees of +y, RANSAC takes out
planes one by one (inliers within one grid cell, 1/150 of the extent); each holding at
least 3 % of them is a floor, table or shelf, and its normal is the least-squares plane
through its inliers. The table gives, per folder, the angle of
each such plane to +y (their point-weighted mean and the largest), and the same for
``mesh.ply`` taken straight to glTF axes (no upright rotation: what the GLB was before).

Where the recording's world is gravity-aligned (``--gt`` a Record3D folder: ARKit's y up;
a ScanNet scene: z up) it also gives the angle between the estimated up (report.json
``upright.up_in_world``) and gravity, after aligning the run's cameras to the dataset's
(rotation only: the run may have estimated its poses).

Usage::

    .venv/bin/python benchmarks/upright.py OUT [OUT ...] [--gt DATASET ...] [--again] [--json upright]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import machine, table, write_json  # noqa: E402

GRAVITY_UP = {"record3d": np.array([0.0, 1.0, 0.0]), "scannet": np.array([0.0, 0.0, 1.0])}


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(abs(a @ b) / np.linalg.norm(a) / np.linalg.norm(b), 0.0, 1.0))))


def horizontal_planes(points: np.ndarray, window_deg: float, seed: int = 0) -> list[tuple[float, int]]:
    """[(angle of the plane's normal to +y in degrees, its points), ...] of the horizontal
    planes in ``points`` (M, 3), y up (module docstring)."""
    import open3d as o3d

    extent = float(np.linalg.norm(np.percentile(points, 98, axis=0) - np.percentile(points, 2, axis=0)))
    cell = extent / 150.0
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points)).voxel_down_sample(cell)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=4 * cell, max_nn=60))
    keep = np.flatnonzero(np.abs(np.asarray(cloud.normals)[:, 1]) >= np.cos(np.radians(window_deg)))
    flat = cloud.select_by_index(keep)
    total = len(flat.points)
    o3d.utility.random.seed(seed)
    planes = []
    while len(flat.points) >= max(50, 0.03 * total) and len(planes) < 8:
        _, inliers = flat.segment_plane(cell, 3, 1000)
        if len(inliers) < 0.03 * total:
            break
        slab = np.asarray(flat.points)[inliers]
        normal = np.linalg.svd(slab - slab.mean(axis=0), full_matrices=False)[2][2]
        angle = _angle(normal, np.array([0.0, 1.0, 0.0]))
        if angle <= window_deg:
            planes.append((angle, len(inliers)))
        flat = flat.select_by_index(inliers, invert=True)
    return planes


def horizontal_faces(vertices: np.ndarray, faces: np.ndarray, window_deg: float) -> dict:
    """The issue's own measure: the area-weighted mean normal of the triangles within
    ``window_deg`` of vertical (floors, table tops, shelves; each turned to face +y), its
    angle to +y, and the share of the surface those triangles make."""
    corners = vertices[faces]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross / np.maximum(2.0 * area, 1e-18)[:, None]
    flat = np.abs(normal[:, 1]) >= np.cos(np.radians(window_deg))
    if not flat.any():
        return {"mean_normal_deg": None, "share": 0.0}
    turned = normal[flat] * np.sign(normal[flat, 1])[:, None]
    mean = (turned * area[flat, None]).sum(axis=0)
    return {"mean_normal_deg": _angle(mean, np.array([0.0, 1.0, 0.0])), "share": float(area[flat].sum() / area.sum())}


def summary(planes: list[tuple[float, int]]) -> dict:
    if not planes:
        return {"planes": 0, "mean_deg": None, "max_deg": None}
    angles, weights = np.array([a for a, _ in planes]), np.array([w for _, w in planes], float)
    return {"planes": len(planes), "mean_deg": float(angles @ weights / weights.sum()), "max_deg": float(angles.max())}


def gravity_error(folder: Path, report: dict, gt: Path) -> float | None:
    """Degrees between report.json's up and the dataset's gravity, in the run's world."""
    from recon.io.datasets import detect_kind, open_dataset
    from recon.io.pose_formats.trajectories import read_poses

    kind = detect_kind(gt)
    if kind not in GRAVITY_UP or "upright" not in report:
        return None
    run = read_poses(folder / "trajectory.txt").poses
    truth = np.asarray(open_dataset(gt).poses)[np.asarray(report["frames"]["indices"])[: len(run)]]
    # The rotation taking the run's camera orientations onto the dataset's (least squares).
    u, _, vt = np.linalg.svd(np.einsum("nij,nkj->ik", truth[:, :3, :3], run[:, :3, :3]))
    world = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    return _angle(np.asarray(report["upright"]["up_in_world"]), world.T @ GRAVITY_UP[kind])


def reference_up(folder: Path) -> np.ndarray:
    """The floor's normal in the world of ``folder``, a run of the same recording with its
    poses given and the sensor's depth fused (``--prior sensor --no-medea --refine none``):
    of the directions within 35 degrees of its cameras' up, the one the most triangle area
    lies within 4 degrees of (floors and table tops), refined by the area-weighted mean of
    those triangles' normals. Sensor depth is flat where the floor is, FastDepth's is not."""
    import open3d as o3d

    from recon.fusion.upright import camera_up, directions_around
    from recon.io.pose_formats.trajectories import read_poses

    mesh = o3d.io.read_triangle_mesh(str(folder / "mesh.ply"))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area = np.linalg.norm(cross, axis=1)
    keep = area > 0
    normals, area = cross[keep] / area[keep, None], area[keep]
    rng = np.random.default_rng(0)
    pick = rng.choice(len(area), size=min(len(area), 50_000), replace=False, p=area / area.sum())
    sample = normals[pick]  # drawn by area: each counts alike
    guess = camera_up(read_poses(folder / "trajectory.txt").poses)
    candidates = directions_around(guess, 35.0, 0.5)
    score = np.concatenate([(np.abs(candidates[s : s + 256] @ sample.T) >= np.cos(np.radians(4.0))).mean(axis=1)
                            for s in range(0, len(candidates), 256)])
    best = candidates[int(np.argmax(score))]
    near = np.abs(normals @ best) >= np.cos(np.radians(3.0))
    mean = (normals[near] * np.sign(normals[near] @ best)[:, None] * area[near, None]).sum(axis=0)
    return mean / np.linalg.norm(mean)


def estimated_again(folder: Path, ply) -> dict:
    """report.json's "upright" as this checkout's estimator gives it from the folder's
    mesh.ply and trajectory.txt (for folders an earlier version wrote)."""
    from recon.fusion.upright import estimate_upright
    from recon.io.pose_formats.trajectories import read_poses

    return estimate_upright(read_poses(folder / "trajectory.txt").poses, np.asarray(ply.vertices)).to_dict()


def measure(folder: Path, gt: Path | None, window_deg: float, again: bool = False,
            reference: np.ndarray | None = None) -> dict:
    import open3d as o3d
    import trimesh

    from recon.export.writers import to_gltf_axes

    report = json.loads((folder / "report.json").read_text())
    ply = o3d.io.read_triangle_mesh(str(folder / "mesh.ply"))
    raw = to_gltf_axes(np.asarray(ply.vertices))
    if again:
        report["upright"] = estimated_again(folder, ply)
        turn = np.asarray(report["upright"]["transform"])[:3, :3]
        glb = trimesh.Trimesh(to_gltf_axes(np.asarray(ply.vertices), turn), np.asarray(ply.triangles), process=False)
    else:
        glb = trimesh.load(folder / "mesh.glb", file_type="glb", force="mesh", process=False)
    upright = report.get("upright") or {}
    return {"folder": str(folder), "tilt_deg": upright.get("tilt_deg"), "source": upright.get("source"),
            "glb": summary(horizontal_planes(np.asarray(glb.vertices), window_deg)),
            "without_rotation": summary(horizontal_planes(raw, window_deg)),
            "glb_faces": horizontal_faces(np.asarray(glb.vertices), np.asarray(glb.faces), window_deg),
            "without_rotation_faces": horizontal_faces(raw, np.asarray(ply.triangles), window_deg),
            "gravity_error_deg": gravity_error(folder, report, gt) if gt else None,
            "reference_error_deg": None if reference is None or not upright else
            _angle(np.asarray(upright["up_in_world"]), reference)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", nargs="+", type=Path, help="output folders of recon run")
    parser.add_argument("--gt", nargs="*", type=Path, default=[], help="the dataset of each folder (or none)")
    parser.add_argument("--window", type=float, default=25.0, help="degrees from +y a surface may be to count")
    parser.add_argument("--again", action="store_true",
                        help="estimate the up again with this checkout's code from mesh.ply and trajectory.txt")
    parser.add_argument("--reference", type=Path,
                        help="a sensor-depth run of the same recording and world: its floor normal (reference_up) "
                             "is the truth every folder's up is measured against")
    parser.add_argument("--json", default="upright", help="results file name under benchmarks/results")
    args = parser.parse_args()
    gts = list(args.gt) + [None] * (len(args.folders) - len(args.gt))
    reference = reference_up(args.reference) if args.reference else None
    rows = [measure(f, g, args.window, args.again, reference) for f, g in zip(args.folders, gts)]

    def fmt(x):
        return "-" if x is None else f"{x:.1f}"

    print(table(["folder", "tilt", "source", "GLB faces deg (share)", "before faces deg", "GLB planes",
                 "GLB mean / max deg", "before mean / max deg", "vs gravity deg",
                 "vs reference deg"],
                [[Path(r["folder"]).name, fmt(r["tilt_deg"]), r["source"] or "-",
                  f"{fmt(r['glb_faces']['mean_normal_deg'])} ({r['glb_faces']['share']:.2f})",
                  fmt(r["without_rotation_faces"]["mean_normal_deg"]), r["glb"]["planes"],
                  f"{fmt(r['glb']['mean_deg'])} / {fmt(r['glb']['max_deg'])}",
                  f"{fmt(r['without_rotation']['mean_deg'])} / {fmt(r['without_rotation']['max_deg'])}",
                  fmt(r["gravity_error_deg"]), fmt(r["reference_error_deg"])] for r in rows]))
    path = write_json(args.json, {"machine": machine(), "window_deg": args.window, "rows": rows,
                                  "reference": None if reference is None else reference.tolist()})
    print(f"written {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

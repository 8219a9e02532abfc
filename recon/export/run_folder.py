"""Reading a finished output folder back for the exports (:mod:`recon.export.tools`).

This module owns what the exports take from an output folder (read through
:mod:`recon.io.output_folder`): the report, trajectory, intrinsics, depth maps per frame,
upright transform and mesh points, and the frames, which the folder does not keep:
:func:`decoded_frames` decodes them again from the run's input with the run's selection and
resamples them as the run did, so the images are the pinhole images the depth and mesh were
made from. World: the run's, turned upright when report.json has ``upright.transform`` T,
world' = T @ world (:attr:`RunFiles.world_poses`, :meth:`RunFiles.to_world`).
More: docs/export.md#what-is-written
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from recon.errors import ReconInputError
from recon.io.output_folder import (
    DEPTH_DIR,
    INTRINSICS_JSON,
    POINT_CLOUD_PLY,
    REPORT_JSON,
    TRAJECTORY,
    depth_files,
    frame_name,
    read_mesh,
    read_report,
)
from recon.io.pose_formats.trajectories import read_poses

DEFAULT_MAX_POINTS = 100_000
POINTS_SEED = 0  # the subset of the mesh's vertices is the same on every export


# --------------------------------------------------------------------------- the run's files


@dataclass(frozen=True)
class RunFiles:
    """What the exports take from one output folder (not one written as segments).

    indices (N,): source frame numbers of the poses; timestamps (N,) seconds; poses (N, 4,
    4) camera-to-world in the run's world, OpenCV axes; intrinsics (N, 4) fx fy cx cy in
    pixels of the depth maps, pixel centres at integers; size (H, W) of the depth maps;
    depth: source frame number -> its depth map (frames of a streamed run may have none);
    transform: the upright transform (4, 4) or None.
    """

    folder: Path
    report: dict
    indices: np.ndarray
    timestamps: np.ndarray
    poses: np.ndarray
    intrinsics: np.ndarray
    size: tuple[int, int]
    depth: dict[int, Path]
    transform: np.ndarray | None

    @property
    def world_poses(self) -> np.ndarray:
        """The poses in the exported world (upright when the run has a transform)."""
        return self.poses if self.transform is None else self.transform @ self.poses

    def to_world(self, xyz: np.ndarray) -> np.ndarray:
        """Points (M, 3) of the run's world in the exported world."""
        t = self.transform
        return xyz if t is None else xyz @ t[:3, :3].T + t[:3, 3]

    def stem(self, row: int) -> str:
        """File stem of the row-th frame in the exports (frame_000123: its source frame number)."""
        return frame_name(int(self.indices[row]))


def read_run_report(folder: Path) -> dict:
    """report.json of output folder `folder`; one-line ReconInputError when there is none."""
    if not folder.is_dir():
        raise ReconInputError(f"{folder}: no such output folder")
    report = read_report(folder)
    if report is None:
        raise ReconInputError(f"{folder}: not an output folder of 'recon run' (no {REPORT_JSON})")
    return report


def segment_folders(folder: Path, report: dict) -> list[str]:
    """Segment folder names of a run written as segments ([] for a single reconstruction)."""
    segments = report.get("segments") or []
    try:
        return [str(s["folder"]) for s in segments]
    except (KeyError, TypeError):
        raise ReconInputError(f"{folder / REPORT_JSON}: unreadable segments list") from None


def upright_transform(report: dict, where) -> np.ndarray | None:
    """report.json's ``upright.transform`` (4, 4), checked to be rigid; None when absent."""
    upright = report.get("upright")
    if not isinstance(upright, dict) or upright.get("transform") is None:
        return None
    try:
        t = np.asarray(upright["transform"], dtype=np.float64)
    except (TypeError, ValueError):
        t = np.zeros(0)
    rigid = (t.shape == (4, 4) and np.isfinite(t).all() and np.allclose(t[3], [0, 0, 0, 1], atol=1e-9)
             and np.allclose(t[:3, :3] @ t[:3, :3].T, np.eye(3), atol=1e-6) and np.linalg.det(t[:3, :3]) > 0)
    if not rigid:
        raise ReconInputError(f"{where}: upright.transform is not a 4x4 rigid transform")
    return t


def _intrinsics(folder: Path, count: int) -> tuple[np.ndarray, tuple[int, int]]:
    """((N, 4) fx fy cx cy per pose, (H, W)) from intrinsics.json."""
    path = folder / INTRINSICS_JSON
    if not path.is_file():
        raise ReconInputError(f"{folder}: no {INTRINSICS_JSON} (not a complete output folder of 'recon run')")
    try:
        data = json.loads(path.read_text())
        shared = [float(data[k]) for k in ("fx", "fy", "cx", "cy")]
        size = (int(data["height"]), int(data["width"]))
        per_frame = data.get("frames")
        rows = ([[float(f[k]) for k in ("fx", "fy", "cx", "cy")] for f in per_frame] if per_frame
                else [shared] * count)
    except (ValueError, KeyError, TypeError) as error:
        raise ReconInputError(f"{path}: unreadable intrinsics ({error})") from None
    if data.get("model", "PINHOLE") != "PINHOLE":
        raise ReconInputError(f"{path}: camera model {data['model']!r}; the exports know PINHOLE only")
    if len(rows) != count:
        raise ReconInputError(f"{path}: {len(rows)} per-frame intrinsics for {count} poses in {TRAJECTORY}")
    return np.asarray(rows, dtype=np.float64), size


def _depth_of(folder: Path, frames: dict, indices: np.ndarray) -> dict[int, Path]:
    """Source frame number -> depth map, matched as report.json says (a streamed run names
    the frames that got depth: depth_indices, depth_names; older reports: every frame, in
    natural order)."""
    if not (folder / DEPTH_DIR).is_dir():
        return {}
    depth_indices = [int(i) for i in frames.get("depth_indices", indices)]
    names = frames.get("depth_names", frames.get("names"))
    if names is not None and len(names) != len(depth_indices):
        raise ReconInputError(f"{folder / REPORT_JSON}: {len(names)} depth names for {len(depth_indices)} frames")
    files = depth_files(folder, names)
    if files and len(files) != len(depth_indices):
        raise ReconInputError(f"{folder / DEPTH_DIR}: {len(files)} depth maps for {len(depth_indices)} frames in "
                              f"{REPORT_JSON}")
    return dict(zip(depth_indices, files))


def read_run(folder) -> RunFiles:
    """The poses, camera, depth maps and upright transform of output folder `folder`; one-line
    ReconInputError when it is not a complete output folder of `recon run` or was written as
    segments (each segment folder is one)."""
    folder = Path(folder)
    report = read_run_report(folder)
    segments = segment_folders(folder, report)
    if segments:
        raise ReconInputError(f"{folder}: a run written as segments ({', '.join(segments)}): export each segment "
                              "folder (recon export OUT exports them all)")
    if not (folder / TRAJECTORY).is_file():
        raise ReconInputError(f"{folder}: no {TRAJECTORY} (not a complete output folder of 'recon run')")
    trajectory = read_poses(folder / TRAJECTORY, "tum")
    count = len(trajectory.poses)
    frames = report.get("frames") or {}
    try:
        indices = np.asarray(frames.get("indices", range(count)), dtype=np.int64)
    except (TypeError, ValueError):
        raise ReconInputError(f"{folder / REPORT_JSON}: unreadable frames.indices") from None
    if len(indices) != count:
        raise ReconInputError(f"{folder / TRAJECTORY}: {count} poses for {len(indices)} frames in {REPORT_JSON}")
    intrinsics, size = _intrinsics(folder, count)
    return RunFiles(folder, report, indices, np.asarray(trajectory.timestamps, np.float64), trajectory.poses,
                    intrinsics, size, _depth_of(folder, frames, indices),
                    upright_transform(report, folder / REPORT_JSON))


def mesh_points(folder, max_points: int = DEFAULT_MAX_POINTS, seed: int = POINTS_SEED
                ) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (M, 3) float64 in the run's world, rgb (M, 3) uint8) of the fused surface: the
    vertices of mesh.ply (point_cloud.ply when there is no mesh), a uniform random subset of
    `max_points` of them (fixed `seed`) when there are more. Empty arrays without either."""
    import open3d as o3d

    folder = Path(folder)
    xyz, colours = np.zeros((0, 3)), None
    mesh = read_mesh(folder)
    if mesh is not None and len(mesh.vertices):
        xyz, colours = np.asarray(mesh.vertices), np.asarray(mesh.vertex_colors) if mesh.has_vertex_colors() else None
    elif (folder / POINT_CLOUD_PLY).is_file():
        cloud = o3d.io.read_point_cloud(str(folder / POINT_CLOUD_PLY))
        xyz, colours = np.asarray(cloud.points), np.asarray(cloud.colors) if cloud.has_colors() else None
    rgb = (np.full((len(xyz), 3), 128, np.uint8) if colours is None
           else np.clip(np.round(colours * 255.0), 0, 255).astype(np.uint8))
    if len(xyz) > max_points:
        keep = np.sort(np.random.default_rng(seed).choice(len(xyz), int(max_points), replace=False))
        xyz, rgb = xyz[keep], rgb[keep]
    return np.asarray(xyz, np.float64), rgb


# --------------------------------------------------------------------------- the frames


def run_input(run: RunFiles, given) -> Path:
    """The run's input: `given`, else report.json's input.path (a relative one is tried from
    the working folder, then from each folder above the output folder)."""
    if given is not None:
        path = Path(given)
        if not path.exists():
            raise ReconInputError(f"{path}: no such file or folder (the run's input)")
        return path
    recorded = (run.report.get("input") or {}).get("path")
    if not recorded:
        raise ReconInputError(f"{run.folder / REPORT_JSON}: names no input (input.path); give it with --input")
    path = Path(recorded)
    candidates = [path] if path.is_absolute() else [path] + [p / path for p in run.folder.resolve().parents]
    for candidate in candidates:
        if candidate.exists():
            return candidate
    raise ReconInputError(f"{path}: the run's input is gone (report.json input.path); the export decodes the frames "
                          "again from it: give its new place with --input")


def _resampling(run: RunFiles) -> tuple[dict | None, np.ndarray | None, float, float]:
    """How the run resampled its frames: (the known lens undone as they were decoded or None,
    the angular velocity (N, 3) rad/s to unroll a rolling shutter with or None, its readout
    in seconds, the radial term undone after the poses or 0)."""
    from recon.geometry.lens import worth_undistorting
    from recon.geometry.rolling_shutter import angular_velocity

    report = run.report
    lens = (report.get("intrinsics") or {}).get("undistorted")
    poses = report.get("poses") or {}
    k1 = float(poses.get("lens_k1") or 0.0)
    undone = poses.get("frames_undistorted")
    if undone is None:  # streamed runs (and older reports) follow the rule of the run
        undone = k1 != 0.0 and worth_undistorting(tuple(run.intrinsics[0]), run.size, k1)
    readout_ms = float((report.get("options") or {}).get("rolling_shutter") or 0.0)
    # A streamed run with estimated poses tracks once and leaves its frames as recorded.
    streamed_estimate = report.get("streamed") and str(poses.get("source", "")).startswith("estimated")
    omega = None
    if readout_ms > 0 and not streamed_estimate:
        omega = angular_velocity(run.poses, run.timestamps)
    return lens, omega, readout_ms / 1000.0, k1 if undone else 0.0


def decoded_frames(run: RunFiles, input_path, progress: bool = False) -> Iterator[tuple[int, np.ndarray]]:
    """(row, rgb (H, W, 3) uint8) for every pose of the run (row: its position in the
    trajectory), decoded from `input_path` with the run's selection and working width and
    resampled as the run resampled them (module docstring)."""
    from tqdm.auto import tqdm

    from recon.core.sequence import Sequence
    from recon.io.frames import open_source

    options = run.report.get("options") or {}
    # Stride 1 unless the run gave one, and no frame limit: a superset of the run's frames
    # (a stride raised for the frame budget, frames left out by the pose gate), picked by number.
    source = open_source(input_path, stride=options.get("stride") or 1, start_time=options.get("start_time"),
                         end_time=options.get("end_time"), width=options.get("width"), fps=options.get("fps"))
    if tuple(source.shape) != tuple(run.size):
        raise ReconInputError(f"{input_path}: frames decode at {source.shape[1]}x{source.shape[0]}, the run's depth "
                              f"maps are {run.size[1]}x{run.size[0]} (not the input of {run.folder}?)")
    lens, omega, readout, k1 = _resampling(run)
    if lens is not None:
        source.to_pinhole(tuple(run.intrinsics[0]), lens["distortion"], lens.get("source", "given"))
    row_of = {int(i): k for k, i in enumerate(run.indices)}
    last, found = max(row_of), set()
    bar = tqdm(total=len(row_of), desc="export frames", unit="frame", disable=not progress, leave=False)
    try:
        for frame in source:
            if frame.index > last:
                break
            row = row_of.get(int(frame.index))
            if row is None:
                continue
            seq = Sequence(run.indices[row:row + 1], run.timestamps[row:row + 1], frame.rgb[None], [run.stem(row)],
                           intrinsics=tuple(float(v) for v in run.intrinsics[row]))
            if omega is not None:
                seq, _ = seq.unroll(omega[row:row + 1], readout)
            if k1:
                seq = seq.undistort(k1)
            found.add(row)
            bar.update()
            yield row, seq.rgb[0]
    finally:
        bar.close()
    if len(found) != len(row_of):
        missing = sorted(int(run.indices[k]) for k in set(range(len(row_of))) - found)
        raise ReconInputError(f"{input_path}: frames {', '.join(map(str, missing[:5]))} of the run are not in the "
                              f"input (not the input of {run.folder}?)")



__all__ = [
    "DEFAULT_MAX_POINTS",
    "POINTS_SEED",
    "RunFiles",
    "decoded_frames",
    "mesh_points",
    "read_run",
    "read_run_report",
    "run_input",
    "segment_folders",
    "upright_transform",
]

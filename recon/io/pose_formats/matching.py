"""Which name each selected frame goes by, and which pose of a pose file belongs to it.

This module owns :func:`frame_names` (the per-frame names of depth files, also used to
match a depth-folder prior and a pose file's frame names) and :func:`match_pose_file`
(the poses and intrinsics of a read pose file for the selected frames).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from recon.errors import ReconInputError
from recon.geometry.camera import resize_intrinsics
from recon.geometry.rigid import interpolate_poses
from recon.io.frames import DatasetSource, ImageFolderSource
from recon.io.output_folder import frame_name
from recon.io.pose_formats.base import PoseData
from recon.io.source import FrameSource


def frame_names(source: FrameSource, indices) -> list[str]:
    """Per-frame names used for depth files (and to match a depth-folder prior) of the
    frames at source `indices` (N,): image file stems, a dataset's colour file stems (of all
    its selected frames), else ``frame_000123`` from the source frame index."""
    if isinstance(source, ImageFolderSource):
        return [source.files[i].stem for i in indices]
    if isinstance(source, DatasetSource):
        return [Path(p).stem for p in source.dataset.rgb_paths]
    return [frame_name(i) for i in indices]


def match_pose_file(data: PoseData, source: FrameSource, indices, timestamps):
    """(poses (N, 4, 4), intrinsics at working size or None) of a read pose file, matched to
    the selected frames: source frame `indices` (N,) int and their `timestamps` (N,) seconds.

    Matching: by frame name when the file names frames (COLMAP, nerfstudio, matrices),
    else by source frame index when the file has one pose per input frame, else by
    position when it has one per selected frame, else by timestamp (TUM).
    """
    indices, timestamps = np.asarray(indices), np.asarray(timestamps, np.float64)
    path = data.path
    n_total = {ImageFolderSource: lambda s: len(s.files), DatasetSource: lambda s: len(s.full)}.get(
        type(source), lambda s: getattr(s, "frame_count_meta", 0))(source)
    poses = None
    if data.names is not None:
        lookup = {Path(str(n)).stem: k for k, n in enumerate(data.names)}
        keys = frame_names(source, indices)
        if all(k in lookup for k in keys):
            poses = data.poses[[lookup[k] for k in keys]]
    if poses is None and len(data) == n_total and indices.max() < len(data):
        poses = data.poses[indices]
    if poses is None and len(data) == len(indices):
        poses = data.poses
    if poses is None and data.timestamps is not None:
        stamps = timestamps + (data.timestamps.min() if data.timestamps.min() > 1e6 else 0.0)
        poses, valid = interpolate_poses(stamps, data.timestamps, data.poses)
        if not valid.all():
            raise ReconInputError(
                f"{path}: no pose near the timestamp of frame {int(indices[np.argmin(valid)])} "
                f"({len(data)} poses for {len(indices)} frames)"
            )
    if poses is None:
        raise ReconInputError(
            f"{path}: {len(data)} poses cannot be matched to the {len(indices)} selected frames "
            f"(need one per input frame, one per selected frame, frame names or timestamps)"
        )
    bad = ~np.isfinite(poses).all(axis=(1, 2))
    if bad.any():
        raise ReconInputError(f"{path}: invalid pose for frame {int(indices[np.argmax(bad)])}")
    intrinsics = None
    if data.intrinsics is not None and data.intrinsics.get("width"):
        k = data.intrinsics
        native = (int(k["height"]), int(k["width"]))
        intrinsics = resize_intrinsics((k["fx"], k["fy"], k["cx"], k["cy"]), native, source.shape)
    return poses, intrinsics

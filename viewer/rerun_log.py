"""Rerun logging for the pipeline: frames, cameras, trajectory, mesh and MEDeA losses.

Written against rerun-sdk 0.41. Every call goes to a dedicated ``rr.RecordingStream``
(never the global one), so several loggers can live in one process.

Entity layout::

    world                         ViewCoordinates RIGHT_HAND_Y_DOWN (static)
    world/camera                  Transform3D (camera-to-world) + Pinhole (camera_xyz RDF)
    world/camera/rgb              Image
    world/camera/prior_depth      DepthImage (meter=1)
    world/camera/adjusted_depth   DepthImage (meter=1)
    world/trajectory              LineStrips3D of the camera centres so far
    world/dropped                 Points3D: centres of frames the quality gate dropped (red)
    tracking                      TextLog: each frame's tracking state (keyframe, tracked,
                                  relocalised, recovered, interpolated, dropped)
    world/mesh                    Mesh3D (static)
    world/points                  Points3D (static)
    medea/<stage>/<term>          Scalars on the "epoch" timeline

Frames are on the "frame" sequence timeline (and "time", a duration in seconds, when a
timestamp is given).

Conventions are the project's: camera-to-world 4x4 poses, OpenCV camera axes (x right,
y down, z forward), z-depth in metres with 0 = invalid, intrinsics ``fx, fy, cx, cy`` in
pixels of the stored image with pixel centres at integer coordinates. Rerun puts the
centre of the top-left pixel at (0.5, 0.5) (its default principal point is
``resolution / 2``), so the principal point is logged as ``cx + 0.5, cy + 0.5``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

MODES = ("spawn", "save", "serve", "off")

CAMERA = "world/camera"
RGB = f"{CAMERA}/rgb"
PRIOR_DEPTH = f"{CAMERA}/prior_depth"
ADJUSTED_DEPTH = f"{CAMERA}/adjusted_depth"
REFINED_DEPTH = f"{CAMERA}/refined_depth"
CONFIDENCE = f"{CAMERA}/confidence"
TRAJECTORY = "world/trajectory"
DROPPED = "world/dropped"
TRACKING = "tracking"
# Tracking states that mean trouble are logged as warnings (rerun's TextLog level).
_TROUBLE = ("interpolated", "dropped", "lost")
MESH = "world/mesh"
POINTS = "world/points"
LOSSES = "medea"


def default_mode() -> str:
    """"spawn" when a display is available (DISPLAY or WAYLAND_DISPLAY set), else "off"."""
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return "spawn"
    return "off"


def _to_numpy(array: Any) -> np.ndarray:
    """numpy view of an array-like, torch tensors (any device, with grad) included."""
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    return np.asarray(array)


def _as_intrinsics(intrinsics: Any) -> tuple[float, float, float, float]:
    """(fx, fy, cx, cy) from a 4-sequence or a 3x3 camera matrix."""
    k = _to_numpy(intrinsics).astype(np.float64)
    if k.shape == (3, 3):
        return float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2])
    if k.shape == (4,):
        return tuple(float(v) for v in k)  # type: ignore[return-value]
    raise ValueError(f"intrinsics must be (fx, fy, cx, cy) or a 3x3 matrix, got shape {k.shape}")


def _rgb_uint8(rgb: Any) -> np.ndarray:
    """(H, W, 3|4) or (H, W) uint8; floats are taken to be in [0, 1]."""
    image = _to_numpy(rgb)
    if image.ndim == 3 and image.shape[0] in (1, 3, 4) and image.shape[-1] not in (1, 3, 4):
        image = np.moveaxis(image, 0, -1)  # CHW -> HWC
    if image.ndim == 3 and image.shape[-1] == 1:
        image = image[..., 0]
    if image.dtype != np.uint8:
        image = np.clip(np.nan_to_num(image.astype(np.float32)) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)


def _depth_f32(depth: Any) -> np.ndarray:
    """(H, W) float32 metres, non-finite and negative values set to 0 (invalid)."""
    d = _to_numpy(depth).astype(np.float32)
    if d.ndim == 3 and d.shape[0] == 1:
        d = d[0]
    elif d.ndim == 3 and d.shape[-1] == 1:
        d = d[..., 0]
    if d.ndim != 2:
        raise ValueError(f"depth must be (H, W), got shape {d.shape}")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    return np.ascontiguousarray(d)


def _logged_size(height: int, width: int, max_width: int | None) -> tuple[int, int]:
    if max_width is None or width <= max_width:
        return height, width
    return max(1, round(height * max_width / width)), max_width


def _resize_rgb(image: np.ndarray, height: int, width: int) -> np.ndarray:
    if image.shape[:2] == (height, width):
        return image
    from PIL import Image as PILImage  # pillow is a rerun-sdk dependency

    return np.asarray(PILImage.fromarray(image).resize((width, height), PILImage.Resampling.BOX))


def _resize_nearest(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize (never mixes valid depth with 0 = invalid)."""
    h, w = depth.shape
    if (h, w) == (height, width):
        return depth
    rows = np.minimum(((np.arange(height) + 0.5) * h / height).astype(np.int64), h - 1)
    cols = np.minimum(((np.arange(width) + 0.5) * w / width).astype(np.int64), w - 1)
    return np.ascontiguousarray(depth[rows[:, None], cols[None, :]])


def _stage_losses(stage: Any) -> Mapping[str, Any]:
    """A stage's {term: [per-epoch values]}: a mapping, or an object with ``.losses``
    (``medea_core.optimize.StageHistory``)."""
    if isinstance(stage, Mapping):
        return stage
    losses = getattr(stage, "losses", None)
    return losses if isinstance(losses, Mapping) else {}


class RerunLogger:
    """Logs the pipeline to Rerun.

    mode: "spawn" (desktop viewer), "save" (write ``path``, an .rrd), "serve" (gRPC server
    plus web viewer on localhost), "off" (every call is a no-op); None = ``default_mode()``.
    max_width: images wider than this are downscaled for logging (intrinsics follow);
    None logs full resolution. jpeg_quality: if set, RGB is logged JPEG-compressed.
    """

    def __init__(
        self,
        mode: str | None = None,
        path: str | Path | None = None,
        app_id: str = "recon",
        *,
        max_width: int | None = 320,
        jpeg_quality: int | None = None,
        grpc_port: int | None = None,
        web_port: int | None = None,
        open_browser: bool = False,
    ) -> None:
        mode = default_mode() if mode is None else mode
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if mode == "save" and path is None:
            raise ValueError('mode "save" needs a path to an .rrd file')
        self.mode = mode
        self.path = Path(path) if path is not None else None
        self.max_width = max_width
        self.jpeg_quality = jpeg_quality
        self.url: str | None = None  # gRPC URL in "serve" mode
        self._centres: list[np.ndarray] = []
        self._dropped: list[np.ndarray] = []
        self._rec: rr.RecordingStream | None = None
        if mode == "off":
            return

        rec = rr.RecordingStream(app_id)
        if mode == "spawn":
            rec.spawn()
        elif mode == "save":
            self.path.parent.mkdir(parents=True, exist_ok=True)
            rec.save(self.path)
        else:  # serve
            self.url = rec.serve_grpc(grpc_port=grpc_port)
            rr.serve_web_viewer(web_port=web_port, open_browser=open_browser, connect_to=self.url)
        self._rec = rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)

    @property
    def enabled(self) -> bool:
        return self._rec is not None

    # ------------------------------------------------------------------ frames

    def log_frame(
        self,
        index: int,
        rgb: Any,
        prior_depth: Any = None,
        adjusted_depth: Any = None,
        pose: Any = None,
        intrinsics: Any = None,
        timestamp: float | None = None,
        refined_depth: Any = None,
        confidence: Any = None,
    ) -> None:
        """Log frame ``index``: images, camera (pose + intrinsics) and the trajectory so far.

        rgb: (H, W, 3) uint8 or float in [0, 1] (CHW accepted); depths (prior, MEDeA's
        adjusted, the refinement's): (H, W) metres, resampled (nearest) to the logged RGB
        size; confidence: (H, W) in [0, 1], the refinement's (logged as an 8-bit image);
        pose: 4x4 camera-to-world; intrinsics: (fx, fy, cx, cy) or 3x3 in pixels of ``rgb``;
        timestamp: seconds.
        """
        rec = self._rec
        if rec is None:
            return
        rec.set_time("frame", sequence=int(index))
        if timestamp is not None:
            rec.set_time("time", duration=float(timestamp))

        # The logged resolution, shared by every image under the pinhole.
        image = _rgb_uint8(rgb) if rgb is not None else None
        if image is not None:
            src_h, src_w = image.shape[:2]
        else:
            first = next((d for d in (prior_depth, adjusted_depth, refined_depth) if d is not None), None)
            if first is None:
                src_h = src_w = None
            else:
                src_h, src_w = _depth_f32(first).shape
        if src_h is not None:
            height, width = _logged_size(src_h, src_w, self.max_width)

        if image is not None:
            image = _resize_rgb(image, height, width)
            archetype = rr.Image(image)
            if self.jpeg_quality is not None and image.ndim == 3 and image.shape[-1] == 3:
                archetype = archetype.compress(jpeg_quality=self.jpeg_quality)
            rec.log(RGB, archetype)
        for entity, depth in ((PRIOR_DEPTH, prior_depth), (ADJUSTED_DEPTH, adjusted_depth),
                              (REFINED_DEPTH, refined_depth)):
            if depth is not None:
                rec.log(entity, rr.DepthImage(_resize_nearest(_depth_f32(depth), height, width), meter=1.0))
        if confidence is not None and src_h is not None:
            conf = _resize_nearest(np.clip(_depth_f32(confidence), 0.0, 1.0), height, width)
            rec.log(CONFIDENCE, rr.Image((conf * 255.0 + 0.5).astype(np.uint8)))

        if intrinsics is not None and src_h is not None:
            fx, fy, cx, cy = _as_intrinsics(intrinsics)
            sx, sy = width / src_w, height / src_h
            rec.log(
                CAMERA,
                rr.Pinhole(
                    focal_length=[fx * sx, fy * sy],
                    # project convention: pixel centres at integers; Rerun: at +0.5
                    principal_point=[(cx + 0.5) * sx, (cy + 0.5) * sy],
                    resolution=[width, height],
                    camera_xyz=rr.ViewCoordinates.RDF,
                ),
            )

        if pose is not None:
            t = _to_numpy(pose).astype(np.float64)
            if t.shape != (4, 4):
                raise ValueError(f"pose must be a 4x4 camera-to-world matrix, got shape {t.shape}")
            rec.log(CAMERA, rr.Transform3D(translation=t[:3, 3], mat3x3=t[:3, :3]))
            self._centres.append(t[:3, 3].copy())
            rec.log(TRAJECTORY, rr.LineStrips3D([np.stack(self._centres)], colors=[[255, 128, 0]]))

    def log_tracking(self, index: int, state: str, pose: Any = None) -> None:
        """Frame ``index``'s tracking state on the frame timeline (a TextLog line; states
        that mean trouble as warnings), and for a dropped frame with a pose its camera
        centre in red under world/dropped."""
        rec = self._rec
        if rec is None:
            return
        rec.set_time("frame", sequence=int(index))
        trouble = state.split(":")[0] in _TROUBLE
        rec.log(TRACKING, rr.TextLog(f"frame {index}: {state}", level=rr.TextLogLevel.WARN if trouble
                                     else rr.TextLogLevel.INFO))
        if pose is not None and state.startswith("dropped"):
            t = _to_numpy(pose).astype(np.float64)
            if np.isfinite(t).all():
                self._dropped.append(t[:3, 3].copy())
                rec.log(DROPPED, rr.Points3D(np.stack(self._dropped), colors=[[230, 30, 30]], radii=0.02))

    # ------------------------------------------------------------------ geometry

    def log_mesh(self, vertices: Any, triangles: Any, vertex_colors: Any = None, entity: str = MESH) -> None:
        """Static triangle mesh in world coordinates; vertex_colors uint8 or float in [0, 1]."""
        rec = self._rec
        if rec is None:
            return
        colors = None
        if vertex_colors is not None:
            colors = _to_numpy(vertex_colors)
            if colors.dtype != np.uint8:
                colors = np.clip(colors.astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        rec.log(
            entity,
            rr.Mesh3D(
                vertex_positions=_to_numpy(vertices).astype(np.float32),
                triangle_indices=_to_numpy(triangles).astype(np.uint32),
                vertex_colors=colors,
            ),
            static=True,
        )

    def log_points(self, points: Any, colors: Any = None, radii: float | None = None, entity: str = POINTS) -> None:
        """Static point cloud in world coordinates; colors uint8 or float in [0, 1]."""
        rec = self._rec
        if rec is None:
            return
        if colors is not None:
            colors = _to_numpy(colors)
            if colors.dtype != np.uint8:
                colors = np.clip(colors.astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        rec.log(entity, rr.Points3D(_to_numpy(points).astype(np.float32), colors=colors, radii=radii), static=True)

    # ------------------------------------------------------------------ losses

    def log_losses(self, history: Mapping[str, Any]) -> None:
        """Per-epoch losses, {stage: {term: [values]}} (or {stage: StageHistory}), as
        ``medea/<stage>/<term>`` scalars on the "epoch" timeline."""
        rec = self._rec
        if rec is None:
            return
        for stage, terms in history.items():
            for term, values in _stage_losses(terms).items():
                if isinstance(values, (str, bytes)) or not isinstance(values, (Sequence, np.ndarray)):
                    continue
                values = np.asarray([float(v) for v in values], dtype=np.float64)
                if values.size == 0:
                    continue
                rec.send_columns(
                    f"{LOSSES}/{stage}/{term}",
                    indexes=[rr.TimeColumn("epoch", sequence=np.arange(values.size))],
                    columns=rr.Scalars.columns(scalars=values),
                )

    def log_epoch(self, stage: str, epoch: int, losses: Mapping[str, float]) -> None:
        """One epoch's losses; matches ``medea_core``'s progress callback
        ``(stage_name, epoch, epoch_losses)`` for live logging."""
        rec = self._rec
        if rec is None:
            return
        rec.reset_time()  # scalars carry only the epoch, not the last frame
        rec.set_time("epoch", sequence=int(epoch))
        for term, value in losses.items():
            rec.log(f"{LOSSES}/{stage}/{term}", rr.Scalars(float(value)))
        rec.reset_time()

    # ------------------------------------------------------------------ lifetime

    def flush(self) -> None:
        if self._rec is not None:
            self._rec.flush()

    def close(self) -> None:
        """Flush and disconnect (completes the .rrd in "save" mode). Idempotent.

        In "serve" mode the stream stays connected: disconnecting would shut the gRPC
        server down, and the data stays viewable until the process exits."""
        rec, self._rec = self._rec, None
        if rec is None:
            return
        rec.flush()
        if self.mode == "serve":
            self._served = rec
        else:
            rec.disconnect()

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

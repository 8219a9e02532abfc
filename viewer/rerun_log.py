"""Rerun logging for the pipeline: frames, cameras, trajectory, mesh and MEDeA losses.

Written against rerun-sdk 0.41; every call goes to a dedicated ``rr.RecordingStream``, so
several loggers can live in one process, and every mode first sends :mod:`viewer.blueprint`.
Live logging, in any order per frame: :meth:`RerunLogger.log_tracking`, ``log_frame``,
``log_depth`` (later, at the frame's time), ``log_mesh(..., index=i)`` every few frames, and
``log_cameras`` once the poses are final. Conventions are the project's (camera-to-world,
OpenCV axes, z-depth in metres with 0 = invalid, pixel centres at integers); the principal
point is logged as ``cx + 0.5, cy + 0.5``, Rerun's pixel centres. Entity paths:
:mod:`viewer.entities`. More: docs/outputs.md#what-a-recording-holds
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr

from .arrays import (
    as_intrinsics,
    camera_of,
    depth_f32,
    logged_size,
    pose_matrix,
    resize_nearest,
    resize_rgb,
    rgb_uint8,
    to_numpy,
)
from .blueprint import default_blueprint
from .entities import (
    ADJUSTED_DEPTH,
    CAMERA,
    CONFIDENCE,
    DROPPED,
    EPOCH_TIMELINE,
    FRAME_TIMELINE,
    LOSSES,
    MESH,
    POINTS,
    PRIOR_DEPTH,
    REFINED_DEPTH,
    RGB,
    TIME_TIMELINE,
    TRACKING,
    TRAJECTORY,
)
from .modes import default_mode

MODES = ("spawn", "save", "serve", "off")

# Frames per trajectory piece. Each new camera re-logs only its own piece: logging the whole
# trajectory with every frame would make a recording grow with the square of its length.
TRAJECTORY_PIECE = 256
# Tracking states that mean trouble are logged as warnings (rerun's TextLog level).
_TROUBLE = ("interpolated", "dropped", "lost")
# A stage's loss terms share one bar chart, drawn over each other: the total, the largest,
# is translucent so that the terms under it show (other names get Rerun's colours). The share
# of pixels the pairs overlap is no loss (its scale is another): a scalar only.
_LOSS_COLORS = {"total": [120, 120, 120, 110], "photometric": [31, 119, 180, 200], "depth": [255, 127, 14, 200],
                "feature": [44, 160, 44, 200]}
_NOT_CHARTED = ("valid_fraction",)


def trajectory_piece(index: int) -> str:
    """Entity path of the trajectory piece that holds frame ``index``."""
    return f"{TRAJECTORY}/{int(index) // TRAJECTORY_PIECE:05d}"


def _log_transform(rec: rr.RecordingStream, pose: np.ndarray) -> None:
    rec.log(CAMERA, rr.Transform3D(translation=pose[:3, 3], mat3x3=pose[:3, :3]))


def _log_pinhole(rec: rr.RecordingStream, intrinsics: Any, source: tuple[int, int], logged: tuple[int, int]) -> None:
    """The camera's pinhole: intrinsics in pixels of a ``source`` (H, W) image, for the images
    logged under it at ``logged`` (H, W)."""
    fx, fy, cx, cy = as_intrinsics(intrinsics)
    (src_h, src_w), (height, width) = source, logged
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
    blueprint: the layout sent as the active and default blueprint; None =
    :func:`viewer.blueprint.default_blueprint`.
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
        blueprint: Any = None,
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
        # Per frame index, so that frames may be logged in pieces and out of order: camera
        # centres (the trajectory), timestamps, logged image size (height, width).
        self._centres: dict[int, dict[int, np.ndarray]] = {}  # per trajectory piece
        self._timestamps: dict[int, float] = {}
        self._sizes: dict[int, tuple[int, int]] = {}
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
        # Active as well as default: a viewer that already holds a layout for this app id
        # (spawn, a reused web viewer) switches to this one instead of keeping its own.
        rec.send_blueprint(default_blueprint() if blueprint is None else blueprint, make_active=True,
                           make_default=True)
        self._rec = rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_DOWN, static=True)

    @property
    def enabled(self) -> bool:
        return self._rec is not None

    def _at_frame(self, rec: rr.RecordingStream, index: int) -> None:
        """Set the time to frame ``index`` (and its timestamp when known) and nothing else,
        so no other timeline's value (another frame's "time", an "epoch") leaks in."""
        rec.reset_time()
        rec.set_time(FRAME_TIMELINE, sequence=index)
        timestamp = self._timestamps.get(index)
        if timestamp is not None:
            rec.set_time(TIME_TIMELINE, duration=timestamp)

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

        Every argument after ``index`` may be None and is then not logged, so a frame can
        be logged in pieces (RGB and camera while tracking, depth later: see
        :meth:`log_depth`). rgb: (H, W, 3) uint8 or float in [0, 1] (CHW accepted); depths
        (prior, MEDeA's adjusted, the refinement's): (H, W) metres, resampled (nearest) to
        the logged RGB size; confidence: (H, W) in [0, 1], the refinement's (logged as an
        8-bit image); pose: 4x4 camera-to-world; intrinsics: (fx, fy, cx, cy) or 3x3 in
        pixels of ``rgb`` (of the depth when rgb is None), or (fx, fy, cx, cy, width, height)
        with the size of the image they are in pixels of (a camera logged without images, or
        with images of another size); timestamp: seconds.
        """
        rec = self._rec
        if rec is None:
            return
        index = int(index)
        if timestamp is not None:
            self._timestamps[index] = float(timestamp)
        self._at_frame(rec, index)

        # The logged resolution, shared by every image under the pinhole: the RGB's, else
        # the one this frame's RGB was logged at earlier, else the depth's.
        image = rgb_uint8(rgb) if rgb is not None else None
        first = next((d for d in (prior_depth, adjusted_depth, refined_depth, confidence) if d is not None), None)
        source = None  # (H, W) of the images given
        if image is not None:
            source = image.shape[:2]
            self._sizes[index] = logged_size(*source, self.max_width)
        elif first is not None:
            source = depth_f32(first).shape
            self._sizes.setdefault(index, logged_size(*source, self.max_width))

        if image is not None:
            image = resize_rgb(image, *self._sizes[index])
            archetype = rr.Image(image)
            if self.jpeg_quality is not None and image.ndim == 3 and image.shape[-1] == 3:
                archetype = archetype.compress(jpeg_quality=self.jpeg_quality)
            rec.log(RGB, archetype)
        for entity, depth in ((PRIOR_DEPTH, prior_depth), (ADJUSTED_DEPTH, adjusted_depth),
                              (REFINED_DEPTH, refined_depth)):
            if depth is not None:
                rec.log(entity, rr.DepthImage(resize_nearest(depth_f32(depth), *self._sizes[index]), meter=1.0))
        if confidence is not None:
            conf = resize_nearest(np.clip(depth_f32(confidence), 0.0, 1.0), *self._sizes[index])
            rec.log(CONFIDENCE, rr.Image((conf * 255.0 + 0.5).astype(np.uint8)))

        camera = camera_of(intrinsics, source)
        if camera is not None:
            k, k_size = camera
            _log_pinhole(rec, k, k_size, self._sizes.get(index) or logged_size(*k_size, self.max_width))
        if pose is not None:
            t = pose_matrix(pose)
            _log_transform(rec, t)
            self._centres.setdefault(index // TRAJECTORY_PIECE, {})[index] = t[:3, 3].copy()
            self._log_piece(rec, index)

    def log_cameras(self, indices: Any, poses: Any, intrinsics: Any, size: tuple[int, int]) -> None:
        """Every frame's final camera, once the poses are known for good: for each frame of
        ``indices`` (frame order) its camera (pose + pinhole) and the trajectory of these
        poses up to it, at that frame's time. Images are not logged again.

        For a run whose frames were logged before their poses were final (a streamed run's
        estimate: no pose or intrinsics yet while the focal search buffers, poses the global
        BA then moves): at each frame time these rows, logged last, replace what was logged
        there before, and the trajectory is these poses alone. poses: (N, 4, 4) camera-to-
        world, NaN for a frame without one, which stays out of the trajectory while its
        camera stays at the frame posed last before it (logged again at its time, so that a
        pose tracking gave it does not show); frames before the first pose are left as they
        are. intrinsics: (fx, fy, cx, cy) or 3x3 in pixels of images of ``size`` (H, W),
        brought to each frame's logged RGB size."""
        rec = self._rec
        if rec is None:
            return
        indices = [int(i) for i in to_numpy(indices).ravel()]
        poses = to_numpy(poses).astype(np.float64)
        if len(poses) != len(indices):
            raise ValueError(f"{len(indices)} frame indices for {len(poses)} poses")
        self._centres = {}  # the trajectory is these poses alone
        held = None
        for k in np.argsort(indices, kind="stable"):
            index, pose = indices[k], poses[k]
            if np.isfinite(pose).all():
                held = pose_matrix(pose)
                self._centres.setdefault(index // TRAJECTORY_PIECE, {})[index] = held[:3, 3].copy()
            elif held is None:
                continue
            self._at_frame(rec, index)
            _log_pinhole(rec, intrinsics, size, self._sizes.get(index) or logged_size(*size, self.max_width))
            _log_transform(rec, held)
            self._log_piece(rec, index)

    def _log_piece(self, rec: rr.RecordingStream, index: int) -> None:
        """The trajectory piece of frame ``index`` as it stands, at the current time (no
        strip while the piece has no centre: that clears one logged there before)."""
        centres = self._piece_centres(int(index) // TRAJECTORY_PIECE)
        strips = [centres] if len(centres) else []
        rec.log(trajectory_piece(index), rr.LineStrips3D(strips, colors=[[255, 128, 0]]))

    def _piece_centres(self, piece: int) -> np.ndarray:
        """(M, 3) centres of one trajectory piece in frame order, led by the last centre of the
        piece before it so that the pieces join into one line; (0, 3) when it has none."""
        own = self._centres.get(piece, {})
        centres = [own[k] for k in sorted(own)]
        before = self._centres.get(piece - 1)
        if before and centres:
            centres.insert(0, before[max(before)])
        return np.stack(centres) if centres else np.zeros((0, 3))

    def log_depth(
        self,
        index: int,
        prior_depth: Any = None,
        adjusted_depth: Any = None,
        refined_depth: Any = None,
        confidence: Any = None,
    ) -> None:
        """Depth (and the refinement's confidence) of frame ``index``, logged at that frame's
        time after its RGB and camera (:meth:`log_frame`), which are not logged again;
        arguments as in :meth:`log_frame`, None ones not logged."""
        self.log_frame(index, None, prior_depth, adjusted_depth, refined_depth=refined_depth, confidence=confidence)

    def log_tracking(self, index: int, state: str, pose: Any = None) -> None:
        """Frame ``index``'s tracking state on the frame timeline (a TextLog line; states
        that mean trouble as warnings), and for a dropped frame with a pose its camera
        centre in red under world/dropped."""
        rec = self._rec
        if rec is None:
            return
        self._at_frame(rec, int(index))
        # "<state>[: why][; scale after break N][; rotation only | large motion]": a frame past a
        # scale break, or whose motion the frames cannot measure, is trouble too.
        trouble = state.split(":")[0].split(";")[0] in _TROUBLE or ";" in state
        rec.log(TRACKING, rr.TextLog(f"frame {index}: {state}", level=rr.TextLogLevel.WARN if trouble
                                     else rr.TextLogLevel.INFO))
        if pose is not None and state.startswith("dropped"):
            t = to_numpy(pose).astype(np.float64)
            if np.isfinite(t).all():
                self._dropped.append(t[:3, 3].copy())
                rec.log(DROPPED, rr.Points3D(np.stack(self._dropped), colors=[[230, 30, 30]], radii=0.02))

    # ------------------------------------------------------------------ geometry

    def log_mesh(self, vertices: Any, triangles: Any, vertex_colors: Any = None, index: int | None = None, *,
                 entity: str = MESH) -> None:
        """Triangle mesh in world coordinates; vertex_colors uint8 or float in [0, 1].

        index None: static (shown at every time). An int: logged on the "frame" timeline
        at that frame, replacing the previous update from there on (a growing live
        reconstruction); do not mix both on one entity (static data hides the updates)."""
        rec = self._rec
        if rec is None:
            return
        if index is not None and not isinstance(index, (int, np.integer)):
            raise TypeError(f"index must be a frame index or None, got {index!r} (entity is keyword-only)")
        colors = None
        if vertex_colors is not None:
            colors = to_numpy(vertex_colors)
            if colors.dtype != np.uint8:
                colors = np.clip(colors.astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        mesh = rr.Mesh3D(
            vertex_positions=to_numpy(vertices).astype(np.float32),
            triangle_indices=to_numpy(triangles).astype(np.uint32),
            vertex_colors=colors,
        )
        if index is None:
            rec.log(entity, mesh, static=True)
            return
        self._at_frame(rec, int(index))
        rec.log(entity, mesh)

    def log_points(self, points: Any, colors: Any = None, radii: float | None = None, entity: str = POINTS) -> None:
        """Static point cloud in world coordinates; colors uint8 or float in [0, 1]."""
        rec = self._rec
        if rec is None:
            return
        if colors is not None:
            colors = to_numpy(colors)
            if colors.dtype != np.uint8:
                colors = np.clip(colors.astype(np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
        rec.log(entity, rr.Points3D(to_numpy(points).astype(np.float32), colors=colors, radii=radii), static=True)

    # ------------------------------------------------------------------ losses

    def log_losses(self, history: Mapping[str, Any]) -> None:
        """Per-epoch losses, {stage: {term: [values]}} (or {stage: StageHistory}), under
        ``medea/<stage>/<term>``: scalars on the "epoch" timeline, and each loss (not the
        pairs' "valid_fraction") as a static bar chart too, one bar per epoch, which shows on
        every timeline: a plot of the scalars shows only on "epoch" (a Rerun view plots against
        the time panel's timeline), not on "frame", where a recording opens. A later call
        replaces the bar charts."""
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
                entity = f"{LOSSES}/{stage}/{term}"
                rec.send_columns(
                    entity,
                    indexes=[rr.TimeColumn(EPOCH_TIMELINE, sequence=np.arange(values.size))],
                    columns=rr.Scalars.columns(scalars=values),
                )
                if term not in _NOT_CHARTED:
                    rec.log(entity, rr.BarChart(values, color=_LOSS_COLORS.get(term)), static=True)

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

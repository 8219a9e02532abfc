"""What an estimated trajectory becomes where its scale breaks (``--on-break``): the
stretches between the scale watch's breaks (``recon.poses.checks.scale_watch``), their joins
(``recon.poses.checks.join``), the stop, and the estimator options each choice implies; and, with
the same choice, a metric scale the depth prior cannot vouch for (``recon.poses.checks.prior_agreement``). Both
drivers (``recon.drivers.oneshot``, ``recon.drivers.streamed``) call :func:`settle_breaks` after the
poses and before depth; each writes the segments that stay apart its own way.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import ReconInputError

log = logging.getLogger(__name__)


def estimator_options(config, frontend_only: bool = False) -> dict:
    """The pose estimator's options of a run (``config`` its PipelineConfig): the user's
    ``pose_options`` over what ``on_break`` implies for the front end: "segments" tracks again
    from where the camera was lost, a new piece of the trajectory (``restart_after_loss``,
    recon.poses.frontend.pieces), where the others fall back to SfM; "keep" returns a trajectory
    whatever the front end's motion checks or SfM's scale spread say (``stop_untrusted`` off,
    ``max_scale_spread`` 0). frontend_only: for a run that only has the front end (streamed),
    which SfM's implied settings do not concern."""
    implied = {"segments": {"restart_after_loss": True}, "stop": {},
               "keep": {"stop_untrusted": False, "max_scale_spread": 0.0}}[config.on_break]
    if frontend_only:
        from ..poses.config import FrontendConfig

        implied = {k: v for k, v in implied.items() if k in FrontendConfig.__dataclass_fields__}
    return {**implied, **config.pose_options}


def trajectory_stretches(info: dict, count: int) -> np.ndarray:
    """(count,) int: per frame of an estimate, the stretch of its trajectory it belongs to
    (0 before the first scale break, n after break n; recon.poses.checks.scale_watch's
    ``frame_verdicts`` in the pose report ``info``); all 0 without a scale watch."""
    verdicts = info.get("scale_watch", {}).get("frame_verdicts") or ["ok"] * count
    return np.array([0 if v == "ok" else int(v.rsplit(" ", 1)[-1]) for v in verdicts], dtype=np.int64)


def join_breaks(stretch: np.ndarray, poses: np.ndarray, positions: np.ndarray, frame, intrinsics,
                views: int = 4, through_map: bool = True) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The stretches of a trajectory joined across its scale breaks where the frames allow
    (recon.poses.checks.join): (stretch (N,) renumbered so that joined stretches share one number,
    poses (N, 4, 4) camera-to-world with each joined stretch moved into the frame of the one
    before, what report.json says of each break). stretch: (N,) as from
    :func:`trajectory_stretches`; positions: the frames that can serve as views (colour and
    depth at hand), in order; frame(position) -> (rgb (H, W, 3) uint8, prior depth (h, w)
    metres); intrinsics of the frames. The depth prior is the scale both sides are brought
    to (the trajectory's units are the prior's metres on the whole, ``backend.metric_rescale``;
    why: docs/decisions.md#joining-across-a-break). through_map: where
    the ORB join finds nothing, join through one SfM model of both stretches' views
    (``recon.poses.sfm.map_join``; skipped without pycolmap). Each break's entry says ``how``
    ("orb" or "map") it was joined."""
    from ..geometry.rigid import apply_similarity
    from ..poses.checks.join import JoinConfig, View, join_stretches

    def view(p: int) -> View:
        return View(*frame(p), poses[p])

    cfg = JoinConfig(views=views)
    label, poses, report = stretch.copy(), np.array(poses, dtype=np.float64, copy=True), []
    usable = [p for p in positions if np.isfinite(poses[p]).all()]
    for k in range(1, int(stretch.max()) + 1):
        # Every other frame of the 2m nearest the break on each side: some baseline between views.
        before = [p for p in usable if stretch[p] == k - 1][-2 * cfg.views::2]
        after = [p for p in usable if stretch[p] == k][:2 * cfg.views:2]
        join, how = None, "orb"
        if before and after:
            join = join_stretches([view(p) for p in before], [view(p) for p in after], intrinsics, cfg)
        if join is None and through_map:
            join, how = _join_through_map(stretch, k, usable, view, intrinsics), "map"
        entry = {"break": k, "joined": join is not None, "tried": [len(before), len(after)]}
        if join is not None:
            entry["how"] = how
            mine = stretch == k
            poses[mine] = apply_similarity(poses[mine], join.rotation, join.translation, join.scale)
            label[mine] = label[np.flatnonzero(stretch == k - 1)[0]]
            entry.update(join.to_dict())
        report.append(entry)
    _, label = np.unique(label, return_inverse=True)
    return label.astype(np.int64), poses, report


def _join_through_map(stretch: np.ndarray, k: int, usable: list[int], view, intrinsics):
    """Break k's join through an SfM model (``recon.poses.sfm.map_join``) of views spread over
    the frames nearest it on each side, or None (also where pycolmap is not installed)."""
    from ..poses.result import evenly_apart
    from ..poses.sfm.map_join import MapJoinConfig, map_join

    cfg = MapJoinConfig()

    def spread(near: list[int]) -> list[int]:  # `views` of the frames nearest the break
        return [near[i] for i in evenly_apart(len(near), cfg.views)]

    before = spread([p for p in usable if stretch[p] == k - 1][-cfg.reach:])
    after = spread([p for p in usable if stretch[p] == k][:cfg.reach])
    try:
        return map_join([view(p) for p in before], [view(p) for p in after], intrinsics, cfg)
    except ReconInputError as err:  # no pycolmap: the ORB join is all there is
        log.debug("no join through the map: %s", err)
        return None


def settle_breaks(config, stretch: np.ndarray, poses: np.ndarray, positions: np.ndarray, frame, intrinsics,
                  info: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """An estimated trajectory at its scale breaks, as ``config.on_break`` says, the same in
    both drivers: the stretches joined where the frames allow (``config.join_segments``;
    stretch, poses, positions, frame and intrinsics as :func:`join_breaks` takes them), then
    the stop ("stop"). Returns (stretch (N,), poses, the pose report ``info`` with the joins):
    every stretch 0 where the run goes on as one trajectory ("keep", no break, or every break
    joined); the driver writes what stays apart as segments."""
    check_metric_scale(config, info)
    check_scale_spread(config, info)
    if config.on_break == "keep" or stretch.max() == 0:
        return np.zeros_like(stretch), poses, info
    if config.join_segments:
        stretch, poses, joins = join_breaks(stretch, poses, positions, frame, intrinsics,
                                            through_map=config.join_through_map)
        info = {**info, "joins": joins}
        say_joins(joins)
    if stretch.max() > 0 and config.on_break == "stop":
        stop_at_breaks(info)
    return stretch, poses, info


def check_metric_scale(config, info: dict) -> None:
    """The depth prior's verdict on an estimate's metric scale (``recon.poses.checks.prior_agreement``,
    report.json's poses.metric_scale): where the prior does not follow the scene, a warning
    that the result is written at that scale and its size is not to be trusted (report.json
    marks it, and the fusion's voxel follows the scene's depth alone:
    :func:`untrusted_scale`), or under "stop" a stop naming the frames."""
    from ..poses.checks.prior_agreement import PriorAgreement

    if not untrusted_scale(info):
        return
    verdict = PriorAgreement.from_dict(info["metric_scale"])
    if config.on_break == "stop":
        raise ReconInputError(verdict.refusal())
    log.warning("%s (report.json: poses.metric_scale)", verdict.said())


def check_scale_spread(config, info: dict) -> None:
    """SfM's verdict on how its map's scale varies against the depth prior's from frame to
    frame (``recon.poses.sfm.mapper.scale_spread``, report.json's poses.scale_spread): beyond the
    prior's noise a warning that the map's parts may be at different scales, or under "stop"
    a stop."""
    spread = info.get("scale_spread")
    if not spread or spread["consistent"]:
        return
    said = (f"SfM's map and the depth prior disagree in scale by x{spread['factor']:.2f} (one standard deviation) "
            "from frame to frame, more than the prior's noise explains: the map's parts may be at different scales")
    if config.on_break == "stop":
        raise ReconInputError(f"stopped (--on-break stop): {said}")
    log.warning("%s (report.json: poses.scale_spread)", said)


def untrusted_scale(info: dict) -> bool:
    """Whether a pose report ``info`` says the depth prior cannot vouch for its metres."""
    return not info.get("metric_scale", {}).get("trusted", True)


def say_joins(joins: list[dict]) -> None:
    """One line on the breaks :func:`join_breaks` joined (and those it could not)."""
    joined = [j for j in joins if j["joined"]]
    if joined:
        scales = ", ".join(f"x{j['scale']:.2f}" + (" through the map" if j.get("how") == "map" else "")
                           for j in joined)
        log.info("%d of %d scale breaks joined (the frames after each posed in the stretch before it, or both "
                 "stretches in one SfM model; scale %s)", len(joined), len(joins), scales)


def stop_at_breaks(info: dict) -> None:
    """ReconInputError naming the scale breaks of an estimate's pose report ``info``, if it
    has any (``--on-break stop``; not a TrackingLostError, which the SfM fallback would answer)."""
    from ..poses.checks.scale_watch import ScaleWatch

    watch = info.get("scale_watch")
    if watch and watch["breaks"]:
        raise ReconInputError(f"stopped where the trajectory's scale breaks (--on-break stop): "
                              f"{ScaleWatch.from_dict(watch).describe()}")


__all__ = ["check_metric_scale", "check_scale_spread", "estimator_options", "join_breaks", "say_joins",
           "settle_breaks", "stop_at_breaks", "trajectory_stretches", "untrusted_scale"]

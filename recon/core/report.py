"""What ``report.json`` says of a run: inputs, options, versions, per-stage timings and
what each stage decided (intrinsics source, pose quality, MEDeA's losses, refinement and
fusion figures). Building it is kept apart from running the stages so that the streamed
pipeline can fill the same report from its windows.
"""

from __future__ import annotations

import platform

import numpy as np

from .refine import refine_summary


def _wh(shape) -> list[int]:
    # report.json keeps sizes as [width, height], the order users read them in (WxH).
    return [int(shape[1]), int(shape[0])]


def scale_vs_prior(log_scales) -> dict:
    """How far MEDeA moved the depth's overall scale from the prior's, from its log-scale
    grids (N, h, w): each frame's median cell, as a factor; the median, 10th and 90th
    percentile over frames. Only translation between views measures that scale.
    why: docs/decisions.md#medeas-scale-under-rotation"""
    # MEDeA returns them on the prior's device, which may be a GPU.
    grids = np.asarray(log_scales.cpu() if hasattr(log_scales, "cpu") else log_scales, np.float64)
    if len(grids) == 0:
        return {}
    per_frame = np.exp(np.median(grids.reshape(len(grids), -1), axis=1))
    p10, median, p90 = np.percentile(per_frame, [10, 50, 90])
    return {"median": float(median), "p10": float(p10), "p90": float(p90)}


def medea_summary(result) -> dict:
    """Per stage: epochs run, whether it stopped early, first and last epoch losses; the
    overall scale MEDeA gave the depth against the prior's (:func:`scale_vs_prior`); the
    search for the prior's scale before Stage I, when it ran (factor, gain, applied, pairs)."""
    if result is None:
        return {}
    out = {"keyframes": int(len(result.keyframes)), "seconds": dict(result.seconds),
           "scale_vs_prior": scale_vs_prior(result.log_scales), "stages": {}}
    if result.global_scale is not None:
        out["global_scale"] = result.global_scale.to_dict()
    for name, history in result.history.items():
        losses = {term: [float(v) for v in values] for term, values in history.losses.items()}
        out["stages"][name] = {
            "epochs": int(history.epochs),
            "stopped_early": bool(history.stopped_early),
            "pairs": int(history.pairs), "pairs_left_out": int(history.pairs_left_out),
            "skipped": bool(history.skipped),
            "first": {t: v[0] for t, v in losses.items() if v},
            "last": {t: v[-1] for t, v in losses.items() if v},
        }
    return out


def fusion_summary(fused, min_confidence: float | None) -> dict:
    """The TSDF volume and mesh figures, the weight threshold meshed at among them;
    min_confidence: the threshold used (None: no confidence was fused)."""
    mesh = fused.mesh
    return {"min_confidence": min_confidence, "weight_threshold": fused.weight_threshold,
            "voxel_size": fused.voxel_size, "trunc": fused.trunc,
            "max_depth": fused.max_depth, "frames_fused": fused.frames_fused, "block_estimate": fused.block_estimate,
            "blocks_used": fused.blocks_used, "fragments_removed": fused.fragments_removed,
            "vertices": len(mesh.vertices), "triangles": len(mesh.triangles),
            "triangles_full": fused.triangles_full or len(mesh.triangles)}


def upright_section(fused) -> dict | None:
    """report.json "upright": the rotation the GLB and the exports were turned by."""
    return None if fused.upright is None else fused.upright.to_dict()


def _input_section(config, source) -> dict:
    """What was read: the input path, its kind, size and frame rate."""
    return {"path": str(config.input), "kind": source.kind, "description": source.description,
            "native_size": _wh(source.native_shape), "fps": source.fps}


def _intrinsics_section(values, source_of_values: str, source) -> dict:
    """The camera used: its intrinsics at working size and where they came from, and the
    known lens the frames were resampled for (``FrameSource.to_pinhole``; None: none)."""
    return {"values": [float(v) for v in values], "source": source_of_values, "undistorted": source.undistorted}


def versions() -> dict:
    import open3d
    import rerun
    import torch

    from .. import __version__

    return {"recon": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "torch": torch.__version__, "open3d": open3d.__version__, "rerun": rerun.__version__}


def build_report(*, config, source, seq, intrinsics_from: str, pose_stage, undistorted: bool, prior, medea_result,
                 refined, fusion, min_confidence: float | None, seconds: dict, files: dict,
                 medea_skipped: str | None = None) -> dict:
    """report.json's content. seq: the sequence as fused (frames left out are not in it);
    prior: the PriorOutput; fusion: the FusionResult, min_confidence its threshold (None: no
    confidence fused); seconds: {stage: wall seconds}; files: {label: path relative to the
    output folder}; medea_skipped: why MEDeA was skipped although enabled."""
    features = seq.features
    return {
        "input": _input_section(config, source),
        "frames": {"count": len(seq), "indices": seq.indices.tolist(), "names": list(seq.names),
                   "working_size": _wh(source.shape)},
        "intrinsics": _intrinsics_section(seq.intrinsics, intrinsics_from, source),
        "poses": {"source": pose_stage.source, **pose_stage.info, "lens_k1": pose_stage.lens_k1,
                  "frames_undistorted": undistorted},
        "prior": {"name": config.prior, "kind": prior.kind, "info": prior.info,
                  "features": None if features is None else list(features.shape[1:])},
        "medea": {"skipped": medea_skipped} if medea_skipped else medea_summary(medea_result),
        "refine": {"method": config.refine, **refine_summary(refined)},
        **_closing_sections(config, fusion, min_confidence, seconds, len(seq)),
        "files": dict(files),
    }


def _closing_sections(config, fusion, min_confidence: float | None, seconds: dict, frames: int,
                      **memory) -> dict:
    """The sections both drivers' reports end with: the fusion and its up axis, the memory
    (``memory``: the driver's own figures beside the peak), the options that reproduce the
    run, the versions, the seconds per stage and per frame (over `frames`)."""
    return {
        "fusion": fusion_summary(fusion, min_confidence),
        "upright": upright_section(fusion),
        "memory": {"peak_rss_mb": peak_memory_mb(), **memory},
        "options": config.to_dict(),
        "versions": versions(),
        "seconds": dict(seconds),
        "seconds_per_frame": {k: v / frames for k, v in seconds.items()},
    }


def peak_memory_mb() -> float | None:
    """This process's peak resident memory (VmHWM) in MB, None where /proc is missing."""
    try:
        for line in open("/proc/self/status"):
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def segments_summary(report: dict, pieces: list, pose_info: dict, seconds_before: dict) -> dict:
    """The summary report.json of a run written as segments (--on-break segments): the
    largest segment's ``report`` with the whole run's frame counts, pose report ``pose_info``
    and ``segments``: per piece (a PipelineResult or StreamResult, each with its own folder
    and report) its folder, first and last frame, frames with depth and triangles; its
    seconds: the stages before the split (``seconds_before``) and the pieces' summed."""
    segments = [{"folder": p.output.name, "frames": [int(p.report["frames"]["indices"][0]),
                                                    int(p.report["frames"]["indices"][-1])],
                 "depth_frames": int(p.report["frames"].get("depth_frames", p.report["frames"]["count"])),
                 "triangles": int(len(p.fusion.mesh.triangles))} for p in pieces]
    frames = {**report["frames"], "count": sum(int(p.report["frames"]["count"]) for p in pieces),
              "depth_frames": sum(s["depth_frames"] for s in segments),
              "indices": [i for p in pieces for i in p.report["frames"]["indices"]]}
    seconds = {}
    for piece in pieces:
        for stage, value in piece.report.get("seconds", {}).items():
            seconds[stage] = seconds.get(stage, 0.0) + value
    return {**report, "frames": frames, "poses": {**report["poses"], **pose_info}, "segments": segments,
            "seconds": {**seconds_before, **seconds}}


def segments_warning(summary: dict) -> str:
    """The one warning of a run written as segments (its summary report)."""
    parts = ", ".join(f"{s['folder']}/ frames {s['frames'][0]}-{s['frames'][1]}" for s in summary["segments"])
    return (f"the trajectory's scale breaks (report.json: poses.scale_watch): written as {len(summary['segments'])} "
            f"separate reconstructions, {parts} (--on-break stop stops instead, keep writes one)")


def stream_report(*, config, source, video, windows: list[dict], fusion, min_confidence, seconds: dict,
                  store_bytes: int, first_result_s: float | None = None) -> dict:
    """report.json of a streamed run (recon.drivers.streamed): the one-shot report's sections, with
    the tracked frames, the depth frames, per window MEDeA's epochs and seconds (or why its
    gate skipped it, with the given poses' fit), the scale anchor and the refinement's
    share, the bytes the frame store parked on disk (store_bytes) and the seconds from the
    run's start to its first window's fused surface (first_result_s)."""
    from .stages import window_frames

    kept = np.isfinite(video.poses).all(axis=(1, 2))
    depth_idx = video.indices[video.depth_frame]
    anchors = [w["anchor"] for w in windows[1:]]
    return {
        "input": _input_section(config, source),
        "streamed": True,
        "frames": {"count": int(kept.sum()), "tracked": len(video.indices), "indices": video.indices[kept].tolist(),
                   "depth_frames": len(depth_idx), "depth_indices": depth_idx.tolist(),
                   "depth_names": [video.names[k] for k in np.flatnonzero(video.depth_frame)],
                   "working_size": _wh(video.size), "depth_frames_rule": config.depth_frames,
                   "depth_by_gap": video.depth_by_gap, "prior_scale": video.prior_scale},
        "intrinsics": _intrinsics_section(video.intrinsics, video.intrinsics_from, source),
        "poses": {"source": video.pose_source, **video.pose_info, "lens_k1": video.lens_k1},
        "prior": {"name": config.prior, "kind": "metric", "info": video.prior_info, "features": video.feature_shape},
        "windows": {"count": len(windows), "size": window_frames(config, video.size), "size_at_640x480": config.window,
                    "overlap": config.window_overlap,
                    "anchor_factors": {"min": min(anchors, default=1.0), "max": max(anchors, default=1.0)},
                    "medea_skipped": sum(1 for w in windows if w.get("medea_skipped")),
                    "stage1_skipped": sum(1 for w in windows if w.get("stage1_skipped")),
                    "stage1_pairs_left_out": sum(int(w.get("stage1_pairs_left_out", 0)) for w in windows),
                    "each": windows, "first_result_s": first_result_s},
        "refine": {"method": config.refine},
        **_closing_sections(config, fusion, min_confidence, seconds, len(video.indices),
                            frame_store_mb=store_bytes / 1e6),
    }

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


def medea_summary(result) -> dict:
    """Per stage: epochs run, whether it stopped early, first and last epoch losses."""
    if result is None:
        return {}
    out = {"keyframes": int(len(result.keyframes)), "seconds": dict(result.seconds), "stages": {}}
    for name, history in result.history.items():
        losses = {term: [float(v) for v in values] for term, values in history.losses.items()}
        out["stages"][name] = {
            "epochs": int(history.epochs),
            "stopped_early": bool(history.stopped_early),
            "first": {t: v[0] for t, v in losses.items() if v},
            "last": {t: v[-1] for t, v in losses.items() if v},
        }
    return out


def fusion_summary(fused, min_confidence: float | None) -> dict:
    """The TSDF volume and mesh figures; min_confidence: the threshold used (None: no
    confidence was fused)."""
    mesh = fused.mesh
    return {"min_confidence": min_confidence, "voxel_size": fused.voxel_size, "trunc": fused.trunc,
            "max_depth": fused.max_depth, "frames_fused": fused.frames_fused, "block_estimate": fused.block_estimate,
            "blocks_used": fused.blocks_used, "fragments_removed": fused.fragments_removed,
            "vertices": len(mesh.vertices), "triangles": len(mesh.triangles)}


def versions() -> dict:
    import open3d
    import rerun
    import torch

    from . import __version__

    return {"recon": __version__, "python": platform.python_version(), "numpy": np.__version__,
            "torch": torch.__version__, "open3d": open3d.__version__, "rerun": rerun.__version__}


def build_report(*, config, source, seq, intrinsics_from: str, pose_stage, undistorted: bool, prior, medea_result,
                 refined, fusion: dict, seconds: dict, files: dict) -> dict:
    """report.json's content. seq: the sequence as fused (frames left out are not in it);
    prior: the PriorOutput; seconds: {stage: wall seconds}; files: {label: path relative
    to the output folder}."""
    features = seq.features
    return {
        "input": {"path": str(config.input), "kind": source.kind, "description": source.description,
                  "native_size": _wh(source.native_shape), "fps": source.fps},
        "frames": {"count": len(seq), "indices": seq.indices.tolist(), "names": list(seq.names),
                   "working_size": _wh(source.shape)},
        "intrinsics": {"values": list(seq.intrinsics), "source": intrinsics_from},
        "poses": {"source": pose_stage.source, **pose_stage.info, "lens_k1": pose_stage.lens_k1,
                  "frames_undistorted": undistorted},
        "prior": {"name": config.prior, "kind": prior.kind, "info": prior.info,
                  "features": None if features is None else list(features.shape[1:])},
        "medea": medea_summary(medea_result),
        "refine": {"method": config.refine, **refine_summary(refined)},
        "fusion": fusion,
        "options": config.to_dict(),
        "versions": versions(),
        "seconds": dict(seconds),
        "seconds_per_frame": {k: v / len(seq) for k, v in seconds.items()},
        "files": dict(files),
    }

"""The pose entry point recon.poses.estimate_poses: the automatic fallback from the front end to
SfM (said once, as a warning), and one-line errors for bad inputs and settings."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from recon.errors import ReconInputError
from recon.geometry.camera import intrinsics_from_fov
from recon.poses import TrackingLostError, estimate_poses
from recon.poses.frontend.streaming import FrontendConfig
from recon.poses.sfm.mapper import SfMConfig


def test_auto_falls_back_to_sfm_when_tracking_is_lost(pose_room, monkeypatch, capsys, caplog):
    seq, prior = pose_room
    import recon.poses.frontend.streaming as fe
    import recon.poses.sfm.mapper as sfm

    def lost(*args, **kwargs):
        raise TrackingLostError("tracking lost at frame 7: test", frame=7)

    sentinel = fe.PoseResult(np.tile(np.eye(4), (36, 1, 1)), seq.intrinsics, np.arange(36), 0.0, {"method": "sfm"})
    monkeypatch.setattr(fe, "estimate_poses_frontend", lost)
    monkeypatch.setattr(sfm, "estimate_poses_sfm", lambda *a, **k: sentinel)
    with caplog.at_level(logging.WARNING, logger="recon"):  # logged before SfM runs, not printed
        res = estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=True)
    assert res.diagnostics["fallback"]["frame"] == 7
    assert capsys.readouterr().out == ""
    assert [r.getMessage() for r in caplog.records] == [  # said once
        "front end failed (tracking lost at frame 7: test); falling back to SfM (pycolmap)"]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="recon"):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False)
    assert capsys.readouterr().out == ""
    assert [r.getMessage() for r in caplog.records] == [
        "front end failed (tracking lost at frame 7: test); the poses are from the SfM fallback (pycolmap)"]

    def sfm_fails(*args, **kwargs):
        raise TrackingLostError("SfM registered only 0 of 4 keyframes")

    monkeypatch.setattr(sfm, "estimate_poses_sfm", sfm_fails)
    with pytest.raises(TrackingLostError, match=r"front end failed \(tracking lost at frame 7: test\), and so did the "
                                                r"SfM fallback \(SfM registered only 0") as info:
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False)
    assert info.value.frame == 7
    with pytest.raises(TrackingLostError):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="frontend", progress=False)

    # Without intrinsics, SfM's focal length is said with the range the front end's estimates left.
    from recon.poses.intrinsics.focal_choice import FocalChoice

    def unsure(*args, **kwargs):
        err = TrackingLostError("the focal length was not found", frame=0)
        err.focal_choice = FocalChoice(300.0, "flow", 269.0, 929.0, {"flow": 300.0}, bracketed=False)
        raise err

    monkeypatch.setattr(fe, "estimate_poses_frontend", unsure)
    monkeypatch.setattr(sfm, "estimate_poses_sfm", lambda *a, **k: sentinel)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="recon"):
        res = estimate_poses(seq.rgb, prior, None, method="auto", progress=False)
    focal = res.diagnostics["focal"]
    assert focal["source"] == "SfM bundle adjustment" and focal["focal"] == seq.intrinsics[0]
    assert focal["low"] == min(269.0, seq.intrinsics[0]) and focal["high"] == 929.0 and focal["disagree"]
    assert any("-929 px open" in r.getMessage() for r in caplog.records)

    def turning(*args, **kwargs):  # no parallax: SfM would have none either
        raise TrackingLostError("the camera turns on the spot", frame=0, sfm_may_help=False)

    monkeypatch.setattr(fe, "estimate_poses_frontend", turning)
    monkeypatch.setattr(sfm, "estimate_poses_sfm", lambda *a, **k: pytest.fail("SfM tried on a turning camera"))
    with pytest.raises(TrackingLostError, match="^the camera turns on the spot$"):
        estimate_poses(seq.rgb, prior, seq.intrinsics, method="auto", progress=False)


def test_the_sfm_fallback_is_refused_where_the_vanishing_points_contradict_its_focal_length(pose_room, monkeypatch):
    """TUM fr1/rpy 50-99 with nothing given: the flow search failed, the vanishing points said
    492 px (not agreed on by enough frames), SfM's bundle adjustment 322 px for a 517 px
    camera, and its trajectory came back 4.7 % of its path off with exit 0. SfM's value is
    now refused when the vanishing points' lies over x1.25 from it (Record3D 0-79: 634 and
    681 px, taken); ``--on-break keep`` (stop_untrusted off) takes it anyway."""
    seq, prior = pose_room
    import recon.poses.frontend.streaming as fe
    import recon.poses.sfm.mapper as sfm
    from recon.poses.intrinsics.focal_choice import FocalChoice

    f_sfm = float(seq.intrinsics[0])
    sentinel = fe.PoseResult(np.tile(np.eye(4), (36, 1, 1)), seq.intrinsics, np.arange(36), 0.0, {"method": "sfm"})
    monkeypatch.setattr(sfm, "estimate_poses_sfm", lambda *a, **k: sentinel)

    def unsure_with(vp: float):
        def unsure(*args, **kwargs):
            err = TrackingLostError("the focal length was not found", frame=0)
            err.focal_choice = FocalChoice(300.0, "flow", 269.0, 929.0, {"flow": 300.0, "vanishing points": vp},
                                           bracketed=False)
            raise err
        return unsure

    monkeypatch.setattr(fe, "estimate_poses_frontend", unsure_with(1.53 * f_sfm))
    refused = (r"SfM fallback's trajectory cannot be trusted: its focal length \(SfM bundle adjustment, \d+ px\) "
               r"and the vanishing points' .* x1\.53")
    with pytest.raises(TrackingLostError, match=refused):
        estimate_poses(seq.rgb, prior, None, method="auto", progress=False)
    kept = estimate_poses(seq.rgb, prior, None, method="auto", progress=False, stop_untrusted=False)
    assert kept.diagnostics["focal"]["focal"] == f_sfm
    monkeypatch.setattr(fe, "estimate_poses_frontend", unsure_with(1.07 * f_sfm))
    assert estimate_poses(seq.rgb, prior, None, method="auto", progress=False).diagnostics["focal"]["focal"] == f_sfm


def test_bad_inputs_raise_one_line_errors(pose_room):
    seq, prior = pose_room
    with pytest.raises(ReconInputError, match="pose method"):
        estimate_poses(seq.rgb, prior, method="slam")
    with pytest.raises(ReconInputError, match="prior depth has 5 frames"):
        estimate_poses(seq.rgb[:8], prior[:5], seq.intrinsics, method="frontend", progress=False)
    with pytest.raises(ReconInputError, match="unknown pose option"):
        estimate_poses(seq.rgb[:8], prior[:8], seq.intrinsics, bogus=1)
    with pytest.raises(ReconInputError, match="ba_stride must be >= 1, got 0"):  # was a ZeroDivisionError
        estimate_poses(seq.rgb[:8], prior[:8], seq.intrinsics, config=FrontendConfig(ba_stride=0))
    with pytest.raises(ReconInputError, match="window must be >= 1"):  # the SfM's own front-end settings too
        estimate_poses(seq.rgb[:8], prior[:8], seq.intrinsics, method="sfm",
                       sfm_config=SfMConfig(frontend=FrontendConfig(window=0)))
    with pytest.raises(ReconInputError, match="positive focal"):
        estimate_poses(seq.rgb[:8], prior[:8], (0, 0, 1, 1))
    f = intrinsics_from_fov(90.0, 480, 640)  # (H, W)
    assert f[0] == pytest.approx(320.0) and f[2] == 319.5

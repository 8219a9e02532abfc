"""Dense optical flow of the pose estimator (recon.poses.flow)."""

from __future__ import annotations

import numpy as np

from recon.poses import flow as fl


def test_dis_flow_does_not_depend_on_earlier_calls(pose_room):
    """A seeded DIS call must not change a later unseeded one (OpenCV keeps state in the
    instance; shared instances made front-end results depend on what ran before)."""
    seq, _ = pose_room
    cfg = fl.FlowConfig()
    a, b, c = (fl.prepare_gray(seq.rgb[i], (240, 320)) for i in (0, 3, 9))
    first = fl.dis_flow(a, b, cfg)
    fl.dis_flow(a, c, cfg, init=2.0 * first + 5.0)
    np.testing.assert_array_equal(fl.dis_flow(a, b, cfg), first)

"""What the SfM fallback gives COLMAP and checks in what comes back (recon.poses.sfm.keyframes):
loop pairs by image similarity, which frames dense registration may reach, and the error
naming the frames that could not be registered."""

from __future__ import annotations

import cv2
import numpy as np

from recon.poses.result import TRUSTED_STATES, TrackingLostError
from recon.poses.sfm import keyframes as skf


def test_loop_pairs_find_where_the_path_comes_back(sfm_room):
    """Out along the room and back: the proposed loop pairs (beyond the sequential window)
    join views of the same place (frames 0-28 all overlap a little, so some pairs are
    looser), and every frame on the way back is paired with its outward twin or a
    neighbour of it."""
    seq, _ = sfm_room
    order = list(range(0, 30, 2)) + list(range(28, -1, -2))  # 30 keyframes, revisiting in reverse
    sift = cv2.SIFT_create(1024)
    desc = [sift.detectAndCompute(cv2.cvtColor(seq.rgb[i], cv2.COLOR_RGB2GRAY), None)[1] for i in order]
    pairs = skf.loop_pairs(skf.bow_vectors([np.clip(d, 0, 255).astype(np.uint8) for d in desc], 256),
                           skf.sequential_gaps(3), 2)
    assert skf.sequential_gaps(3) == {1, 2, 3, 4}
    assert pairs and all(b - a > 4 for a, b in pairs)
    gaps = np.array([abs(order[a] - order[b]) for a, b in pairs])
    # Random pairs would sit ~10 frames apart. Which looser pairs come back besides the close
    # ones varies with the CPU's SIFT and k-means arithmetic (up to 16 frames apart on one
    # Intel Xeon, 12 on AMD EPYC), so the bound is on the bulk.
    assert np.median(gaps) <= 2 and np.mean(gaps <= 6) >= 0.7, gaps
    for b in range(18, 30):  # the way back, beyond the sequential window of the turn
        assert any(abs(order[a] - order[b]) <= 2 for a, c in pairs if c == b), order[b]


def test_dense_registration_reaches_one_keyframe_beyond_the_model():
    # Keyframes 0, 3, 6, 9; only 0 and 3 in the model: frames up to the next chosen
    # keyframe (6) may be registered densely, frames 7-8 (between two keyframes COLMAP
    # could not place) are not even tried.
    assert skf.dense_candidates(10, [0, 3, 6, 9], {0, 3}) == [1, 2, 4, 5, 6]
    assert skf.dense_candidates(7, [0, 3, 6], {3}) == [0, 1, 2, 4, 5, 6]


def test_registration_error_names_the_unregistered_range():
    status = ["keyframe", "tracked"] * 5 + ["interpolated"] * 4 + ["keyframe", "tracked", "interpolated", "keyframe"]
    err = skf.registration_error(status, 7, 0.8)
    assert isinstance(err, TrackingLostError) and err.frame == 10
    assert str(err) == ("SfM registered only 13 of 18 frames (7 of 7 keyframes in COLMAP's model, 6 densely; need "
                        "80%): frames 10-13 and 1 shorter range(s) could not be registered")
    assert skf.registration_error(status, 7, 0.7) is None
    # Named as the video numbers the frames (every 3rd from 30); the error's frame stays a position.
    err = skf.registration_error(status, 7, 0.8, number=lambda i: 30 + 3 * i)
    assert err.frame == 10 and "frames 60-69 and 1 shorter range(s)" in str(err)
    assert skf.unregistered_ranges(np.array([s in TRUSTED_STATES for s in status])) == [(10, 13), (16, 16)]

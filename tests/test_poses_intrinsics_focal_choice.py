"""The focal length from nothing: the rule between the flow search and the vanishing points
(recon.poses.intrinsics.focal_choice), and the range the warning gives."""

import numpy as np
import pytest

from recon.poses.config import FrontendConfig
from recon.poses.intrinsics.calib import FocalSearch
from recon.poses.intrinsics.focal_choice import DISAGREEMENT, VANISHING_ACCURACY, choose_focal, flat_range
from recon.poses.intrinsics.rotation_focal import RotationFocal
from recon.poses.intrinsics.vanishing import VanishingFocal

CFG = FrontendConfig()


def _search(best: float, width: float) -> FocalSearch:
    """A search whose score is a parabola in log f with its minimum at `best`, rising by 2 %
    (FLAT_SCORE) at best * exp(+-width)."""
    focals = best * np.exp(np.linspace(-1.0, 1.0, 41))
    scores = 1.0 + 0.02 * (np.log(focals / best) / width) ** 2
    return FocalSearch(best, list(zip(focals.tolist(), scores.tolist())))


def _vp(focal: float, share: float, trusted: bool = True) -> VanishingFocal:
    return VanishingFocal(focal, share, int(40 * share), 40, 40, trusted)


def test_vanishing_points_most_frames_agree_on_are_taken():
    """Where most frames agree on the vanishing points they are taken, however far the search
    is (the phone video's first clip: search -48 %, vanishing points +1.5 %), and the range
    the warning gives spans both."""
    choice = choose_focal(_search(514.0, 0.02), _vp(1008.0, 1.0), CFG)
    assert choice.focal == 1008.0 and choice.source == "vanishing points"
    assert (choice.low, choice.high) == (514.0, 1008.0) and choice.disagree
    assert "514-1008 px open" in choice.warning(640)
    close = choose_focal(_search(544.0, 0.02), _vp(528.0, 0.68), CFG)
    assert close.focal == 528.0 and not close.disagree and "open" not in close.warning(640)


def test_a_weak_vanishing_point_estimate_only_widens_the_range():
    """A minority of agreeing frames (trusted or not) does not replace the search: on the
    recordings as many such estimates were 50-66 % off as right. It joins the range."""
    for vp in (_vp(253.0, 0.25), _vp(461.0, 0.15, trusted=False)):
        choice = choose_focal(_search(600.0, 0.02), vp, CFG)
        assert choice.focal == 600.0 and choice.source == "flow"
        assert choice.low == pytest.approx(vp.focal / VANISHING_ACCURACY) and choice.high >= 600.0 and choice.disagree


def test_the_range_holds_the_vanishing_points_give_or_take_their_accuracy():
    """ScanNet's second keyframe segment: vanishing points 1.9 % above the camera's 578 px
    on a minority of frames, the search's flat region at 773-929 px. The range reaches
    below the vanishing points by their measured accuracy, so it holds the camera."""
    choice = choose_focal(_search(929.0, 0.1), _vp(589.0, 0.28), CFG)
    assert choice.focal == 929.0 and choice.disagree and choice.low < 578.0 < choice.high


def test_a_flat_search_score_is_a_range():
    """Focal lengths the search scored within 2 % of its best are not ruled out (KITTI's
    straight drive: flat from 340 to 690 px); a sharp minimum with no other estimate gives no
    range."""
    low, high = flat_range(_search(460.0, 0.35))
    assert low == pytest.approx(460.0 * np.exp(-0.35), rel=0.06) and high == pytest.approx(460 * np.exp(0.35), rel=0.06)
    flat = choose_focal(_search(460.0, 0.35), None, CFG)
    assert flat.focal == 460.0 and flat.disagree and flat.low < 369.0 < flat.high
    sharp = choose_focal(_search(524.0, 0.02), None, CFG)
    assert sharp.high / sharp.low < DISAGREEMENT and not sharp.disagree


def test_a_search_that_did_not_bracket_its_minimum_rules_nothing_out():
    """TUM fr1/rpy's second segment: the search's best score lay at the lowest candidate
    (300 px for a 517 px camera, the score still falling), with the vanishing points of a
    few frames at 492 px. Such a search has not found the focal length: the range spans
    every candidate it scored, so it holds the camera."""
    focals = [268.5, 349.2, 440.4, 532.6, 641.8, 772.5, 929.3, 296.9, 285.7]
    scores = [2393.0, 6073.0, 5563.0, 3177.0, 3256.0, 4974.0, 6939.0, 2384.0, 2386.0]
    search = FocalSearch(296.9, list(zip(focals, scores)), bracketed=False)
    assert flat_range(search) == (268.5, 929.3)
    choice = choose_focal(search, _vp(492.2, 0.1, trusted=False), CFG)
    assert choice.focal == 296.9 and choice.disagree and choice.low < 517.0 < choice.high
    assert "268-929 px open" in choice.warning(640)
    bracketed = choose_focal(FocalSearch(296.9, list(zip(focals, scores)), bracketed=True), None, CFG)
    assert bracketed.high < 517.0


def test_a_focal_length_the_search_did_not_bracket_is_not_found():
    """The search's value at an end of its candidates, with no vanishing points taken, is
    not a focal length the frames fixed: the front end does not trust a trajectory built on
    it. Vanishing points most frames agree on are found whatever the search did."""
    edge = FocalSearch(268.5, [(268.5, 1.0), (349.2, 1.5), (929.3, 2.0)], bracketed=False)
    assert not choose_focal(edge, _vp(492.2, 0.1, trusted=False), CFG).found
    assert "--fov" in choose_focal(edge, None, CFG).not_found()
    assert choose_focal(edge, _vp(992.0, 0.8), CFG).found
    assert choose_focal(_search(524.0, 0.02), None, CFG).found


def test_the_rotation_estimate_is_taken_where_trusted_and_no_vanishing_points_are_agreed_on():
    """TUM fr1/rpy 50-99, a camera turning on the spot: the search's minimum lay at the end of
    its sweep (300 px) and the vanishing points were not agreed on; the homographies of its
    turns gave 515 px for a 517 px camera. They are taken, with their own range; untrusted
    they change nothing, and vanishing points most frames agree on still come first."""
    unbracketed = FocalSearch(300.0, [(300.0, 1.0), (400.0, 1.1)], bracketed=False)
    turning = RotationFocal(515.0, 482.0, 554.0, 86, 70, 0.81, True)
    choice = choose_focal(unbracketed, _vp(492.0, 0.3, trusted=False), CFG, turning)
    assert choice.source == "rotation" and choice.focal == 515.0 and choice.found
    assert choice.low == pytest.approx(min(482.0, 492.0 / VANISHING_ACCURACY)) and choice.high == 554.0
    assert choice.candidates["rotation"] == 515.0 and "(rotation)" in choice.warning(640)
    loose = RotationFocal(580.0, 436.0, 767.0, 95, 75, 0.79, False)
    assert choose_focal(unbracketed, None, CFG, loose) == choose_focal(unbracketed, None, CFG)
    assert choose_focal(_search(530.0, 0.02), _vp(528.0, 0.68), CFG, turning).source == "vanishing points"

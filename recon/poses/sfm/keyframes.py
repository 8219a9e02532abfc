"""What the SfM fallback gives COLMAP and how it checks what comes back: keyframes chosen
by image motion, the extra image pairs that close loops, and the registration check
(``recon.poses.sfm.mapper`` runs COLMAP and the dense registration between them).

Keyframes follow accumulated flow (DROID-SLAM's motion filter) and steps the flow cannot
follow; loop pairs come from a bag of visual words over the keyframes' own SIFT
descriptors, TF-IDF weighted (Sivic and Zisserman 2003, "Video Google").
Pure numpy / OpenCV: no COLMAP state here.
More: docs/poses.md#how-the-sfm-fallback-runs-colmap
"""

from __future__ import annotations

from bisect import bisect_left, bisect_right

import cv2
import numpy as np

from recon.poses.matching import flow as fl
from recon.poses.result import TRUSTED_STATES, FrameNumbers, TrackingLostError, by_position, frame_spans


def step_motion(grays: list[np.ndarray], flow_cfg: fl.FlowConfig, px_scale: float, min_correlation: float,
                min_confidence: float, min_local_correlation: float = -1.0) -> tuple[np.ndarray, np.ndarray]:
    """Flow between consecutive frames: mean magnitude (N-1,) in 640-px-wide pixels
    (``px_scale``: such pixels per flow pixel) and whether the flow is trusted (N-1,) bool.

    grays: N flow-resolution grey images (h, w) uint8. A step is untrusted when the grey
    levels the flow joins correlate less than ``min_correlation`` (unrelated images give a
    smooth, self-consistent but meaningless flow: ``flow.match_correlation``), its 7x7
    windows less than ``min_local_correlation`` (``flow.local_correlation``), or its mean
    confidence is below ``min_confidence``; its magnitude is then NaN.
    """
    n = len(grays)
    motion = np.full(max(n - 1, 0), np.nan)
    ok = np.zeros(max(n - 1, 0), dtype=bool)
    for i in range(1, n):
        fwd, _, cf, _ = fl.flow_pair(grays[i - 1], grays[i], flow_cfg)
        if (float(cf.mean()) < min_confidence
                or fl.match_correlation(grays[i - 1], grays[i], fwd, cf) < min_correlation
                or fl.local_correlation(grays[i - 1], grays[i], fwd, cf) < min_local_correlation):
            continue
        motion[i - 1] = fl.mean_magnitude(fwd, cf) * px_scale
        ok[i - 1] = True
    return motion, ok


def _greedy_keyframes(motion: np.ndarray, ok: np.ndarray, spacing: float) -> list[int]:
    """Keyframe indices for one spacing: frame 0, every frame at which the motion summed
    since the last keyframe reaches `spacing`, both frames of an untrusted step, the last."""
    kfs = [0]
    acc = 0.0
    for i in range(1, len(motion) + 1):
        if not ok[i - 1]:
            if kfs[-1] != i - 1:
                kfs.append(i - 1)
            kfs.append(i)
            acc = 0.0
            continue
        acc += motion[i - 1]
        if acc >= spacing:
            kfs.append(i)
            acc = 0.0
    if kfs[-1] != len(motion):
        kfs.append(len(motion))
    return kfs


def select_keyframes(motion: np.ndarray, ok: np.ndarray, spacing: float, max_keyframes: int) -> tuple[list[int], float]:
    """Keyframes (sorted frame indices, first and last included) and the spacing used.

    motion, ok: (N-1,) from ``step_motion``. spacing: the accumulated flow (640-px
    pixels) between keyframes; raised (bisection on its log) until at most
    `max_keyframes` remain. When the untrusted steps alone force more keyframes than
    that, an evenly spread subset of the selection is kept.
    """
    n = len(motion) + 1
    if n == 1:
        return [0], spacing
    kfs = _greedy_keyframes(motion, ok, spacing)
    if len(kfs) <= max_keyframes:
        return kfs, spacing
    total = float(np.nansum(motion)) + spacing
    lo, hi = spacing, max(total, spacing)
    best = _greedy_keyframes(motion, ok, hi)
    for _ in range(30):
        mid = float(np.sqrt(lo * hi))
        trial = _greedy_keyframes(motion, ok, mid)
        if len(trial) <= max_keyframes:
            hi, best = mid, trial
        else:
            lo = mid
        if hi / lo < 1.01:
            break
    if len(best) > max_keyframes:
        pick = np.unique(np.round(np.linspace(0, len(best) - 1, max(max_keyframes, 2))).astype(int))
        best = [best[k] for k in pick]
    return best, hi


def bow_vectors(descriptors: list[np.ndarray], words: int, per_image: int = 1000, seed: int = 0) -> np.ndarray:
    """L2-normalised TF-IDF bag-of-words vectors (K, words') of K images' descriptors
    (each (n_k, 128), SIFT as COLMAP stores them, uint8).

    The vocabulary is k-means on a sample of the same descriptors (at most 200 per image):
    no trained vocabulary ships with the package, and a few hundred words learnt on the
    scene itself are enough to rank a few hundred images. `per_image` descriptors (a
    seeded random subset) make each image's histogram; words' <= words when there are few
    descriptors.
    """
    rng = np.random.default_rng(seed)
    subsets = [d[rng.choice(len(d), min(len(d), per_image), replace=False)].astype(np.float32) if len(d) else
               np.zeros((0, 128), np.float32) for d in descriptors]
    sample = np.concatenate([s[: min(len(s), 200)] for s in subsets])
    K = len(descriptors)
    if len(sample) < 2:
        return np.zeros((K, 1))
    k = int(min(words, len(sample) // 2))
    cv2.setRNGSeed(seed)
    _, _, centres = cv2.kmeans(sample, k, None, (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 15, 0.5), 1,
                               cv2.KMEANS_PP_CENTERS)
    c2 = (centres**2).sum(1)
    tf = np.zeros((K, k))
    for j, s in enumerate(subsets):
        if len(s):
            word = np.argmin(c2[None] - 2.0 * s @ centres.T, axis=1)
            tf[j] = np.bincount(word, minlength=k) / len(s)
    # Words in every image say nothing about where a picture was taken (IDF).
    idf = np.log(K / np.maximum((tf > 0).sum(0), 1))
    v = tf * idf
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def sequential_gaps(overlap: int, quadratic: bool = True) -> set[int]:
    """Keyframe-order gaps b - a that COLMAP's sequential matching pairs: 1..overlap, and
    with its quadratic overlap also 2^j for j < overlap."""
    return set(range(1, overlap + 1)) | ({2**j for j in range(overlap)} if quadratic else set())


def loop_pairs(vectors: np.ndarray, matched_gaps: set[int], per_image: int) -> list[tuple[int, int]]:
    """Pairs (a, b), a < b, of rows of `vectors` (K, D) whose gap b - a is not in
    `matched_gaps` (``sequential_gaps``: pairs sequential matching has already made):
    each keyframe's `per_image` most similar ones by cosine similarity, when that
    similarity is positive."""
    K = len(vectors)
    sim = vectors @ vectors.T
    idx = np.arange(K)
    gap = np.abs(idx[:, None] - idx[None])
    far = (gap > 0) & ~np.isin(gap, sorted(matched_gaps))
    pairs = set()
    for a in range(K):
        cand = idx[far[a] & (sim[a] > 0)]
        for b in cand[np.argsort(-sim[a, cand], kind="stable")[:per_image]]:
            pairs.add((min(a, int(b)), max(a, int(b))))
    return sorted(pairs)


def unregistered_ranges(trusted: np.ndarray) -> list[tuple[int, int]]:
    """Inclusive (first, last) frame ranges where trusted (N,) bool is False, longest first
    (ties: earliest first)."""
    bad = ~np.asarray(trusted, dtype=bool)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], bad.astype(np.int8), [0]])))
    ranges = [(int(a), int(b) - 1) for a, b in zip(edges[::2], edges[1::2])]
    return sorted(ranges, key=lambda r: (r[0] - r[1], r[0]))


def dense_candidates(n: int, kf_ids: list[int], in_model) -> list[int]:
    """Frames (not in the model) worth registering densely: those next to a keyframe in
    the model, i.e. whose nearest chosen keyframe before or after (kf_ids, sorted) is in it
    (``in_model``: a set of frame indices). Keyframes are chosen one flow spacing apart, so
    this reaches one spacing beyond the model and no further: the flow to a model keyframe
    across a keyframe COLMAP could not place is not to be trusted."""
    out = []
    for i in range(n):
        if i in in_model:
            continue
        k, j = bisect_left(kf_ids, i), bisect_right(kf_ids, i)
        prev = kf_ids[k - 1] if k > 0 else None
        nxt = kf_ids[j] if j < len(kf_ids) else None
        if prev in in_model or nxt in in_model:
            out.append(i)
    return out


def registration_error(status: list[str], num_keyframes: int, need: float,
                       number: FrameNumbers = by_position) -> TrackingLostError | None:
    """The one-line failure when fewer than `need` (a fraction) of the frames have a
    trusted status (``result.TRUSTED_STATES``; status: N labels of ``FRAME_STATES``), else
    None. Names the longest range of frames that could not be registered (by `number`)."""
    n = len(status)
    trusted = np.array([s in TRUSTED_STATES for s in status])
    if trusted.sum() >= need * n and trusted.sum() >= 2:
        return None
    model = status.count("keyframe")
    ranges = unregistered_ranges(trusted)
    first, last = ranges[0]
    where = f"frame{'s' if first != last else ''} {frame_spans([(first, last)], number)}"
    more = f" and {len(ranges) - 1} shorter range(s)" if len(ranges) > 1 else ""
    return TrackingLostError(
        f"SfM registered only {int(trusted.sum())} of {n} frames ({model} of {num_keyframes} keyframes in COLMAP's "
        f"model, {int(trusted.sum()) - model} densely; need {need:.0%}): {where}{more} could not be registered",
        frame=first)

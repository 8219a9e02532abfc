"""Frame-pair sampling: the hierarchical Pairs(a, b) sets, keyframes, and the
short-sequence fallback.

Pairs(a, b) = {(i, j) : |i - j| = 2^l, i mod 2^l = 0, a <= l <= b}. Both i and j are
multiples of 2^l, so every pair appears in both directions; (i, j) means "warp frame j
into view i".
"""

from __future__ import annotations

import torch


def hierarchical_pairs(num_frames: int, min_level: int, max_level: int) -> torch.Tensor:
    """Pairs(a, b) for a sequence of `num_frames` frames.

    Args:
        num_frames: sequence length N.
        min_level: a, the smallest level (pairs 2^a frames apart).
        max_level: b, the largest level (pairs 2^b frames apart).

    Returns:
        (P, 2) int64 tensor of (i, j), sorted by level, then i, then j; (0, 2) when no
        level has a pair.
    """
    out = []
    for level in range(min_level, max_level + 1):
        step = 2**level
        anchors = torch.arange(0, num_frames, step)
        lower, upper = anchors[:-1], anchors[1:]
        if lower.numel() == 0:
            continue
        forward = torch.stack([lower, upper], dim=1)
        pairs = torch.cat([forward, forward.flip(1)])
        out.append(pairs[torch.argsort(pairs[:, 0] * num_frames + pairs[:, 1])])
    if not out:
        return torch.zeros((0, 2), dtype=torch.long)
    return torch.cat(out)


def frames_in(pairs: torch.Tensor) -> torch.Tensor:
    """Sorted unique frame indices that appear in a set of pairs.

    Args:
        pairs: (P, 2) frame pairs (i, j).

    Returns:
        (K,) sorted unique frame indices.
    """
    return torch.unique(pairs.flatten())


def connects(pairs: torch.Tensor, frames: torch.Tensor) -> bool:
    """Whether the pairs, as undirected edges, join all of `frames` into one component.

    Args:
        pairs: (P, 2) frame pairs (i, j).
        frames: (K,) the frames to be joined.

    Returns:
        True when every frame is reachable from every other through the pairs (one frame
        or none: True).
    """
    frames = frames.tolist()
    if len(frames) <= 1:
        return True
    root = {f: f for f in frames}

    def find(f: int) -> int:
        while root[f] != f:
            root[f] = root[root[f]]
            f = root[f]
        return f

    for i, j in pairs.tolist():
        if i in root and j in root:
            root[find(i)] = find(j)
    return len({find(f) for f in frames}) == 1


def nearest_keyframe(num_frames: int, keyframes: torch.Tensor) -> torch.Tensor:
    """Temporally nearest keyframe of every frame (the earlier one on ties).

    Args:
        num_frames: sequence length N.
        keyframes: (K,) sorted frame indices, K >= 1.

    Returns:
        (N,) int64 keyframe index per frame.
    """
    frames = torch.arange(num_frames)
    distance = (frames[:, None] - keyframes[None, :]).abs()
    return keyframes[distance.argmin(dim=1)]


def stage_pairs(num_frames: int, stage1_levels: tuple[int, int], stage2_levels: tuple[int, int]):
    """Stage I pairs, keyframes and Stage II pairs, with the short-sequence fallback.

    A sequence needs at least 2^a + 1 frames for Pairs(a, b) of Stage I to be non-empty
    (9 frames for the paper's a = 3). Shorter sequences have no frames far enough apart
    for keyframe selection to mean anything, so every frame becomes a keyframe and
    Stage I runs on every level that exists, Pairs(0, floor(log2(N - 1))); Stage II then
    has nothing left to optimise and its pair set is empty.

    Args:
        num_frames: sequence length N.
        stage1_levels: (a, b) levels of Stage I.
        stage2_levels: (a, b) levels of Stage II.

    Returns:
        (stage1_pairs (P1, 2), keyframes (K,), stage2_pairs (P2, 2)), all int64; the
        keyframes are the frames of the Stage I pairs.
    """
    a, b = stage1_levels
    p1 = hierarchical_pairs(num_frames, a, b)
    if p1.numel() == 0:
        if num_frames < 2:
            empty = torch.zeros((0, 2), dtype=torch.long)
            return empty, torch.arange(num_frames), empty
        top = max(0, (num_frames - 1).bit_length() - 1)
        p1 = hierarchical_pairs(num_frames, 0, top)
        return p1, torch.arange(num_frames), torch.zeros((0, 2), dtype=torch.long)
    keyframes = frames_in(p1)
    p2 = hierarchical_pairs(num_frames, *stage2_levels)
    return p1, keyframes, p2

"""Where a graph's correction goes between two keyframes.

The optimised trajectory moves every frame with its keyframe: the correction of keyframe
a, C_a = est_a odom_a^-1, applied to the frame's odometry pose. The change of correction
from keyframe a to the next keyframe b is then one step at b, wherever between them the
front end's error lies. A front end that knows which of its frames are uncertain (a poor
fit, a re-anchor's jump) reports each frame's *spread*, its share of the noise of the
keyframe's relative pose (any unit: only the ratios count); the frames of a stretch whose
spreads are all given then take exp(w log(C_a^-1 C_b)) of that change, w the cumulative
spread from a up to and including the frame (0 at a, 1 at b): the change is put where the
noise is, as a chain of per-frame factors would put it.
"""

from __future__ import annotations

import numpy as np

from slam.deskew import interpolate_pose


def spread_corrections(
    odom: np.ndarray,
    frame_kf: np.ndarray,
    kf_frames: dict[int, int],
    kf_estimates: dict[int, np.ndarray],
    spread: np.ndarray,
) -> np.ndarray:
    """(N, 4, 4) optimised pose of every frame from its odometry pose ``odom`` (N, 4, 4).

    frame_kf (N,): the keyframe id each frame follows; kf_frames: keyframe id -> the index of
    its own frame; kf_estimates: keyframe id -> its optimised pose; spread (N,): each
    frame's share of its keyframe stretch's noise (NaN: not given). A stretch from keyframe
    a to the next one b gets the spread change of correction where every frame after a's
    up to b's gives a finite spread summing to more than 0; otherwise (and after the last
    keyframe) its frames follow a's correction rigidly."""
    odom = np.asarray(odom, dtype=np.float64)
    frame_kf = np.asarray(frame_kf)
    spread = np.asarray(spread, dtype=np.float64)
    ids = sorted(kf_frames)
    corr = {k: kf_estimates[k] @ np.linalg.inv(odom[kf_frames[k]]) for k in ids}
    out = np.stack([corr[k] for k in frame_kf]) @ odom
    for a, b in zip(ids[:-1], ids[1:], strict=True):
        first, last = kf_frames[a], kf_frames[b]
        share = spread[first + 1 : last + 1]
        if last <= first + 1 or not np.all(np.isfinite(share)) or share.sum() <= 0.0:
            continue
        frames = np.arange(first + 1, last)
        frames = frames[frame_kf[frames] == a]
        if not len(frames):
            continue
        w = np.cumsum(share)[frames - first - 1] / share.sum()
        R, t = interpolate_pose(np.linalg.inv(corr[a]) @ corr[b], w)
        step = np.tile(np.eye(4), (len(frames), 1, 1))
        step[:, :3, :3], step[:, :3, 3] = R, t
        out[frames] = corr[a] @ step @ odom[frames]
    return out


__all__ = ["spread_corrections"]

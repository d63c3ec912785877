"""Registration steps of the DPCR-SLAM front end (``frontends.dpcr2d``) as pure functions:
the check of a first registration against the wheel odometry, and the revisit search of
the submap on the old regional maps (and which maps are old)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from frontends.dpcr2d_maps import Region
from slam.features.lines2d import extract_lines
from slam.mapping.grid2d import compose2d, inverse2d, transform2d
from slam.registration.correlative2d import correlative_search
from slam.registration.plicp import LineReference, PlicpResult, inlier_share, plicp


def check_wheels(
    pts: np.ndarray,
    ref: LineReference,
    predicted: np.ndarray,
    res: PlicpResult,
    prior: dict,
    cfg,
    counts: dict,
) -> PlicpResult:
    """The first registration ``res`` of scan ``pts`` on the submap ``ref``, unless it
    lands beyond ``cfg.wheel_check_m`` / ``wheel_check_deg`` of the wheels' ``predicted``
    pose and PLICP near the prediction (``wheel_check_distance``) fits the submap at
    least as well (share of points within ``wheel_check_inlier_m`` of its lines): a
    registration far from the wheels must be the better fit. ``counts`` (the frame's
    diagnostics) gets the fits and ``wheel_kept`` = 1 when the near one was taken."""
    step = compose2d(inverse2d(predicted), res.pose)
    if cfg.wheel_check_m <= 0 or (
        np.hypot(step[0], step[1]) <= cfg.wheel_check_m
        and abs(np.degrees(step[2])) <= cfg.wheel_check_deg
    ):
        return res
    near_cfg = replace(cfg.plicp, max_distance=cfg.wheel_check_distance)
    near = plicp(pts, ref, predicted, near_cfg, **prior)
    fit = [inlier_share(pts, ref, r.pose, cfg.wheel_check_inlier_m) for r in (res, near)]
    counts.update(wheel_check=1, wheel_check_fit=fit[0], wheel_check_near_fit=fit[1])
    if fit[1] >= fit[0] and near.matches >= cfg.plicp.min_matches:
        counts["wheel_kept"] = 1
        return near
    return res


def search_poor_fit(
    pts: np.ndarray,
    ref: LineReference,
    predicted: np.ndarray,
    res: PlicpResult,
    prior: dict,
    cfg,
    counts: dict,
) -> PlicpResult:
    """The first registration ``res`` of scan ``pts`` on the submap ``ref``, unless its
    RMSE is above ``cfg.poor_fit_rmse`` (m) and PLICP from the best pose of a correlative
    search around the ``predicted`` pose (window ``cfg.poor_fit_search``, same wheel
    ``prior``) brings at least ``cfg.poor_fit_gain`` more of the scan's points within
    ``wheel_check_inlier_m`` of the submap's lines: PLICP converges to the nearest basin,
    which in a fast turn can be a wall several degrees off; its residual rises there, and a
    search over the whole window finds the basin most of the scan agrees with. ``counts``
    gets the two fits and ``poor_fit_kept`` = 1 when the searched pose was taken."""
    if cfg.poor_fit_rmse <= 0 or res.rmse <= cfg.poor_fit_rmse:
        return res
    found = correlative_search(ref.points, pts, predicted, cfg.poor_fit_search)
    other = plicp(pts, ref, found.pose, cfg.plicp, **prior)
    fit = [inlier_share(pts, ref, r.pose, cfg.wheel_check_inlier_m) for r in (res, other)]
    counts.update(poor_fit=1, poor_fit_fit=fit[0], poor_fit_search_fit=fit[1])
    if fit[1] >= fit[0] + cfg.poor_fit_gain and other.matches >= cfg.plicp.min_matches:
        counts["poor_fit_kept"] = 1
        return other
    return res


def old_maps(
    regions: dict[int, Region], division, path: float, pose: np.ndarray, cfg
) -> list[Region]:
    """The maps of the regions near the robot at ``pose`` (centres within
    ``revisit_radius``) that it left ``revisit_path`` m ago or more (``path``: m travelled
    so far), nearest first (at most ``revisit_regions``): what a revisit should land on.
    The maps it drew since, in its current (maybe drifted) frame, are left out."""
    near = []
    for region_id, region in regions.items():
        if region.left_at is None or path - region.left_at < cfg.revisit_path:
            continue
        centre = transform2d(region.offset, division.centre(region_id)[None])[0]
        d = float(np.linalg.norm(centre - pose[:2]))
        if d <= cfg.revisit_radius:
            near.append((d, region_id))
    return [regions[i] for _, i in sorted(near)[: cfg.revisit_regions]]


def revisit_match(
    target: np.ndarray, maps: list[Region], cfg, counts: dict
) -> tuple[bool, np.ndarray | None]:
    """The revisit search of ``Dpcr2dConfig.revisit_search``: the submap's obstacle cells
    ``target`` (map frame) searched over the window ``cfg.revisit`` on the union of the
    old ``maps`` (at their offsets), refined by PLICP; the correction (x, y, theta, map
    frame) when unique, inlying, close to the search's peak and beyond the second
    registration's basin, else None; with whether the search ran (the old maps hold
    enough cells). Its scores go into ``counts`` (the frame's diagnostics)."""
    hits = [m.grid.obstacle_hits() for m in maps]
    reference = np.vstack([transform2d(m.offset, h[0]) for m, h in zip(maps, hits, strict=True)])
    if len(reference) < cfg.min_points:
        return False, None
    weights = np.concatenate([h[1] for h in hits])
    lines = extract_lines(reference, cfg.region_grid.resolution, cfg.lines, weights)
    ref = LineReference.from_lines(lines)
    found = correlative_search(reference, target, np.zeros(3), cfg.revisit)
    counts.update(revisit_score=found.score, revisit_uniqueness=found.uniqueness)
    if found.uniqueness > cfg.revisit_max_uniqueness:
        return True, None
    res = plicp(target, ref, found.pose, cfg.regional_plicp)
    dist, _ = ref.tree.query(transform2d(res.pose, target))
    inliers = float(np.mean(dist < cfg.revisit_match_distance))
    refine = compose2d(inverse2d(found.pose), res.pose)
    counts.update(revisit_inliers=inliers, revisit_m=float(np.linalg.norm(res.pose[:2])),
                  revisit_deg=float(np.degrees(res.pose[2])),
                  revisit_refine_m=float(np.linalg.norm(refine[:2])))  # fmt: skip
    if (
        inliers < cfg.revisit_min_inliers
        or res.matches < cfg.regional_plicp.min_matches
        or np.linalg.norm(refine[:2]) > 2 * cfg.revisit.resolution
        or abs(np.degrees(refine[2])) > 2 * cfg.revisit.angle_step_deg
    ):
        return True, None
    if (
        np.linalg.norm(res.pose[:2]) < cfg.revisit_min_m
        and abs(np.degrees(res.pose[2])) < cfg.revisit_min_deg
    ):
        return True, None  # within the second registration's basin: it runs as usual
    return True, res.pose

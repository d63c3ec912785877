"""DPCR-SLAM front end (paper 003, sections 3.1-3.4): dual registration of 2D laser scans.

Per scan: (1) the first registration, improved PLICP of the scan against the line
features of the submap (the last N scans, lines refreshed every K1 frames); the scan then
joins the submap. (2) Every ``second_every`` frames the second registration, improved
PLICP of the submap's obstacle cells against the line features of the regional map of the
region the robot is in (refreshed every K2 frames); the correction moves the robot and the
submap. A region's map fuses the scans taken in it (probabilistic grid); entering a region
that already has a map registers against that map at once, which is what keeps the
trajectory consistent when the robot comes back.

The workspace is divided into regions of width S (eqs. (3)-(5), ``slam.mapping.grid2d``).
A keyframe is emitted whenever the robot enters another region: its cloud is the obstacle
map of the region just left (in the keyframe's frame), and its ``RegionTag`` names the regions,
so that the region-graph factor plugin (``slam.region_graph``) can link regional maps.
Poses are planar: z = 0, roll = pitch = 0.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import replace

import numpy as np

from frontends.dpcr2d_config import Dpcr2dConfig
from frontends.dpcr2d_maps import Region, fuse_visits
from frontends.dpcr2d_steps import (
    check_wheels,
    old_maps,
    revisit_match,
    search_poor_fit,
)
from slam.features.lines2d import extract_lines
from slam.mapping.grid2d import (
    OccupancyGrid,
    RegionDivision,
    StaleWheels,
    compose2d,
    inverse2d,
    matrix_to_pose2,
    planar_information,
    planar_points,
    pose2_to_matrix,
    predict2d,
    stale_parts,
    transform2d,
    wheel_step,
    wrap,
)
from slam.mapping.scan_window2d import ScanWindow
from slam.registration.correlative2d import correlative_search
from slam.registration.local_lines2d import local_line_reference
from slam.registration.plicp import LineReference, PlicpResult, plicp
from slam.types import FrameDiagnostics, Odometry, RegionAnchor, RegionTag, Scan, TrackingStatus

__all__ = ["Dpcr2d", "Dpcr2dConfig", "matrix_to_pose2", "pose2_to_matrix"]

_PLANE = [3, 4, 2]  # (x, y, theta) in the 6x6 information's (rx, ry, rz, tx, ty, tz)


class Dpcr2d:
    """The DPCR-SLAM front end (plugin name ``dpcr2d``)."""

    Config = Dpcr2dConfig

    def __init__(self, cfg: Dpcr2dConfig | None = None):
        self.cfg = cfg or Dpcr2dConfig()
        self.division = RegionDivision.with_width(
            self.cfg.region_width, self.cfg.region_grid.resolution
        )
        # the scan-matched relative poses are this much better than the planar model; the
        # wheel odometry alone (first registration off) keeps the model
        self._info_scale = self.cfg.graph_info_scale if self.cfg.first_registration else 1.0
        self.pose = np.zeros(3)
        self.motion = np.zeros(3)  # last frame-to-frame motion (own frame)
        self.frame = 0
        self.window: deque[tuple[np.ndarray, np.ndarray]] = deque()  # (points, pose)
        self.submap = OccupancyGrid(self.cfg.submap_grid)
        self.submap_ref: LineReference | None = None
        self.submap_refreshed_at = -(10**9)
        self.fine = ScanWindow(self.cfg.refine)  # raw points of the last scans (refinement)
        self.regions: dict[int, Region] = {}
        self.region: int | None = None
        self.pose_kf = np.zeros(3)
        self.counts = {"rejected": 0, "second_registrations": 0, "second_rejected": 0,
                       "revisit_searches": 0, "reanchored": 0, "wheel_kept": 0,
                       "poor_fit_kept": 0, "stalls": 0}  # fmt: skip
        self.path = 0.0  # path length so far (m)
        self._odom: np.ndarray | None = None
        # stale_wheels: the last readings whose position / heading were new, and the motion
        # the scans registered since
        self._wheels = StaleWheels()
        self._stale = (False, False)  # this frame's reading repeats position, heading
        # running wheel-odometry error^2 (m^2, rad^2), from a wide start (5 cm, 2 deg) until
        # the robot has shown its wheels (about 20 accepted frames)
        self._odom_err2 = np.array([0.05**2, np.radians(2.0) ** 2])
        # graph feedback: the map frame (self.pose, the window, the regions' offsets) vs
        # the reported odometry frame: map = feedback o reported; kf_map[k] the map pose of
        # keyframe k when it was emitted (the frame its region's grid was drawn in)
        self.feedback = np.zeros(3)
        self.kf_id = -1
        self.kf_map: list[np.ndarray] = []
        self._kf_path: list[float] = []  # path length (m) at each keyframe
        self._anchors_taken = False  # a factor plugin turns re-anchors into loop edges
        self._hooked = False  # the pipeline calls on_graph_update (re-anchors are loops)
        self._moved_since_kf = np.zeros(3)  # map-frame moves of on_graph_update since then
        self.visit: OccupancyGrid | None = None  # the scans since the last keyframe
        # visit graph (visit_scans): the last scans at their reported poses, and each
        # keyframe's visit cloud (its frame) for visit_grid
        self._recent: deque[tuple[np.ndarray, np.ndarray]] = deque(
            maxlen=self.cfg.visit_scans + self.cfg.visit_pad
        )
        self._since_kf = 0
        self.visit_points: list[np.ndarray] = []
        # each visit's own scans (pose in the keyframe's frame, points float32): the
        # probabilistic map.pgm (visit_grid with free space)
        self.visit_scans: list[list[tuple[np.ndarray, np.ndarray]]] = []
        self._visit_scan_bytes = 0
        self._lost = False  # the last registered frame was rejected
        # noise (m^2, rad^2) of the poorly fitting frames since the last keyframe
        self._poor_var = np.zeros(2)
        self._turn = 0.0  # absolute turn (rad) since the last keyframe (turn_sigma_m_per_rad)
        self._after_anchor = False  # a visit after an anchored re-anchor (anchor_after_sigma_m)
        self._wheel_gap: np.ndarray | None = None
        self._anchor: RegionAnchor | None = None  # this frame's re-anchor, if any

    # ------------------------------------------------------------------ storage
    def storage_bytes(self) -> dict[str, int]:
        """Bytes of the stored grids: submap and regional maps (paper 003's metric), and
        with ``visit_scans`` the visit clouds."""
        out = {
            "submap": self.submap.nbytes,
            "regional_maps": sum(r.grid.nbytes for r in self.regions.values()),
        }
        if self.cfg.visit_scans:  # the visit graph's clouds (float32 x, y as stored)
            out["visit_clouds"] = sum(8 * len(p) for p in self.visit_points)
            out["visit_scans"] = self._visit_scan_bytes
        return out

    def region_placements(self, estimates: dict[int, np.ndarray]) -> dict[int, np.ndarray] | None:
        """Each regional map's placement (x, y, theta) in the graph's frame, from the
        optimised poses (4x4, by keyframe id) of the keyframes that opened them: the
        corrections ``global_grid`` takes; None without graph feedback (the maps are then
        drawn in the front end's frame: ``slam.io.grid_map.region_corrections``)."""
        if not self._hooked:
            return None
        out = {}
        for region_id, region in self.regions.items():
            T = estimates.get(region.owner)
            if T is not None and region.owner < len(self.kf_map):
                drawn = self.kf_map[region.owner]
                out[region_id] = compose2d(matrix_to_pose2(T), inverse2d(drawn))
        return out

    def on_factor_plugins(self, plugins: list) -> None:
        """The run's factor plugins: re-anchors are visit-graph loop edges only when one
        takes them (``region_edges``); without it (``--no-loop``) the odometry jumps."""
        self._anchors_taken = any(getattr(p, "takes_anchors", False) for p in plugins)

    def on_graph_update(self, view) -> None:
        """After a region-graph optimisation (``cfg.graph_feedback``): move the robot, the
        submap and the regional maps (their offsets) to the optimised poses."""
        if not self.cfg.graph_feedback or len(view.keyframes) != self.kf_id + 1:
            return
        self._hooked = True
        for region in self.regions.values():
            if region.owner < len(self.kf_map):
                T = matrix_to_pose2(view.estimate(region.owner))
                region.offset = compose2d(T, inverse2d(self.kf_map[region.owner]))
        # the map frame: the last keyframe's correction (less what earlier calls since its
        # emission applied already)
        delta = compose2d(
            compose2d(matrix_to_pose2(view.estimate(self.kf_id)), inverse2d(self.kf_map[-1])),
            inverse2d(self._moved_since_kf),
        )
        self._moved_since_kf = compose2d(delta, self._moved_since_kf)
        self.feedback = compose2d(delta, self.feedback)
        if np.linalg.norm(delta[:2]) > 1e-6 or abs(delta[2]) > 1e-7:
            self._move(delta)
        else:
            self.pose = compose2d(delta, self.pose)

    def visit_grid(
        self, estimates: dict[int, np.ndarray], free_space: bool = True
    ) -> OccupancyGrid | None:
        """With ``visit_scans``: the map re-fused from the visits at their optimised poses
        (4x4, by keyframe id); None otherwise. ``free_space`` (map.pgm): every scan of
        each visit with hits and misses along its beams (``slam.mapping.carve2d``, the
        region grid's log-odds, no sub-cell means), so that the map has free space as
        map_server reads it; False: each keyframe's visit cloud, hits only."""
        if not self.cfg.visit_scans:
            return None
        return fuse_visits(self.visit_scans, self.visit_points, estimates,
                           self.cfg.region_grid, free_space)  # fmt: skip

    def global_grid(self, corrections: dict[int, np.ndarray] | None = None) -> OccupancyGrid:
        """The global map: the regional maps fused probabilistically (log-odds added, paper
        003 section 3.5 step 6), each moved by its region's correction (x, y, theta) from the
        region graph (world frame: optimised pose o odometry pose^-1); none = as built."""
        out = OccupancyGrid(self.cfg.region_grid)
        for region_id, region in self.regions.items():
            T = None if corrections is None else corrections.get(region_id)
            out.add_grid(region.grid, T)
        return out

    # ------------------------------------------------------------------ steps
    def _points(self, scan: Scan) -> np.ndarray:
        return planar_points(scan.xyz, self.cfg.max_range)

    def _rebuild_submap(self) -> None:
        self.submap = OccupancyGrid(self.cfg.submap_grid)
        for pts, pose in self.window:
            self.submap.add_scan(transform2d(pose, pts), pose[:2], free_space=False)

    def _refresh_submap_lines(self) -> None:
        obstacles, hits = self.submap.obstacle_hits()
        self.submap_ref = self._reference(obstacles, hits, self.submap, self.cfg.submap_lines)
        self.submap_refreshed_at = self.frame

    def _reference(self, obstacles, hits, grid, kind: str) -> LineReference | None:
        """The line reference of a grid's obstacle points: split-and-merge lines
        (``fitted``) or each point's local line (``local``)."""
        if not len(obstacles):
            return None
        if kind == "local":
            return local_line_reference(obstacles, self.cfg.refine.lines)
        return LineReference.from_lines(
            extract_lines(obstacles, grid.cfg.resolution, self.cfg.lines, hits)
        )

    def _region_ref(self, region: Region) -> LineReference | None:
        if self.frame - region.refreshed_at >= self.cfg.k2 or region.ref is None:
            obstacles, hits = region.grid.obstacle_hits()
            if len(obstacles) < self.cfg.min_points:
                return None
            region.ref = self._reference(obstacles, hits, region.grid, self.cfg.regional_lines)
            region.refreshed_at = self.frame
        return region.ref

    def _prior_info(self, predicted: np.ndarray) -> np.ndarray:
        """3x3 information (x, y, theta; the prediction's frame) of the wheel-odometry
        step to ``predicted``: the model of ``planar_information`` (2 cm + 2 %, 0.5 deg +
        2 %), widened to what this robot's odometry has shown (the running RMS of its
        disagreement with the accepted registrations: FR079's wheels turn 2-5 deg off
        the scans on many frames, a simulated or a good robot's stay within the model)."""
        step = compose2d(inverse2d(self.pose), predicted)
        info = planar_information(pose2_to_matrix(step))[np.ix_(_PLANE, _PLANE)]
        model_t2, model_r2 = 1.0 / info[0, 0], 1.0 / info[2, 2]
        var_t = max(model_t2, self._odom_err2[0])
        var_r = max(model_r2, self._odom_err2[1])
        return np.diag([1.0 / var_t, 1.0 / var_t, 1.0 / var_r])

    def _poor_fit_var(self, status: TrackingStatus, diag: FrameDiagnostics) -> np.ndarray:
        """The noise (m^2, rad^2) this frame adds to its keyframe's: where the scan does not
        pin its pose (still a poor fit after the search, or the prediction kept)
        ``poor_fit_sigma_*``, a registered one at most its disagreement with the wheels
        (``poor_fit_wheel_bound``); a re-anchor that moved the reported pose its own size
        (the jump is a correction of the drift before it, not a motion the scans measured)."""
        cfg = self.cfg
        added = np.zeros(2)
        if self.frame == 0 or not cfg.first_registration or cfg.poor_fit_sigma_m <= 0:
            return added
        kept = status in (TrackingStatus.LOST, TrackingStatus.PREDICTED)
        if kept or diag.counts.get("rmse", 0.0) > cfg.poor_fit_rmse > 0:
            var = np.array([cfg.poor_fit_sigma_m**2, np.radians(cfg.poor_fit_sigma_deg) ** 2])
            gap = None if kept else self._wheel_gap
            if cfg.poor_fit_wheel_bound and gap is not None:
                var = np.minimum(var, [gap[0] ** 2 + gap[1] ** 2, gap[2] ** 2])
            added += var
        if diag.counts.get("reanchored") and self._anchor is None:
            jump = [diag.counts["reanchor_jump_m"], np.radians(diag.counts["reanchor_deg"])]
            added += np.square(jump)
        return added

    def _information(self, relative: np.ndarray) -> np.ndarray:
        """6x6 information of the motion since the last keyframe: the planar model times
        ``graph_info_scale``, its plane's variances widened by the poorly fitting frames."""
        info = self._info_scale * planar_information(relative)
        if not self._poor_var.any():
            return info
        var = 1.0 / np.diag(info)
        var[_PLANE] += self._poor_var[[0, 0, 1]]  # x, y, theta
        return np.diag(1.0 / var)

    def _turn_var(self, step: np.ndarray) -> float:
        """The translation variance (m^2) this frame's turn adds to its keyframe's
        (``turn_sigma_m_per_rad``): the keyframe's grows to (c x the absolute turn since
        it)^2, this frame's part the growth it makes."""
        c = self.cfg.turn_sigma_m_per_rad
        if c <= 0 or self.frame == 0:
            return 0.0
        before = self._turn
        self._turn += abs(float(wrap(step[2])))
        return c**2 * (self._turn**2 - before**2)

    def _anchor_var(self) -> float:
        """The translation variance (m^2) this frame adds to its keyframe's when the visit
        follows a re-anchor made a loop edge (``anchor_after_sigma_m``): an even share,
        sigma^2 / ``visit_scans``, of what the whole visit claims more."""
        s = self.cfg.anchor_after_sigma_m
        if s <= 0 or not self._after_anchor or self.cfg.visit_scans <= 0:
            return 0.0
        return s**2 / self.cfg.visit_scans

    def _spread(self, step: np.ndarray, poor: np.ndarray) -> float:
        """This frame's share of its keyframe's noise (m^2 + rad^2, ``Odometry.spread``): the
        planar model of its own step, scaled as the keyframe's, plus what a poor fit or a
        re-anchor added (``poor``: m^2, rad^2)."""
        var = 1.0 / np.diag(self._info_scale * planar_information(pose2_to_matrix(step)))
        return float(var[_PLANE[0]] + var[_PLANE[2]] + poor[0] + poor[1])

    def _learn_odometry_noise(self, predicted: np.ndarray, registered: np.ndarray) -> None:
        """Running (about 20 frames) mean of the squared wheel-odometry error per frame,
        translation (per axis) and heading, against the accepted registration."""
        err = compose2d(inverse2d(predicted), registered)
        sq = np.array([0.5 * float(err[0] ** 2 + err[1] ** 2), float(err[2]) ** 2])
        self._odom_err2 = 0.95 * self._odom_err2 + 0.05 * sq

    def _plausible(self, res: PlicpResult, start: np.ndarray) -> bool:
        step = compose2d(inverse2d(start), res.pose)
        return (
            res.matches >= self.cfg.plicp.min_matches
            and np.linalg.norm(step[:2]) <= self.cfg.max_step
            and abs(np.degrees(step[2])) <= self.cfg.max_step_deg
        )

    def _second_registration(self, timings: dict) -> None:
        """Submap obstacles -> regional map of the current region; moves robot + submap."""
        region = self.regions.get(self.region) if self.region is not None else None
        if region is None:
            return
        t = time.perf_counter()
        ref = self._region_ref(region)
        target = self.submap.obstacle_points()
        if ref is None or len(target) < self.cfg.min_points:
            return
        target = transform2d(inverse2d(region.offset), target)  # into the grid's frame
        res = plicp(target, ref, np.zeros(3), self.cfg.regional_plicp)
        self.counts["second_registrations"] += 1
        if not self._plausible(res, np.zeros(3)):
            self.counts["second_rejected"] += 1
            return
        delta = region.in_map(res.pose)  # map-frame correction of the submap
        local = compose2d(compose2d(inverse2d(self.pose), delta), self.pose)  # robot frame
        cfg = self.cfg
        large = (0 < cfg.second_max_m < np.hypot(local[0], local[1])
                 or 0 < cfg.second_max_deg < abs(np.degrees(local[2])))  # fmt: skip
        if large and not self._second_evidence(target, ref, res.pose):
            self.counts["second_rejected"] += 1
            return
        if self.cfg.second_gain < 1.0:
            delta = compose2d(compose2d(self.pose, self.cfg.second_gain * local),
                              inverse2d(self.pose))  # fmt: skip
        self._move(delta)
        timings["second_ms"] = (time.perf_counter() - t) * 1e3

    def _second_evidence(self, target: np.ndarray, ref: LineReference, pose: np.ndarray) -> bool:
        """A correction beyond ``second_max_*`` is taken when it brings a share of at least
        ``second_evidence`` more of the submap's cells within ``second_evidence_m`` (m) of the
        regional map than no correction (a real drift does; a distorted map does not);
        ``second_evidence`` < 0: never."""
        cfg = self.cfg
        if cfg.second_evidence < 0:
            return False
        before, _ = ref.tree.query(target)
        after, _ = ref.tree.query(transform2d(pose, target))
        near = cfg.second_evidence_m
        gain = np.mean(after < near) - np.mean(before < near)
        return bool(gain >= cfg.second_evidence)

    def _move(self, delta: np.ndarray) -> None:
        """Move the robot and the submap by the world-frame correction ``delta``."""
        self.pose = compose2d(delta, self.pose)
        self.window = deque((pts, compose2d(delta, pose)) for pts, pose in self.window)
        self.fine.move(delta)
        self._rebuild_submap()
        self._refresh_submap_lines()

    def _reanchor(self, maps: list[Region], counts: dict) -> bool:
        """Wide search of the submap on the old maps around the robot (see
        ``revisit_search``); True when the robot and the submap moved onto them."""
        cfg = self.cfg
        target = self.submap.obstacle_points()
        if len(target) < cfg.min_points:
            return False
        searched, pose = revisit_match(target, maps, cfg, counts)
        if searched:
            self.counts["revisit_searches"] += 1
        if pose is None:
            return False
        res_pose = pose
        self.counts["reanchored"] += 1
        local = compose2d(compose2d(inverse2d(self.pose), res_pose), self.pose)  # robot frame
        counts.update(reanchored=1, reanchor_m=float(np.linalg.norm(res_pose[:2])),
                      reanchor_deg=float(np.degrees(res_pose[2])),
                      reanchor_jump_m=float(np.linalg.norm(local[:2])))  # fmt: skip
        self._move(res_pose)
        big = (np.linalg.norm(local[:2]) > cfg.visit_anchor_min_m
               or abs(np.degrees(local[2])) > cfg.visit_anchor_min_deg)  # fmt: skip
        old_kf = self._anchor_keyframe() if cfg.visit_scans > 0 and big else None
        if self._hooked and self.cfg.reanchor_loops and maps[0].owner < len(self.kf_map):
            # a loop, not odometry: the reported pose does not jump; the keyframe of this
            # frame carries the match as a constraint on the nearest map's keyframe
            self.feedback = compose2d(res_pose, self.feedback)
            placed = compose2d(maps[0].offset, self.kf_map[maps[0].owner])
            z = compose2d(inverse2d(placed), self.pose)
            self._anchor = RegionAnchor(maps[0].owner, (float(z[0]), float(z[1]), float(z[2])))
        elif old_kf is not None:  # the visit graph's loop edge (visit_anchor_edges)
            self.feedback = compose2d(res_pose, self.feedback)
            z = compose2d(inverse2d(self.kf_map[old_kf]), self.pose)
            self._anchor = RegionAnchor(old_kf, (float(z[0]), float(z[1]), float(z[2])))
        else:  # the reported pose jumps: the visit's recent scans shared the drift it removes
            moved = compose2d(compose2d(inverse2d(self.feedback), res_pose), self.feedback)
            self._recent = deque(((p, compose2d(moved, q)) for p, q in self._recent),
                                 maxlen=self._recent.maxlen)  # fmt: skip
        return True

    def _anchor_keyframe(self) -> int | None:
        """The keyframe a re-anchor is measured from (``visit_anchor_edges``): the one made
        ``revisit_path`` m of path or more ago whose map pose lies nearest the robot's
        corrected pose, within ``revisit_radius``; None without one."""
        cfg = self.cfg
        if not cfg.visit_anchor_edges or not self._anchors_taken or not self.kf_map:
            return None
        old = np.flatnonzero(self.path - np.asarray(self._kf_path) >= cfg.revisit_path)
        if not len(old):
            return None
        dist = np.linalg.norm(np.asarray(self.kf_map)[old, :2] - self.pose[:2], axis=1)
        k = int(np.argmin(dist))
        return int(old[k]) if dist[k] <= cfg.revisit_radius else None

    def _visit_clouds(self) -> bool:
        return self.cfg.visit_clouds and self.cfg.graph_feedback and self._hooked

    def _fuse_visit(self, pts: np.ndarray, pose: np.ndarray) -> None:
        """The visit since the last keyframe (map frame): the submap's scans, then each scan."""
        if not self._visit_clouds():
            return
        if self.visit is None:
            self.visit = OccupancyGrid(self.cfg.region_grid)
            for p, q in self.window:
                self.visit.add_scan(transform2d(q, p), q[:2])
            return  # the window holds this scan already
        self.visit.add_scan(transform2d(pose, pts), pose[:2])

    def _fuse_region(self, pts: np.ndarray, pose: np.ndarray) -> None:
        region = self.regions.get(self.region)
        if region is None:  # entering a new region: its map starts from the submap
            region = Region(OccupancyGrid(self.cfg.region_grid), owner=max(self.kf_id, 0))
            for p, q in self.window:
                region.grid.add_scan(transform2d(q, p), q[:2])
            self.regions[self.region] = region
            return
        pose = region.to_grid(pose)
        region.grid.add_scan(transform2d(pose, pts), pose[:2])

    def _visit_cloud(self, anchor: np.ndarray) -> np.ndarray:
        """The keyframe's visit cloud ((N, 3) float32, its frame): the scans since the
        keyframe before and ``visit_pad`` before those (``slam.visit_graph.visit_cloud``)."""
        from slam.visit_graph import visit_cloud

        n = min(len(self._recent), self._since_kf + (self.cfg.visit_pad if self.kf_id else 0))
        recent = list(self._recent)[len(self._recent) - n :]
        inv = inverse2d(anchor)
        own = list(self._recent)[len(self._recent) - min(self._since_kf, len(self._recent)) :]
        self.visit_scans.append([(compose2d(inv, q), p.astype(np.float32)) for p, q in own])
        self._visit_scan_bytes += sum(8 * len(p) + 24 for p, _ in own)
        self._since_kf = 0
        local = visit_cloud(np.array([q for _, q in recent]), [p for p, _ in recent], anchor,
                            self.cfg.region_grid.resolution)  # fmt: skip
        self.visit_points.append(local.astype(np.float32))
        return np.column_stack([local, np.zeros(len(local))]).astype(np.float32)

    # ------------------------------------------------------------------ contract
    def _track(
        self, scan: Scan, pts: np.ndarray, diag: FrameDiagnostics
    ) -> tuple[np.ndarray, TrackingStatus]:
        """The first registration: the scan on the submap's lines from the prediction
        (wheel odometry or constant velocity), the prediction kept when implausible (LOST)
        or when the scan is not registered (PREDICTED; the first scan starts the map)."""
        cfg = self.cfg
        odom = None if scan.odom is None else np.asarray(scan.odom, dtype=np.float64)
        use = cfg.use_odometry
        predicted = (
            predict2d(self.pose, self.motion, self._odom if use else None, odom)
            if self.frame
            else self.pose
        )
        from_wheels = bool(use and self.frame and self._odom is not None and odom is not None)
        if cfg.stale_wheels and odom is not None:
            predicted = self._catch_up(predicted, odom, from_wheels)
        self._odom = odom
        if len(pts) < cfg.min_points:
            diag.skipped = f"too few points ({len(pts)})"
            return predicted, TrackingStatus.PREDICTED
        if not (cfg.first_registration and self.submap_ref is not None and len(self.submap_ref)):
            first = self.frame == 0  # the first scan starts the map
            return predicted, TrackingStatus.TRACKED if first else TrackingStatus.PREDICTED
        t = time.perf_counter()
        prior = {}
        if from_wheels and cfg.odometry_prior:
            prior = {"prior": predicted, "prior_info": self._prior_info(predicted)}
        start = predicted
        if not from_wheels and self.frame <= cfg.start_frames:  # the motion is unknown
            start = correlative_search(self.submap_ref.points, pts, predicted, cfg.start).pose
        res = plicp(pts, self.submap_ref, start, cfg.plicp, **prior)
        if from_wheels and self._plausible(res, predicted):
            kept = check_wheels(pts, self.submap_ref, predicted, res, prior, cfg, diag.counts)
            self.counts["wheel_kept"] += int(kept is not res)
            res = kept
        if self._plausible(res, predicted):
            searched = search_poor_fit(
                pts, self.submap_ref, predicted, res, prior, cfg, diag.counts
            )
            self.counts["poor_fit_kept"] += int(searched is not res)
            res = searched
        diag.timings_ms["first_ms"] = (time.perf_counter() - t) * 1e3
        diag.counts.update(rmse=res.rmse, matches=res.matches, iterations=res.iterations)
        if not self._plausible(res, predicted):
            self.counts["rejected"] += 1
            diag.rejected = True
            return predicted, TrackingStatus.LOST
        if cfg.refine.scans and len(self.fine):
            t = time.perf_counter()
            res = self._refine(pts, res, prior, diag.counts)
            diag.timings_ms["refine_ms"] = (time.perf_counter() - t) * 1e3
        self._wheel_gap = compose2d(inverse2d(predicted), res.pose) if from_wheels else None
        if from_wheels:
            self._learn_odometry_noise(predicted, res.pose)
        return res.pose, TrackingStatus.RECOVERED if self._lost else TrackingStatus.TRACKED

    def _catch_up(self, predicted: np.ndarray, odom: np.ndarray, from_wheels: bool) -> np.ndarray:
        """``stale_wheels``: the prediction from the wheels, a stale part of the reading
        caught up when the step is a stall's (``slam.mapping.grid2d.wheel_step``); the
        stale parts updated for the next frame."""
        cfg = self.cfg
        stale_xy, stale_heading = stale_parts(self._odom, odom)
        if from_wheels:
            step, xy, heading = wheel_step(self._odom, odom, self.motion, self._wheels,
                                           cfg.stall_m, np.radians(cfg.stall_deg))  # fmt: skip
            if xy or heading:
                predicted = compose2d(self.pose, step)
                self.counts["stalls"] += 1
        self._wheels.update(odom, stale_xy, stale_heading)
        self._stale = (stale_xy, stale_heading)
        return predicted

    def _refine(self, pts: np.ndarray, res: PlicpResult, prior: dict, counts: dict) -> PlicpResult:
        """The first registration refined by PLICP on the local lines of the raw points
        of the last scans (``refine``, ``slam.mapping.scan_window2d``), with the same wheel
        prior; kept when within ``refine_max_m`` / ``refine_max_deg`` of it."""
        cfg = self.cfg
        out = plicp(pts, self.fine.reference(), res.pose, cfg.refine_plicp, **prior)
        step = compose2d(inverse2d(res.pose), out.pose)
        ok = (
            out.matches >= cfg.refine_plicp.min_matches
            and np.hypot(step[0], step[1]) <= cfg.refine_max_m
            and abs(np.degrees(step[2])) <= cfg.refine_max_deg
        )
        counts.update(refine_m=float(np.hypot(step[0], step[1])), refine_kept=int(ok))
        return out if ok else res

    def _add_to_submap(self, pts: np.ndarray) -> None:
        """The scan joins the sliding submap (the oldest leaves it); lines refreshed every K1."""
        cfg, pose = self.cfg, self.pose
        if len(pts) >= cfg.min_points:
            if cfg.refine.scans:
                self.fine.add(pts, pose)
            self.window.append((pts, pose.copy()))
            self.submap.add_scan(transform2d(pose, pts), pose[:2], free_space=False)
            if len(self.window) > cfg.submap_scans:
                old_pts, old_pose = self.window.popleft()
                self.submap.add_scan(
                    transform2d(old_pose, old_pts), old_pose[:2], weight=-1.0, free_space=False
                )
        if self.frame - self.submap_refreshed_at >= cfg.k1 or self.submap_ref is None:
            self._refresh_submap_lines()

    def _regions_step(
        self, pts: np.ndarray, previous: np.ndarray, diag: FrameDiagnostics
    ) -> tuple[bool, int, int | None, bool]:
        """Which region the robot is in (the revisit search on entering one), the
        regional map fused, the second registration; returns (keyframe?, region, the
        region left, entered another region?)."""
        cfg, timings = self.cfg, diag.timings_ms
        self.path += float(np.linalg.norm(self.pose[:2] - previous[:2]))
        region = int(self.division.region_of(self.pose[:2][None])[0])
        entered = region != self.region
        left = self.region
        if left is not None and left in self.regions and entered:
            self.regions[left].left_at = self.path
        t = time.perf_counter()
        reanchored = False
        periodic = cfg.revisit_every > 0 and self.frame % cfg.revisit_every == 0
        if (entered or periodic) and cfg.revisit_search and cfg.second_registration:
            maps = old_maps(self.regions, self.division, self.path, self.pose, cfg)
            if maps:
                reanchored = self._reanchor(maps, diag.counts)
                timings["revisit_ms"] = (time.perf_counter() - t) * 1e3
            if reanchored:  # the region the corrected pose is in
                region = int(self.division.region_of(self.pose[:2][None])[0])
                entered = region != left
        self.region = region
        if cfg.visit_scans > 0:  # a re-anchor's jump ends the visit: no cloud spans it
            # an anchored one ends it too: its keyframe carries the loop edge
            is_kf = self.frame == 0 or (self.frame + 1) % cfg.visit_scans == 0 or reanchored
        else:
            is_kf = self.frame == 0 or entered or self._anchor is not None
        if is_kf:
            self.kf_id += 1
        if len(pts) >= cfg.min_points:
            self._fuse_region(pts, self.pose)
            self._fuse_visit(pts, self.pose)
        due = self.frame % cfg.second_every == 0 or (entered and region in self.regions)
        if cfg.second_registration and due and not reanchored:
            self._second_registration(timings)
        return is_kf, region, left, entered

    def _region_cloud(self, left: int | None) -> np.ndarray | None:
        """A region keyframe's cloud: the map of the region just left (or the visit with
        ``visit_clouds``) in the keyframe's frame; None without a region event."""
        cloud = None
        if left is not None and left in self.regions:
            if self._visit_clouds():
                obs = self.visit.obstacles() if self.visit is not None else np.zeros((0, 2))
            else:
                left_region = self.regions[left]
                obs = transform2d(left_region.offset, left_region.grid.obstacles())
            local = transform2d(inverse2d(self.pose), obs)
            cloud = np.column_stack([local, np.zeros(len(local))]).astype(np.float32)
        self.visit = None  # the next visit starts after the graph update
        self._moved_since_kf = np.zeros(3)
        return cloud

    def process(self, scan: Scan) -> Odometry:
        t0 = time.perf_counter()
        diag = FrameDiagnostics()
        timings = diag.timings_ms
        self._anchor = None
        pts = self._points(scan)
        pose, status = self._track(scan, pts, diag)
        if status is not TrackingStatus.PREDICTED:  # lost until a registration is trusted
            self._lost = status is TrackingStatus.LOST
        if any(self._stale):  # the motion the scans give while the wheels repeat themselves
            self._wheels.registered(compose2d(inverse2d(self.pose), pose), *self._stale)
        previous, self.pose = self.pose, pose
        t = time.perf_counter()
        self._add_to_submap(pts)
        timings["submap_ms"] = (time.perf_counter() - t) * 1e3
        t = time.perf_counter()
        is_kf, region, left, entered = self._regions_step(pts, previous, diag)
        timings["region_ms"] = (time.perf_counter() - t) * 1e3

        reported = compose2d(inverse2d(self.feedback), self.pose)
        T = pose2_to_matrix(reported)
        relative = np.linalg.inv(pose2_to_matrix(self.pose_kf)) @ T
        cloud, tag = None, None
        visits = self.cfg.visit_scans > 0
        if visits:
            self._recent.append((pts, reported))
            self._since_kf += 1
        if is_kf and visits:
            cloud = self._visit_cloud(reported)
            tag = RegionTag(region, -1, visit=True)
        elif is_kf:  # a re-anchor inside a region: no region event
            left = left if entered else None
            cloud = self._region_cloud(left)
            tag = RegionTag(region, -1 if left is None else left)
        if self._anchor is not None:
            tag = replace(tag or RegionTag(), anchor=self._anchor)
        step = compose2d(inverse2d(previous), self.pose)
        poor = self._poor_fit_var(status, diag) + [self._turn_var(step) + self._anchor_var(), 0.0]
        self._poor_var += poor
        spread = self._spread(step, poor)
        info = self._information(relative)
        if is_kf:
            self.pose_kf = reported
            self.kf_map.append(self.pose.copy())
            self._kf_path.append(self.path)
            self._poor_var = np.zeros(2)
            self._turn = 0.0
            self._after_anchor = self._anchor is not None
        self.motion = step.copy() if self.frame else np.zeros(3)
        self.motion[2] = float(wrap(self.motion[2]))
        self.frame += 1
        timings["total_ms"] = (time.perf_counter() - t0) * 1e3
        diag.counts.update(regions=len(self.regions), **self.storage_bytes())
        return Odometry(
            stamp=scan.stamp,
            pose=T,
            is_keyframe=is_kf,
            relative=relative,
            info=info,
            cloud=cloud,
            status=status,
            diagnostics=diag,
            region=tag,
            spread=spread,
        )

"""Settings of the DPCR-SLAM front end (``frontends.dpcr2d``, paper 003)."""

from __future__ import annotations

from dataclasses import dataclass, field

from slam.errors import ConfigError
from slam.features.lines2d import LineConfig
from slam.mapping.grid2d import GridConfig
from slam.mapping.scan_window2d import ScanWindowConfig
from slam.registration.correlative2d import CorrelativeConfig
from slam.registration.plicp import PlicpConfig


def _submap_grid() -> GridConfig:
    # hits only over a sliding window: a cell is an obstacle once two scans hit it
    return GridConfig(hit=1.0, miss=-1.0, clamp=300.0, occupied=0.5)


@dataclass
class Dpcr2dConfig:
    """DPCR-SLAM settings (paper 003).

    submap_scans: N, the scans of the submap; k1 / k2: frames between line refreshes of
    the submap / regional map (K2 > K1); region_width: S (m; the paper's study
    recommends 4 m); second_every: frames between second registrations;
    first_registration / second_registration: switch either off (the ablation; both off
    = wheel odometry with maps); use_odometry: predict from the wheel odometry when the
    input has it (``Scan.odom``; else constant velocity) - along a corridor whose ends
    the laser does not see, nothing else says how far the robot went; odometry_prior:
    the wheel-odometry increment also enters the first registration's solve as a
    weighted prior (``slam.registration.plicp``; noise model
    ``slam.mapping.grid2d.planar_information`` of the step), not only as its start;
    max_range (m):
    scan points beyond are dropped; min_points: fewest points of a usable scan;
    max_step (m, deg): a registration moving the pose further than this from the
    prediction is rejected (the prediction is kept); submap_grid / region_grid: the two
    grids (5 cm cells).

    revisit_search: on entering a region, the submap is searched over the wide window
    ``revisit`` (rotations and shifts, ``slam.registration.correlative2d``) on the maps
    of the regions around (centres within ``revisit_radius`` m, the nearest
    ``revisit_regions``) that the robot left ``revisit_path`` m ago or more (drawn before
    the drift since; the drifted pose may well fall in a region never mapped), before the
    second registration, which only converges within ~0.3 m / a few degrees: real
    revisits come back 15 deg / metres off. The match is taken when it is unique (second
    peak / best <= ``revisit_max_uniqueness``) and, after PLICP, ``revisit_min_inliers``
    of the submap's obstacle cells lie within ``revisit_match_distance`` of the map; the
    robot and the submap then move onto the region's map (re-anchored), so that the scans
    that follow draw its walls where they already are. A correction within
    ``revisit_min_m`` and ``revisit_min_deg`` is left to the second registration.
    revisit_every (0: off): also search every that many frames, not only on region
    changes: a front end that lost its heading where no old map was (FR079, scans 4545 -
    4575) comes back along corridors where the search on each region change is
    ambiguous, and is re-anchored by metres at the first unique one; searched often, it
    is re-anchored where the maps first tell (docs/dpcr2d.md, "Drifting off the maps
    between region changes"; off by default: the short relations' p90 is worse).

    graph_feedback: after each region-graph optimisation (the pipeline's
    ``on_graph_update``) the robot, its submap and every regional map move to where the
    graph put them: a regional map is placed by the optimised pose of the keyframe that
    opened it (a per-region offset, the grid itself is never resampled), the robot by that
    of the last keyframe; scans that follow are drawn, and registered, in the graph's
    frame. The reported odometry stays continuous (the moves are not in it: the graph made
    them). visit_clouds (with graph_feedback): a keyframe's cloud, what the region edges
    register, is the visit just ended (the submap at its start and every scan since, in
    the front end's frame) instead of the regional map: a revisited map's older part lies
    where the graph put it, and an edge from it would measure the graph's own estimate.
    reanchor_loops (with graph_feedback): a re-anchor is an edge of the region graph
    (this keyframe on the nearest old map's keyframe), not a jump of the odometry.

    visit_scans (0: off): the visit graph (``slam.visit_graph``): a keyframe at
    frame 0 and at the last frame of every ``visit_scans`` (not at region changes) and
    at a re-anchor (its jump ends the visit; the visit's earlier scans, which shared the
    drift it removes, are moved with it), its cloud the hit cells of the scans since the
    keyframe before and the ``visit_pad`` before those, drawn at this front end's own
    poses (measurement only, never a map the graph moved), for the region-edges plugin's
    visit loop search; ``visit_grid`` fuses these clouds at the optimised keyframe poses
    (``map.pgm``). Needs graph_feedback off. visit_anchor_edges (with visit_scans): a
    re-anchor is a loop edge of the visit graph instead of a jump of the odometry: its
    frame is a keyframe whose pose on the old map is measured in the frame of the nearest
    keyframe made ``revisit_path`` m of path or more before (``RegionTag.anchor``;
    Gaussian, never gated: the wide search vouched for it), and the graph spreads the
    correction over the stretch that drifted. A re-anchor that moves the robot less than
    ``visit_anchor_min_m`` and ``visit_anchor_min_deg`` (3 sigmas of the edge's claimed
    5 cm / 1 deg: the jumped front end agrees with such an edge within its noise), one
    without an old keyframe within ``revisit_radius``, or without a factor plugin that
    takes the edge (``--no-loop``), jumps the odometry as before.

    wheel_check_m / wheel_check_deg (0: off): a first registration that lands farther
    than this from the wheel-odometry prediction must fit the submap better than PLICP
    from the prediction within ``wheel_check_distance`` m (the share of the scan's points
    within ``wheel_check_inlier_m`` of the submap's lines, ``plicp.inlier_share``); else
    the registration near the wheels is taken (MIT-CSAIL's 5 Hz turns: PLICP jumps to a
    wall 20 deg off the wheels and the scans). poor_fit_rmse (m; 0: off): a first
    registration with a larger RMSE (about twice the usual: median 1.5 - 2.2 cm on the
    real logs) is searched again, a correlative search over ``poor_fit_search`` around the
    prediction then PLICP, and the searched pose taken when it brings at least
    ``poor_fit_gain`` more of the scan's points within ``wheel_check_inlier_m`` of the
    submap's lines (``frontends.dpcr2d_steps.search_poor_fit``): FR079's heading, lost
    by 7.6 deg in one registration of a fast turn (scan 4544), is kept (docs/dpcr2d.md,
    "A poor first registration searched again").
    start_frames: without wheel odometry the first registrations of these frames search
    the motion (``start``, a correlative window around the constant-velocity prediction)
    instead of assuming rest.
    stale_wheels: the position or the heading of a wheel reading that repeats the last
    one exactly did not update (``slam.mapping.grid2d.stale_parts``); at the first new
    value, a step that departs from the robot's last motion by more than ``stall_m`` /
    ``stall_deg`` is a stall's catch-up when the wheels' motion since that part's last
    new value, less the motion the scans registered meanwhile, lies closer to it
    (``wheel_step``; otherwise the robot was at rest in that part, as in a turn on the
    spot). Off, a stalled odometry's catch-up step (MIT-CSAIL at 5 Hz: 2 - 4 stale
    readings, then up to 0.95 m / 86 deg at once) is a prediction, and a wheel prior, of
    the stall's motion counted twice, which the first registration cannot undo
    (MIT-CSAIL's front end turned 41 - 53 deg too far there). The tolerances are more
    than an indoor robot's speed changes between two scans and less than a stall's
    catch-up.

    graph_info_scale: a keyframe's information (the odometry factor of the graph) is the
    model of ``planar_information`` (2 cm + 2 %, 0.5 deg + 2 % of the turn) times this:
    on the real logs this front end's relative poses are about 8x more accurate than
    that model (self-consistency relations, median 0.8 - 1 cm over 0.5 - 2 m; the
    optimised graphs leave the odometry factors at chi2 / dof 0.01 - 0.04), and a loose
    chain lets the loop edges bend the trajectory between vertices, which the
    relations see as steps (Intel 1.09 -> 1.24 cm mean with 1, 1.08 cm with 64). Only with
    the first registration on (wheel odometry alone keeps the model).
    poor_fit_sigma_m / poor_fit_sigma_deg (0: off): that accuracy holds only where the
    scans fit; each frame whose registration still fits worse than ``poor_fit_rmse``
    after the search, or that kept its prediction (rejected, too few points), adds this
    much (1 sigma, independent per frame: about such a fit's RMSE) to the keyframe's
    odometry noise, and a re-anchor (``revisit_search``) that moved the reported pose its
    own size, so that the loop edges can take out what such a stretch got wrong (FR079
    read at 1 deg: 26 reversing and turning frames with 20 - 35 % of the points on the
    submap slipped 1.1 m / 2 deg, and every loop edge that saw it was switched off
    against a chain claiming centimetres; docs/dpcr2d.md, "Where the scans do not fit").
    On in ``dpcr2d`` (5 cm, 1 deg: the visit graph's edges claim their real noise); off
    for the region graph, whose edges claim PLICP's millimetres and bend a looser chain.
    poor_fit_wheel_bound: a registered frame's share is at most how far its registration
    and its wheel odometry disagree (translation, heading): where the two agree the frame
    did not slip, and the loop edges should not put a correction there (Intel: the short
    relations of the graph 1.25 -> 1.24 cm, its front end's); a kept prediction and a
    re-anchor are not bounded.
    turn_sigma_m_per_rad (m per rad, 0: off): the planar model gives a keyframe's
    translation noise by the distance travelled only, so a stretch that turns in place
    claims millimetres, but scans taken while turning are skewed by the turn and their
    registrations' translation errors add up with it (one sense of rotation: the same
    sign); each frame adds to its keyframe's translation variance (both axes) so that it
    is (this x the absolute turn since the keyframe)^2, its own part of that as its
    spread, and the graph puts a correction where the robot turned instead of on the
    next poorly fitting frame (docs/dpcr2d.md, "Where the visit graph is worse than its
    front end").
    anchor_after_sigma_m (m, 0: off): the visit after a re-anchor made a loop edge
    (``visit_anchor_edges``) claims this much more translation noise (both axes), spread
    evenly over its frames (this^2 / ``visit_scans`` each): the front end has just moved its
    submap onto an old map, and its motion over the next visit is measured on that move
    (Intel: the visit after three re-anchors within 8 scans of a turn on the spot slid
    0.2 - 0.3 m along a corridor against every loop edge there; docs/dpcr2d.md,
    "Re-anchors under the gate").

    refine (``slam.mapping.scan_window2d.ScanWindowConfig``; ``refine.scans`` 0: off):
    after the first registration, PLICP of the scan on the raw points of the last
    ``refine.scans`` scans (each taken >= 5 cm / 2 deg from the one before), every point
    matched to the line of its own neighbourhood (``slam.registration.local_lines2d``),
    with the same wheel prior, settings ``refine_plicp``; its pose is taken when within
    ``refine_max_m`` / ``refine_max_deg`` of the first registration's. The submap's lines
    (split and merge over 5 cm cells, 6 cm tolerance) leave a few mm - cm of bias along
    real walls that are not straight; the scans' own points do not. submap_lines /
    regional_lines: "fitted" (those lines) or "local" (each obstacle cell's local line).

    second_gain: the share of the second registration's correction applied (expressed
    about the robot): the correction is the regional map's noise as much as the drift
    since the last one, and jumps of the trajectory every ``second_every`` frames are
    what the short relations see; a gain below 1 averages that noise while the drift is
    still taken out over a few registrations. second_max_m / second_max_deg (0: off): a
    larger correction (about the robot) is not applied (the revisit search handles real
    jumps). second_evidence (< 0: off) / second_evidence_m: such a larger correction is
    taken all the same when it brings at least that share more of the submap's cells
    within second_evidence_m of the regional map than no correction. All off by default:
    measured on the real logs, not kept (docs/dpcr2d.md, "The short-range residual of the
    front end", "Large second-registration corrections on evidence").
    """

    submap_scans: int = 20
    k1: int = 5
    k2: int = 20
    region_width: float = 4.0
    second_every: int = 5
    first_registration: bool = True
    second_registration: bool = True
    use_odometry: bool = True
    odometry_prior: bool = True
    max_range: float = 30.0
    min_points: int = 30
    max_step: float = 0.5
    max_step_deg: float = 20.0
    submap_grid: GridConfig = field(default_factory=_submap_grid)
    region_grid: GridConfig = field(default_factory=GridConfig)
    lines: LineConfig = field(default_factory=LineConfig)
    plicp: PlicpConfig = field(default_factory=PlicpConfig)
    regional_plicp: PlicpConfig = field(default_factory=lambda: PlicpConfig(max_distance=0.3))
    revisit_search: bool = True
    revisit_path: float = 10.0
    revisit_radius: float = 6.0
    revisit_every: int = 0
    revisit_regions: int = 6
    revisit: CorrelativeConfig = field(default_factory=lambda: CorrelativeConfig(max_shift=4.0))
    revisit_max_uniqueness: float = 0.8
    revisit_min_inliers: float = 0.5
    revisit_match_distance: float = 0.1
    revisit_min_m: float = 0.15
    revisit_min_deg: float = 2.0
    graph_feedback: bool = False
    visit_clouds: bool = True
    reanchor_loops: bool = True
    visit_scans: int = 0
    visit_pad: int = 15
    visit_anchor_edges: bool = False
    visit_anchor_min_m: float = 0.15
    visit_anchor_min_deg: float = 3.0
    wheel_check_m: float = 0.1
    wheel_check_deg: float = 4.0
    wheel_check_distance: float = 0.15
    wheel_check_inlier_m: float = 0.05
    poor_fit_rmse: float = 0.04
    poor_fit_gain: float = 0.1
    poor_fit_search: CorrelativeConfig = field(
        default_factory=lambda: CorrelativeConfig(max_shift=0.5, max_angle_deg=20.0)
    )
    start_frames: int = 3
    stale_wheels: bool = True
    stall_m: float = 0.1
    stall_deg: float = 5.0
    graph_info_scale: float = 64.0
    poor_fit_sigma_m: float = 0.0
    poor_fit_sigma_deg: float = 1.0
    poor_fit_wheel_bound: bool = True
    turn_sigma_m_per_rad: float = 0.0
    anchor_after_sigma_m: float = 0.0
    start: CorrelativeConfig = field(
        default_factory=lambda: CorrelativeConfig(max_shift=0.5, max_angle_deg=20.0)
    )
    submap_lines: str = "fitted"
    regional_lines: str = "fitted"
    second_gain: float = 1.0
    second_max_m: float = 0.0
    second_max_deg: float = 0.0
    second_evidence: float = -1.0
    second_evidence_m: float = 0.05
    refine: ScanWindowConfig = field(default_factory=ScanWindowConfig)
    refine_plicp: PlicpConfig = field(
        default_factory=lambda: PlicpConfig(max_distance=0.3, max_iterations=10, tolerance=1e-4)
    )
    refine_max_m: float = 0.1
    refine_max_deg: float = 2.0

    def __post_init__(self) -> None:
        if self.submap_scans < 1 or self.k1 < 1 or self.k2 < self.k1 or self.second_every < 1:
            raise ConfigError("dpcr2d: submap_scans, k1, second_every >= 1 and k2 >= k1")
        if not self.region_width > 0:
            raise ConfigError(f"dpcr2d: region_width must be > 0, got {self.region_width}")
        if self.submap_lines not in ("fitted", "local") or self.regional_lines not in (
            "fitted",
            "local",
        ):
            raise ConfigError("dpcr2d: submap_lines and regional_lines are 'fitted' or 'local'")
        if not 0 < self.second_gain <= 1:
            raise ConfigError(f"dpcr2d: second_gain must be in (0, 1], got {self.second_gain}")
        if self.visit_scans < 0 or self.visit_pad < 0:
            raise ConfigError("dpcr2d: visit_scans and visit_pad must be >= 0")
        if self.visit_scans and self.graph_feedback:
            raise ConfigError(
                "dpcr2d: visit_scans needs graph_feedback off (measurement-only clouds)"
            )

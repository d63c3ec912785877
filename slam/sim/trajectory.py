"""Smooth ground-robot trajectories along closed planar curves, and car drives along open
routes (:func:`route_trajectory`: speed limits, stops, acceleration limits, body sway).

The robot follows a closed curve for ``loops`` laps (e.g. 1.1 so that it revisits its
start). Speed is continuous: it ramps up from a crawl and slows in tight turns; yaw
follows the path tangent; a small roll/pitch wobble (default 1 deg) exercises 6-DoF.

Optional (off by default): smooth random speed changes (accelerating and braking),
high-frequency roll/pitch vibration (a few Hz, like a wheeled robot on paving), and
uneven terrain: the robot then drives on a height field, its sensor at ``height`` above
the ground and its attitude following the local slope.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from slam.errors import InputError

_DS = 0.01  # table spacing along the path (m)


def resample_closed(xy: np.ndarray, ds: float = _DS) -> np.ndarray:
    """Resample a closed polyline (N,2) (last point != first) at arc-length spacing ~ds (m)."""
    xy = np.asarray(xy, dtype=float)
    closed = np.vstack([xy, xy[:1]])
    seg = np.hypot(*np.diff(closed, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(np.ceil(s[-1] / ds)), 8)
    s_new = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.column_stack([np.interp(s_new, s, closed[:, 0]), np.interp(s_new, s, closed[:, 1])])


def corner_profile(length: float, ds: float = 0.002) -> np.ndarray:
    """xy (K,2) of a 90-degree left turn starting at the origin heading +x, curvature
    ``pi/length * sin^2(pi u/length)`` (zero at both ends: continuous yaw rate)."""
    u = np.arange(0.0, length + ds / 2, ds)
    heading = 0.5 * np.pi * (u / length - np.sin(2 * np.pi * u / length) / (2 * np.pi))
    x = np.concatenate([[0.0], np.cumsum(0.5 * (np.cos(heading[1:]) + np.cos(heading[:-1])) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (np.sin(heading[1:]) + np.sin(heading[:-1])) * ds)])
    return np.column_stack([x, y])


def rounded_rectangle(width: float, height: float, corner_length: float = 2.5) -> np.ndarray:
    """Closed counter-clockwise centre line (N,2) of a width x height (m) rectangle centred at
    the origin with smooth corners; starts at the middle of the bottom (south) side heading +x."""
    c = corner_profile(corner_length)
    d = c[-1, 0]  # the corner advances d along its entry direction and d sideways
    if 2 * d >= min(width, height):
        raise InputError("rounded_rectangle: corners longer than the sides")
    pieces = []
    legs = [(width, 0.0), (height, 0.5 * np.pi), (width, np.pi), (height, 1.5 * np.pi)]
    start = np.array([0.0, -0.5 * height])
    pos = start.copy()
    for i, (side, yaw) in enumerate(legs):
        rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
        straight = side / 2 - d if i == 0 else side - 2 * d
        if i == len(legs) - 1:
            straight = side - 2 * d
        n = max(int(straight / 0.01), 1)
        pieces.append(pos + np.outer(np.linspace(0, straight, n, endpoint=False), rot[:, 0]))
        pos = pos + straight * rot[:, 0]
        pieces.append(pos + c[:-1] @ rot.T)
        pos = pos + c[-1] @ rot.T
    # Last half of the bottom side back to the start.
    rest = width / 2 - d
    pieces.append(
        pos + np.outer(np.linspace(0, rest, max(int(rest / 0.01), 1), endpoint=False), [1.0, 0.0])
    )
    return np.vstack(pieces)


def rotation_zyx(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """(M,3,3) Rz(yaw) @ Ry(pitch) @ Rx(roll), angles in rad (vectorised)."""
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    R = np.empty((np.size(yaw), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = -sp, cp * sr, cp * cr
    return R


@dataclass
class Trajectory:
    """T_world_sensor(t) of a robot following a closed curve; t in s from the start."""

    s_tab: np.ndarray  # (K,) arc length (m)
    t_tab: np.ndarray  # (K,) time at s (s)
    xy_tab: np.ndarray  # (K,2) position (m)
    yaw_tab: np.ndarray  # (K,) unwrapped heading (rad)
    height: float  # sensor height above the ground (m)
    wobble_amp: np.ndarray  # (2, H) roll / pitch amplitudes (rad)
    wobble_freq: np.ndarray  # (2, H) Hz
    wobble_phase: np.ndarray  # (2, H) rad
    loop_length: float  # length of one lap (m)
    z_tab: np.ndarray | None = None  # (K,) ground height (m); None: flat ground at z = 0
    pitch_tab: np.ndarray | None = None  # (K,) pitch (rad) from the terrain slope
    roll_tab: np.ndarray | None = None  # (K,) roll (rad) from the terrain slope
    # Car-like drives (see :func:`route_trajectory`), per table entry, interpolated in time
    # (the tables hold two entries at the same place for a stop):
    wobble_scale_tab: np.ndarray | None = None  # (K,) 0..1 factor of wobble and vibration
    attitude_tab: np.ndarray | None = None  # (K, 2) extra roll, pitch (rad): body sway

    @property
    def duration(self) -> float:
        return float(self.t_tab[-1])

    @property
    def length(self) -> float:
        return float(self.s_tab[-1])

    def distance_at(self, times: np.ndarray) -> np.ndarray:
        """Distance travelled (m) at ``times`` (s); clamped to [0, duration]."""
        return np.interp(np.asarray(times, dtype=float), self.t_tab, self.s_tab)

    def pose_at(self, times) -> np.ndarray:
        """(M,4,4) T_world_sensor at ``times`` (M,) s (vectorised; clamped to the ends)."""
        t = np.atleast_1d(np.asarray(times, dtype=float))
        s = self.distance_at(t)
        x = np.interp(s, self.s_tab, self.xy_tab[:, 0])
        y = np.interp(s, self.s_tab, self.xy_tab[:, 1])
        yaw = np.interp(s, self.s_tab, self.yaw_tab)
        arg = (
            2 * np.pi * self.wobble_freq[:, :, None] * t[None, None, :]
            + self.wobble_phase[:, :, None]
        )
        rp = np.sum(self.wobble_amp[:, :, None] * np.sin(arg), axis=1)  # (2, M)
        if self.wobble_scale_tab is not None:
            rp = rp * np.interp(t, self.t_tab, self.wobble_scale_tab)[None, :]
        if self.attitude_tab is not None:
            rp = rp + np.stack([np.interp(t, self.t_tab, a) for a in self.attitude_tab.T])
        z = self.height
        if self.z_tab is not None:
            z = np.interp(s, self.s_tab, self.z_tab) + self.height
            rp[0] += np.interp(s, self.s_tab, self.roll_tab)
            rp[1] += np.interp(s, self.s_tab, self.pitch_tab)
        T = np.tile(np.eye(4), (t.size, 1, 1))
        T[:, :3, :3] = rotation_zyx(yaw, rp[1], rp[0])
        T[:, 0, 3], T[:, 1, 3], T[:, 2, 3] = x, y, z
        return T


def _wobble(
    wobble_deg: float, vibration_deg: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(amp rad, freq Hz, phase rad), each (2, H): roll / pitch suspension wobble (2
    harmonics, 0.15-0.9 Hz) plus, when vibration_deg > 0, 3 harmonics of 2-9 Hz vibration."""
    amp = np.deg2rad(wobble_deg) * np.array([[0.6, 0.4], [0.6, 0.4]])
    freq = rng.uniform(0.15, 0.9, size=(2, 2))
    phase = rng.uniform(0, 2 * np.pi, size=(2, 2))
    if vibration_deg > 0:
        amp = np.hstack([amp, np.deg2rad(vibration_deg) * np.tile([0.5, 0.3, 0.2], (2, 1))])
        freq = np.hstack([freq, rng.uniform(2.0, 9.0, size=(2, 3))])
        phase = np.hstack([phase, rng.uniform(0, 2 * np.pi, size=(2, 3))])
    return amp, freq, phase


def _closed_lap(
    xy: np.ndarray, start_offset: float
) -> tuple[np.ndarray, np.ndarray, float, float, float]:
    """(base, heading, winding, lap, ds): the resampled closed curve starting start_offset
    (m) along it, its unwrapped heading (rad), turns per lap, lap length and step (m)."""
    base = resample_closed(xy)
    n = len(base)
    seg = np.hypot(*np.diff(np.vstack([base, base[:1]]), axis=0).T)
    lap = float(seg.sum())
    shift = int(round(start_offset / lap * n)) % n
    base = np.roll(base, -shift, axis=0)
    # Periodic tangent and heading of one lap.
    d = (np.roll(base, -1, axis=0) - np.roll(base, 1, axis=0)) * 0.5
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    winding = float(np.round((heading[-1] - heading[0]) / (2 * np.pi)))
    return base, heading, winding, lap, lap / n


def _periodic_curvature(heading: np.ndarray, ds: float) -> np.ndarray:
    """(N,) curvature (1/m) of a closed lap, smoothed periodically over ~1 m."""
    kappa = np.gradient(heading, ds)
    w = max(int(1.0 / ds), 1)
    kappa_s = np.convolve(np.concatenate([kappa[-w:], kappa, kappa[:w]]), np.ones(w) / w, "same")
    return kappa_s[w:-w]


def _speed_factor(s: np.ndarray, variation: float, rng: np.random.Generator) -> np.ndarray:
    """(K,) factor 1 + variation x f(s) of smooth random speed changes along the route: 3
    sines of wavelengths 12-50 m, f normalised to amplitude <= 1."""
    wl = rng.uniform(12.0, 50.0, 3)
    ph = rng.uniform(0, 2 * np.pi, 3)
    w_ = rng.uniform(0.5, 1.0, 3)
    f = np.sum(w_[:, None] * np.sin(2 * np.pi * s[None, :] / wl[:, None] + ph[:, None]), 0)
    return 1.0 + variation * f / w_.sum()


def closed_curve_trajectory(
    xy: np.ndarray,
    *,
    loops: float,
    speed: float,
    height: float,
    rng: np.random.Generator,
    turn_slowdown: float = 0.6,
    ramp_distance: float = 1.0,
    wobble_deg: float = 1.0,
    start_offset: float = 0.0,
    speed_variation: float = 0.0,
    vibration_deg: float = 0.0,
    terrain: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
) -> Trajectory:
    """Drive ``loops`` laps of the closed curve ``xy`` (N,2) counter-clockwise.

    speed: cruise speed (m/s); in turns v = speed / (1 + turn_slowdown * |curvature|).
    The first ``ramp_distance`` m accelerate smoothly from 15 % of cruise speed.
    start_offset: distance (m) along the curve where the robot starts.
    speed_variation: relative amplitude of smooth random speed changes along the route
    (wavelengths 12-50 m): the robot accelerates and brakes (0 = off).
    vibration_deg: amplitude (deg) of high-frequency roll/pitch vibration (3 harmonics at
    2-9 Hz per axis; 0 = off).
    terrain: ground height z(x, y) (m), vectorised; the sensor rides ``height`` above it
    and the robot pitches / rolls with the slope (averaged over a 0.6 m wheelbase).
    """
    if loops <= 0 or speed <= 0:
        raise InputError("trajectory needs loops > 0 and speed > 0")
    base, heading, winding, lap, ds = _closed_lap(xy, start_offset)
    n = len(base)
    s_lap = np.arange(n) * ds
    # Curvature, smoothed over ~1 m, for the speed profile.
    kappa_s = _periodic_curvature(heading, ds)

    total = loops * lap
    s = np.arange(0.0, total + ds, ds)
    k = np.floor(s / lap)
    s_mod = s - k * lap
    period_s = np.concatenate([s_lap, [lap]])
    xy_tab = np.column_stack(
        [np.interp(s_mod, period_s, np.append(base[:, i], base[0, i])) for i in range(2)]
    )
    yaw_lap = np.append(heading, heading[0] + 2 * np.pi * winding)
    yaw_tab = np.interp(s_mod, period_s, yaw_lap) + 2 * np.pi * winding * k
    kap = np.interp(s_mod, period_s, np.append(kappa_s, kappa_s[0]))
    v = speed / (1.0 + turn_slowdown * np.abs(kap))
    if speed_variation > 0:
        v = v * _speed_factor(s, speed_variation, rng)
    u = np.clip(s / ramp_distance, 0.0, 1.0)
    v = v * (0.15 + 0.85 * u * u * (3 - 2 * u))
    t_tab = np.concatenate([[0.0], np.cumsum(0.5 * (1 / v[1:] + 1 / v[:-1]) * np.diff(s))])

    amp, freq, phase = _wobble(wobble_deg, vibration_deg, rng)
    traj = Trajectory(s, t_tab, xy_tab, yaw_tab, height, amp, freq, phase, lap)
    if terrain is not None:
        traj.z_tab, traj.pitch_tab, traj.roll_tab = _terrain_attitude(terrain, xy_tab, yaw_tab, s)
    return traj


def _terrain_attitude(
    terrain: Callable[[np.ndarray, np.ndarray], np.ndarray],
    xy: np.ndarray,
    yaw: np.ndarray,
    s: np.ndarray,
    wheelbase: float = 0.6,
    step: float = 0.05,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground height, pitch and roll (rad) along the path over a terrain z(x, y); the
    slopes are central differences over the wheelbase (front/rear, left/right wheels)."""
    # Evaluate on a coarser grid along the path (the terrain is smooth), then interpolate.
    sub = np.arange(0, len(s), max(int(round(step / max(s[1] - s[0], 1e-9))), 1))
    if sub[-1] != len(s) - 1:
        sub = np.append(sub, len(s) - 1)
    x, y, th = xy[sub, 0], xy[sub, 1], yaw[sub]
    fwd = np.column_stack([np.cos(th), np.sin(th)]) * (0.5 * wheelbase)
    left = np.column_stack([-np.sin(th), np.cos(th)]) * (0.5 * wheelbase)
    z = terrain(x, y)
    grade = (terrain(x + fwd[:, 0], y + fwd[:, 1]) - terrain(x - fwd[:, 0], y - fwd[:, 1])) / (
        wheelbase
    )
    bank = (terrain(x + left[:, 0], y + left[:, 1]) - terrain(x - left[:, 0], y - left[:, 1])) / (
        wheelbase
    )
    # Rz(yaw) Ry(pitch) Rx(roll): nose up is a negative pitch, left side up a positive roll.
    pitch = -np.arctan(grade)
    roll = np.arctan(bank * np.cos(pitch))
    return (np.interp(s, s[sub], z), np.interp(s, s[sub], pitch), np.interp(s, s[sub], roll))


# ---------------------------------------------------------------------------- car routes


def _turn(angle: float, length: float, ds: float) -> np.ndarray:
    """xy (K,2) of a turn by ``angle`` (rad, + = left) starting at the origin heading +x,
    with curvature ``angle / length * (1 - cos(2 pi u / length))`` (zero at both ends)."""
    u = np.arange(0.0, length + ds / 2, ds)
    heading = angle * (u / length - np.sin(2 * np.pi * u / length) / (2 * np.pi))
    c, s_ = np.cos(heading), np.sin(heading)
    x = np.concatenate([[0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * ds)])
    y = np.concatenate([[0.0], np.cumsum(0.5 * (s_[1:] + s_[:-1]) * ds)])
    return np.column_stack([x, y])


def lane_route(
    nodes: np.ndarray,
    *,
    lane_offset: float = 0.0,
    left_turn_length: float = 26.0,
    right_turn_length: float = 18.0,
    ds: float = 0.05,
) -> np.ndarray:
    """Open path (K,2) through street-centre ``nodes`` (N,2) (m), driven ``lane_offset``
    m right of the centre line, every corner rounded by a curvature-continuous turn of
    ``left_turn_length`` / ``right_turn_length`` m of arc (minimum radius length / (2 *
    |angle|); for 90 deg: 8.3 / 5.7 m). Nodes where the route goes straight on are kept."""
    nodes = np.asarray(nodes, dtype=float)
    d = np.diff(nodes, axis=0)
    e = d / np.hypot(d[:, 0], d[:, 1])[:, None]
    n = np.column_stack([e[:, 1], -e[:, 0]])  # right of the direction of travel
    pieces = []
    pos = nodes[0] + lane_offset * n[0]
    for i in range(1, len(nodes) - 1):
        ein, eout = e[i - 1], e[i]
        angle = float(np.arctan2(ein[0] * eout[1] - ein[1] * eout[0], ein @ eout))
        # Corner of the two offset lane lines: p + a ein = q + b eout.
        p = nodes[i] + lane_offset * n[i - 1]
        q = nodes[i] + lane_offset * n[i]
        if abs(angle) < 1e-6:
            continue
        a, _ = np.linalg.solve(np.column_stack([ein, -eout]), q - p)
        corner = p + a * ein
        turn = _turn(angle, left_turn_length if angle > 0 else right_turn_length, ds)
        X, Y = turn[-1]
        x0 = X - Y * np.cos(angle) / np.sin(angle)  # turn start before the corner (m)
        start = corner - x0 * ein
        rot = np.column_stack([ein, [-ein[1], ein[0]]])
        straight = float((start - pos) @ ein)
        if straight < 0:
            raise InputError(f"lane_route: leg {i} too short for its turns")
        k = max(int(straight / ds), 1)
        pieces.append(pos + np.outer(np.arange(k) * (straight / k), ein))
        pieces.append(start + turn[:-1] @ rot.T)
        pos = start + turn[-1] @ rot.T
    end = nodes[-1] + lane_offset * n[-1]
    rest = float((end - pos) @ e[-1])
    k = max(int(rest / ds), 1)
    pieces.append(pos + np.outer(np.arange(k + 1) * (rest / k), e[-1]))
    return np.vstack(pieces)


def speed_profile(
    s: np.ndarray,
    v_limit: np.ndarray,
    *,
    accel: float,
    decel: float,
) -> np.ndarray:
    """Fastest speed (m/s) at arc lengths ``s`` (K,) under ``v_limit`` (K,) (0 where the
    car must stop), accelerating at most ``accel`` and braking at most ``decel`` m/s^2;
    v^2 grows at most linearly in distance (v dv/ds = a), forward and backward passes."""
    v = np.array(v_limit, dtype=float)
    ds = np.diff(s)
    for i in range(len(v) - 1):  # numba-free: K ~ 1e5, once per scene
        v[i + 1] = min(v[i + 1], np.sqrt(v[i] ** 2 + 2 * accel * ds[i]))
    for i in range(len(v) - 2, -1, -1):
        v[i] = min(v[i], np.sqrt(v[i + 1] ** 2 + 2 * decel * ds[i]))
    return v


def _dwell_entries(
    s: np.ndarray, t: np.ndarray, stops: list[tuple[float, float]]
) -> tuple[np.ndarray, np.ndarray]:
    """(idx, t_rep): table entries repeated at each stop (distance m, dwell s), the second
    entry at the same place dwell seconds later and every later time shifted by the dwell."""
    dwell: dict[int, float] = {}
    for sd, dw in stops:
        i = int(np.clip(np.searchsorted(s, sd), 0, len(s) - 1))
        dwell[i] = dwell.get(i, 0.0) + float(dw)
    rep = np.ones(len(s), dtype=int)
    rep[[i for i, dw in dwell.items() if dw > 0]] = 2
    idx = np.repeat(np.arange(len(s)), rep)
    second = np.concatenate([[False], idx[1:] == idx[:-1]])
    add = np.zeros(len(idx))
    add[second] = [dwell[i] for i in idx[second]]
    return idx, t[idx] + np.cumsum(add)


def _open_path(
    xy: np.ndarray, speed_limit: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(xy, s, v_lim, heading, kappa): the open path without repeated points, its arc length
    (m), speed limit (m/s), unwrapped heading (rad) and curvature (1/m, ~1 m smoothing)."""
    xy = np.asarray(xy, dtype=float)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-9])
    xy = xy[keep]
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    v_lim = np.asarray(speed_limit, dtype=float)[keep]
    d = np.gradient(xy, s, axis=0)
    heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    kappa = np.gradient(heading, s)
    w = max(int(1.0 / max(s[1] - s[0], 1e-6)), 1)
    return xy, s, v_lim, heading, np.convolve(kappa, np.ones(w) / w, "same")


def _route_speed(
    s: np.ndarray,
    v_lim: np.ndarray,
    kappa: np.ndarray,
    stops: list[tuple[float, float]],
    lateral_accel: float,
    accel: float,
    decel: float,
) -> np.ndarray:
    """(K,) speed (m/s) along the route: the limit, sqrt(lateral_accel / |kappa|) in curves,
    0 at both ends and at the stops, under the acceleration bounds (m/s^2)."""
    with np.errstate(divide="ignore"):
        v_lim = np.minimum(v_lim, np.sqrt(lateral_accel / np.abs(kappa)))
    v_lim[0] = v_lim[-1] = 0.0
    stop_idx = sorted({int(np.clip(np.searchsorted(s, sd), 0, len(s) - 1)) for sd, _ in stops})
    v_lim[stop_idx] = 0.0
    return speed_profile(s, v_lim, accel=accel, decel=decel)


def route_trajectory(
    xy: np.ndarray,
    *,
    speed_limit: np.ndarray,
    stops: list[tuple[float, float]],
    height: float,
    rng: np.random.Generator,
    lateral_accel: float = 2.5,
    accel: float = 1.5,
    decel: float = 2.5,
    wobble_deg: float = 0.3,
    vibration_deg: float = 0.1,
    pitch_per_accel_deg: float = 0.25,
    roll_per_accel_deg: float = 0.35,
    sway_speed: float = 4.0,
) -> Trajectory:
    """A car's drive along the open path ``xy`` (K,2) (m, dense), from standstill to
    standstill.

    speed_limit (K,) m/s along the path; in curves v <= sqrt(lateral_accel / |curvature|);
    accelerations bounded by ``accel`` / ``decel`` (m/s^2). stops: (distance along the
    path m, dwell s): the car brakes to 0 there and waits (a stop at 0 waits at the start).
    The body pitches forward by ``pitch_per_accel_deg`` per m/s^2 of braking (backward
    when accelerating) and rolls out of the turn by ``roll_per_accel_deg`` per m/s^2 of
    lateral acceleration; suspension wobble (``wobble_deg``, 0.15-0.9 Hz) and road
    vibration (``vibration_deg``, 2-9 Hz) fade out below ``sway_speed`` m/s (0 at rest).
    """
    xy, s, v_lim, heading, kappa_s = _open_path(xy, speed_limit)
    v = _route_speed(s, v_lim, kappa_s, stops, lateral_accel, accel, decel)
    dt = 2.0 * np.diff(s) / np.maximum(v[1:] + v[:-1], 1e-9)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    a_long = np.gradient(0.5 * v**2, s)
    a_lat = v**2 * kappa_s
    idx, t_rep = _dwell_entries(s, t, stops)
    s_rep, v_rep = s[idx], v[idx]
    a_long_r, a_lat_r = a_long[idx], a_lat[idx]
    at_rest = v_rep == 0
    a_long_r[at_rest] = a_lat_r[at_rest] = 0.0
    attitude = np.column_stack(
        [
            np.deg2rad(roll_per_accel_deg) * a_lat_r,  # left turn: left side up
            np.deg2rad(pitch_per_accel_deg) * a_long_r * -1.0,  # braking: nose down
        ]
    )
    amp, freq, phase = _wobble(wobble_deg, vibration_deg, rng)
    return Trajectory(
        s_rep,
        t_rep,
        xy[idx],
        heading[idx],
        height,
        amp,
        freq,
        phase,
        float(s[-1]),
        wobble_scale_tab=np.clip(v_rep / sway_speed, 0.0, 1.0),
        attitude_tab=attitude,
    )

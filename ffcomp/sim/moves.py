"""Reference trajectories: synthetic test moves generated in code, and planned G-code files.

Used by the bench (it must run without any G-code file) and by the tests.  The planner is a small
Klipper-like lookahead: constant acceleration ``a`` on every segment, junction speeds from
Klipper's square-corner-velocity rule, speeds limited so that every segment can stop in time.
The G-code planner of :mod:`ffcomp.gcode` is the firmware-exact one (:func:`load_gcode_trajectory`);
this one only has to make repeatable, realistic stress moves.

Units: SI (m, m/s, m/s^2, s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..kinematics import DeltaGeometry, check_reachable, inverse

__all__ = ["Trajectory", "plan_polyline", "square_path", "zigzag_path", "polygon_path", "zmove_path", "pattern",
           "PATTERNS", "PATTERN_SCV_M_S",
           "load_gcode_trajectory", "longest_piece"]


@dataclass(frozen=True)
class Trajectory:
    """A sampled nozzle reference and the carriage heights it maps to.

    Attributes
    ----------
    name : str
    t_s : ndarray, shape (N,)
        Uniform times, s.
    xyz_m, q_m : ndarray, shape (N, 3)
        Nozzle reference (m) and carriage heights by inverse kinematics (m).
    e_mm : ndarray, shape (N,), optional
        Extruder position (mm of filament) where the reference comes from a G-code file.
    """

    name: str
    t_s: np.ndarray
    xyz_m: np.ndarray
    q_m: np.ndarray
    e_mm: np.ndarray | None = None

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] - self.t_s[0])


def _junction_v2(d_prev: np.ndarray, d_next: np.ndarray, accel: float, scv: float) -> float:
    """Klipper's junction speed squared for unit directions ``d_prev -> d_next``."""
    cos_theta = float(np.clip(-np.dot(d_prev, d_next), -1.0, 1.0))
    if cos_theta > 0.999999:
        return 0.0
    if cos_theta < -0.999999:
        return math.inf
    sin_half = math.sqrt(0.5 * (1.0 - cos_theta))
    r_jd = sin_half / (1.0 - sin_half)
    jd = scv**2 * (math.sqrt(2.0) - 1.0) / accel
    return jd * accel * r_jd


def plan_polyline(points_m, speed_m_s: float, accel_m_s2: float, *, scv_m_s: float = 0.005,
                  rate_hz: float = 1000.0,
                  pad_s: tuple[float, float] = (0.05, 0.25)) -> tuple[np.ndarray, np.ndarray]:
    """Plan and sample a polyline that starts and ends at rest.

    Parameters
    ----------
    points_m : array_like, shape (P, 3)
        Vertices, m.
    speed_m_s, accel_m_s2 : float
        Cruise speed and acceleration.
    scv_m_s : float
        Square corner velocity (Klipper's junction rule).
    rate_hz : float
        Sample rate.
    pad_s : (float, float)
        Rest before the first and after the last move (to let the printer settle), s.

    Returns
    -------
    t_s : ndarray, shape (N,)
    xyz_m : ndarray, shape (N, 3)
    """
    P = np.asarray(points_m, float)
    seg = np.diff(P, axis=0)
    length = np.linalg.norm(seg, axis=1)
    keep = length > 1e-12
    seg, length = seg[keep], length[keep]
    P = np.vstack([P[:1], P[1:][keep]])
    unit = seg / length[:, None]
    n = length.shape[0]
    a, vmax2 = float(accel_m_s2), float(speed_m_s) ** 2
    vj2 = np.zeros(n + 1)  # speed^2 at each vertex
    for i in range(1, n):
        vj2[i] = min(vmax2, _junction_v2(unit[i - 1], unit[i], a, scv_m_s))
    for i in range(n - 1, -1, -1):  # backward: be able to slow down
        vj2[i] = min(vj2[i], vj2[i + 1] + 2 * a * length[i])
    for i in range(n):  # forward: be able to speed up
        vj2[i + 1] = min(vj2[i + 1], vj2[i] + 2 * a * length[i])
    # trapezoid of each segment
    v0, v1 = np.sqrt(vj2[:-1]), np.sqrt(vj2[1:])
    vc2 = np.minimum(vmax2, 0.5 * (vj2[:-1] + vj2[1:]) + a * length)
    vc = np.sqrt(vc2)
    ta, td = (vc - v0) / a, (vc - v1) / a
    d_acc, d_dec = (vc2 - vj2[:-1]) / (2 * a), (vc2 - vj2[1:]) / (2 * a)
    tc = np.maximum(length - d_acc - d_dec, 0.0) / np.where(vc > 0, vc, 1.0)
    dur = ta + tc + td
    t_start = pad_s[0] + np.concatenate([[0.0], np.cumsum(dur)[:-1]])
    t_end = pad_s[0] + float(dur.sum()) + pad_s[1]
    t = np.arange(int(math.ceil(t_end * rate_hz)) + 1) / rate_hz
    j = np.clip(np.searchsorted(t_start, t, side="right") - 1, 0, n - 1)
    tau = np.clip(t - t_start[j], 0.0, dur[j])
    s = np.where(tau < ta[j], v0[j] * tau + 0.5 * a * tau**2,
                 np.where(tau < ta[j] + tc[j], d_acc[j] + vc[j] * (tau - ta[j]),
                          length[j] - v1[j] * (dur[j] - tau) - 0.5 * a * (dur[j] - tau) ** 2))
    s = np.clip(s, 0.0, length[j])
    xyz = P[j] + unit[j] * s[:, None]
    xyz[t < pad_s[0]] = P[0]
    return t, xyz


def square_path(centre_m, side_m: float = 0.06, loops: int = 2) -> np.ndarray:
    """Vertices of a square (counter-clockwise from the lower-left corner), ``loops`` times round."""
    c = np.asarray(centre_m, float)
    h = 0.5 * side_m
    corners = np.array([[-h, -h], [h, -h], [h, h], [-h, h]])
    pts = np.vstack([np.tile(corners, (loops, 1)), corners[:1]])
    return np.column_stack([pts + c[:2], np.full(len(pts), c[2])])


def zigzag_path(centre_m, width_m: float = 0.04, pitch_m: float = 0.002, lines: int = 12) -> np.ndarray:
    """Vertices of a zig-zag infill: ``lines`` x-direction lines ``pitch_m`` apart."""
    c = np.asarray(centre_m, float)
    h = 0.5 * width_m
    y0 = -0.5 * pitch_m * (lines - 1)
    pts = []
    for i in range(lines):
        xs = (-h, h) if i % 2 == 0 else (h, -h)
        y = y0 + i * pitch_m
        pts += [(xs[0], y), (xs[1], y)]
    pts = np.asarray(pts)
    return np.column_stack([pts + c[:2], np.full(len(pts), c[2])])


def polygon_path(centre_m, segments: int = 64, chord_m: float = 0.0008, loops: int = 2) -> np.ndarray:
    """Vertices of a regular polygon (a sliced circle), ``loops`` times round.

    The default (64 chords of 0.8 mm, radius 8.15 mm) is a sliced circle whose segment rate is
    250 Hz at 200 mm/s: every vertex is a small velocity kink, a 250 Hz comb of excitation.
    """
    c = np.asarray(centre_m, float)
    r = chord_m / (2.0 * math.sin(math.pi / segments))
    th = np.arange(segments * loops + 1) * 2.0 * math.pi / segments
    return np.column_stack([c[0] + r * np.cos(th), c[1] + r * np.sin(th), np.full(len(th), c[2])])


def zmove_path(centre_m, side_m: float = 0.03, rise_m: float = 0.012) -> np.ndarray:
    """Vertices of a loop that climbs and drops in z on every edge (all three carriages move apart)."""
    c = np.asarray(centre_m, float)
    h = 0.5 * side_m
    pts = np.array([[-h, -h, 0.0], [h, -h, rise_m], [h, h, 0.0], [-h, h, 1.5 * rise_m], [-h, -h, 0.0]])
    return pts + c


#: pattern name -> (vertex builder, speed m/s); accelerations are set by the caller
PATTERNS = {
    "square": (square_path, 0.150),
    "zigzag": (zigzag_path, 0.250),
    "polygon": (polygon_path, 0.200),
    "zmove": (zmove_path, 0.150),
}

#: square corner velocity per pattern (m/s; default 5 mm/s): the polygon's is high enough that it
#: runs at its full 200 mm/s (with 5 mm/s Klipper would slow its 5.6 degree corners to ~93 mm/s)
PATTERN_SCV_M_S = {"polygon": 0.020}


def pattern(name: str, geom: DeltaGeometry, centre_mm=(0.0, 0.0, 30.0), *, accel_mm_s2: float = 10000.0,
            rate_hz: float = 1000.0, speed_mm_s: float | None = None, **kw) -> Trajectory:
    """A stress pattern (a key of :data:`PATTERNS`) translated to ``centre_mm``.

    ``kw`` goes to the vertex builder (``side_m``, ``loops``; ``width_m``, ``pitch_m``, ``lines``).
    Raises :class:`~ffcomp.errors.KinematicsError` if the pattern leaves the printable disc.
    """
    if name not in PATTERNS:
        raise ValueError(f"unknown pattern {name!r}; known: {', '.join(PATTERNS)}")
    build, speed = PATTERNS[name]
    verts = build(np.asarray(centre_mm, float) * 1e-3, **kw)
    check_reachable(geom, verts, what=f"{name} vertex")
    v = speed if speed_mm_s is None else speed_mm_s * 1e-3
    t, xyz = plan_polyline(verts, v, accel_mm_s2 * 1e-3, rate_hz=rate_hz, scv_m_s=PATTERN_SCV_M_S.get(name, 0.005))
    c = centre_mm
    return Trajectory(f"{name}@({c[0]:g},{c[1]:g},{c[2]:g})", t, xyz, inverse(geom, xyz))


def load_gcode_trajectory(profile, path, *, split: bool = True, hold_margin_s: float = 0.0,
                          quiet_z_period_s: float | None = None) -> Trajectory:
    """Parse, plan and sample a G-code file at the profile's rate (:mod:`ffcomp.gcode`).

    The planner executes homing (``G28``) as a jump, which no printer could follow; with
    ``split`` the samples are cut at such jumps and the longest piece is returned (the machine is
    at rest on both sides of a homing move, so each piece starts and ends at rest).
    ``hold_margin_s``: rest (s) added where a compensation with that margin adds it
    (:mod:`ffcomp.gcode.margins`), so the file's plan runs on the compensated output's clock.
    ``quiet_z_period_s``: the z moves next to holds planned with quiet ramps, as a compensation with
    ``--quiet-z`` plans them (:class:`ffcomp.gcode.klipper.KlipperPlanner`).
    """
    from ..gcode.sampler import concat_blocks, sample_gcode

    qkw = {} if quiet_z_period_s is None else {"quiet_z_period_s": quiet_z_period_s}
    blk = concat_blocks(sample_gcode(str(path), profile, **qkw))
    xyz, q, e = blk.xyz_m, blk.q_m, blk.e_mm
    n = int(round(hold_margin_s * blk.fs_hz))
    if n > 0:
        from ..gcode.margins import with_margins
        from ..gcode.planner import GcodePlan

        moves = {mv.index: mv for mv in GcodePlan(str(path), profile, **qkw)}
        xyz, q, e = with_margins((xyz, q, e), blk.move_index, moves, n)
    t = blk.t_s if len(q) == len(blk.t_s) else blk.t_s[0] + np.arange(len(q)) / blk.fs_hz
    traj = Trajectory(Path(path).name, t, xyz, q, e)
    return longest_piece(traj, profile) if split else traj


def longest_piece(traj: Trajectory, profile, pad_s: float = 0.25) -> Trajectory:
    """The longest part of ``traj`` without a jump faster than the profile's speed limits allow.

    When something was cut, the piece is held at its last position for ``pad_s`` more.
    """
    lim = profile.limits
    dt = float(traj.t_s[1] - traj.t_s[0]) if traj.t_s.shape[0] > 1 else 1.0
    v_max = 1.5e-3 * max(lim.max_velocity_mm_s, lim.max_z_velocity_mm_s)
    step = np.linalg.norm(np.diff(traj.xyz_m, axis=0), axis=1)
    cuts = np.flatnonzero(step > v_max * dt + 1e-9) + 1
    if cuts.size == 0:
        return traj
    edges = np.concatenate([[0], cuts, [traj.t_s.shape[0]]])
    k = int(np.argmax(np.diff(edges)))
    sl = slice(int(edges[k]), int(edges[k + 1]))
    n_pad = int(round(pad_s / dt))  # let the printer settle after the last move of the piece
    xyz = np.vstack([traj.xyz_m[sl], np.repeat(traj.xyz_m[sl][-1:], n_pad, axis=0)])
    q = np.vstack([traj.q_m[sl], np.repeat(traj.q_m[sl][-1:], n_pad, axis=0)])
    e = None if traj.e_mm is None else np.concatenate([traj.e_mm[sl], np.repeat(traj.e_mm[sl][-1:], n_pad)])
    name = f"{traj.name}[{traj.t_s[sl][0]:.2f}-{traj.t_s[sl][-1]:.2f} s]"
    return Trajectory(name, np.arange(len(xyz)) * dt, xyz, q, e)

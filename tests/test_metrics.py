"""Tests of ffcomp.sim.metrics on paths with known errors."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from ffcomp.sim.metrics import (
    ErrorReport,
    best_lag,
    contour_error,
    error_spectrum,
    evaluate,
    lag_aligned_error,
    point_segment_distance,
    summarise,
    time_aligned_error,
    worst_region,
)

DT_S = 1e-3
T_S = np.arange(0.0, 2.0 + DT_S / 2, DT_S)
R_M = 0.05


def _min_jerk(tau):
    tau = np.clip(tau, 0.0, 1.0)
    return tau**3 * (10 - 15 * tau + 6 * tau**2)


def _spiral(t_s):
    """1.5 turns of a rising circle, at rest before 0.2 s and after 1.8 s, in m."""
    s = _min_jerk((t_s - 0.2) / 1.6)
    phi = 2 * np.pi * 1.5 * s
    return np.column_stack([R_M * np.cos(phi), R_M * np.sin(phi), 0.01 * s])


@pytest.mark.parametrize("lag_s", [0.0034567, -0.0071234, 0.005, 0.0])
def test_pure_time_shift_recovers_lag(lag_s):
    ref, act = _spiral(T_S), _spiral(T_S - lag_s)
    assert best_lag(T_S, ref, act) == pytest.approx(lag_s, abs=1e-5)
    err, lag = lag_aligned_error(T_S, ref, act)
    assert lag == pytest.approx(lag_s, abs=1e-5)
    assert np.sqrt(np.mean(err**2)) < 1e-6  # < 1 um (linear interpolation of a 1 kHz grid)
    if lag_s:
        time_rms = np.sqrt(np.mean(time_aligned_error(ref, act) ** 2))
        assert np.sqrt(np.mean(err**2)) < 1e-3 * time_rms


def test_best_lag_limits_and_grid_checks():
    ref = _spiral(T_S)
    with pytest.raises(ValueError, match="too short"):
        best_lag(T_S[:30], ref[:30], ref[:30], max_lag_s=0.02)
    t_bad = T_S.copy()
    t_bad[5] += 3e-4
    with pytest.raises(ValueError, match="uniform"):
        best_lag(t_bad, ref, ref)
    with pytest.raises(ValueError, match="shape"):
        time_aligned_error(ref, ref[:, :2])


def test_time_aligned_error_is_difference():
    ref, act = _spiral(T_S), _spiral(T_S - 0.002)
    np.testing.assert_array_equal(time_aligned_error(ref, act), act - ref)


@pytest.mark.parametrize(
    "p, a, b, expected",
    [
        ([0.5, 1.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 1.0),  # projects inside
        ([-3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 5.0),  # before a
        ([4.0, 0.0, 4.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0], 5.0),  # after b
        ([1.0, 2.0, 2.0], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], 2 * math.sqrt(2)),  # degenerate
        ([1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [2.0, 2.0, 2.0], 0.0),  # on the segment
        ([0.0, 0.0, 1.0], [-1.0, -1.0, 0.0], [1.0, 1.0, 0.0], 1.0),  # above the diagonal
    ],
)
def test_point_segment_distance_hand_cases(p, a, b, expected):
    assert point_segment_distance(np.array(p), np.array(a), np.array(b)) == pytest.approx(expected, abs=1e-15)


def test_point_segment_distance_broadcasts():
    p = np.array([[0.5, 1.0, 0.0], [-3.0, 4.0, 0.0]])
    d = point_segment_distance(p, np.zeros(3), np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(d, [1.0, 5.0])


def test_contour_uses_segments_not_just_vertices():
    ref = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    act = np.array([[0.5, 0.1, 0.0], [1.2, 0.5, 0.0], [0.9, 0.9, 0.0], [2.0, 2.0, 0.0]])
    np.testing.assert_allclose(contour_error(ref, act), [0.1, 0.2, 0.1, math.sqrt(2)], atol=1e-15)


def test_contour_of_line_moved_along_itself_is_zero_and_offset_is_d():
    direction = np.array([0.6, 0.8, 0.0])
    normal = np.array([-0.8, 0.6, 0.0])
    line = lambda t: 0.1 * _min_jerk((t - 0.2) / 1.6)[:, None] * direction  # noqa: E731
    ref = line(T_S)
    assert np.max(contour_error(ref, line(T_S - 0.0123))) < 1e-15
    d = 37e-6
    np.testing.assert_allclose(contour_error(ref, line(T_S - 0.0123) + d * normal), d, rtol=1e-9)


def test_contour_of_circle_moved_along_itself_and_offset():
    ref = _spiral(T_S)
    ref[:, 2] = 0.0
    act = _spiral(T_S - 0.0077)
    act[:, 2] = 0.0
    # polyline chords lie inside the circle by at most the sagitta R (1 - cos(dphi / 2))
    dphi = np.max(np.abs(np.diff(np.arctan2(ref[:, 1], ref[:, 0]))[:100])) + np.max(
        np.linalg.norm(np.diff(ref, axis=0), axis=1)) / R_M
    sagitta = R_M * (1 - math.cos(dphi / 2))
    assert np.max(contour_error(ref, act)) <= sagitta + 1e-15
    d = 50e-6
    act_off = act * (1 + d / R_M)  # radial offset by d
    np.testing.assert_allclose(contour_error(ref, act_off), d, atol=sagitta + 1e-12)


def test_summarise_against_numpy():
    err_um = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [-6.0, 8.0, 1.0], [1.0, -2.0, 2.0]])
    s = summarise(err_um * 1e-6)
    np.testing.assert_allclose(s.rms_um, np.sqrt(np.mean(err_um**2, axis=0)))
    np.testing.assert_allclose(s.p95_um, np.percentile(np.abs(err_um), 95, axis=0))
    np.testing.assert_allclose(s.max_um, [6.0, 8.0, 2.0])
    norm = np.linalg.norm(err_um, axis=1)
    assert s.rms_norm_um == pytest.approx(np.sqrt(np.mean(norm**2)))
    assert s.p95_norm_um == pytest.approx(np.percentile(norm, 95))
    assert s.max_norm_um == pytest.approx(math.sqrt(101.0))
    assert s.n_samples == 4
    one = summarise(np.array([1.0, -3.0]) * 1e-6)
    assert one.rms_um == pytest.approx((math.sqrt(5.0),))
    assert one.max_norm_um == pytest.approx(3.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.n_samples = 3


def test_error_spectrum_finds_sinusoid():
    t = np.arange(0, 4.0, 1e-3)
    err = np.column_stack([2e-6 * np.sin(2 * np.pi * 50 * t), 1e-6 * np.sin(2 * np.pi * 120 * t), 0 * t])
    f, amp = error_spectrum(t, err)
    assert amp.shape == (f.size, 3)
    assert f[np.argmax(amp[:, 0])] == pytest.approx(50.0)
    assert f[np.argmax(amp[:, 1])] == pytest.approx(120.0)
    assert amp[:, 0].max() == pytest.approx(2e-6, rel=0.02)
    assert amp[:, 1].max() == pytest.approx(1e-6, rel=0.02)
    f1, amp1 = error_spectrum(t, err[:, 0])
    assert amp1.shape == f1.shape


def test_worst_region_finds_hot_cell():
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.1, 0.1, size=(5000, 2))
    xyz = np.column_stack([xy, np.zeros(len(xy))])
    err = np.full(len(xy), 1e-6)
    hot = (xy[:, 0] >= 0.04) & (xy[:, 0] < 0.06) & (xy[:, 1] >= -0.02) & (xy[:, 1] < 0.0)
    err[hot] = 5e-6
    w = worst_region(xyz, err, grid_mm=20)
    assert (w.x_mm, w.y_mm) == (50.0, -10.0)
    assert w.rms_um == pytest.approx(5.0)
    assert w.cell_rms_um.shape == (w.y_centres_mm.size, w.x_centres_mm.size) == (10, 10)
    assert w.cell_count.sum() == len(xy)
    np.testing.assert_allclose(np.nanmin(w.cell_rms_um), 1.0)


def test_evaluate_report_and_json():
    ref = _spiral(T_S)
    act = _spiral(T_S - 0.004)
    act[:, 0] += 20e-6 * np.sin(2 * np.pi * 35 * T_S)
    rep = evaluate(T_S, ref, act)
    assert isinstance(rep, ErrorReport)
    assert rep.lag_s == pytest.approx(0.004, abs=2e-4)
    assert rep.duration_s == pytest.approx(2.0)
    assert rep.contour.rms_norm_um <= rep.lag.rms_norm_um + 1e-9 < rep.time.rms_norm_um
    assert rep.lag.max_norm_um == pytest.approx(20.0, rel=0.1)
    d = json.loads(json.dumps(rep.to_dict()))
    assert d["lag_s"] == rep.lag_s
    assert len(d["time"]["rms_um"]) == 3 and len(d["contour"]["rms_um"]) == 1
    assert d["worst"]["grid_mm"] == 20.0


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_contour_matches_brute_force(seed):
    # random walk with self-crossings, a slow (dense) stretch and long jumps
    rng = np.random.default_rng(seed)
    scale = np.r_[np.full(100, 1e-3), np.full(150, 1e-5), np.full(50, 5e-3)]
    steps = rng.normal(size=(300, 3)) * scale[:, None]
    ref = np.cumsum(steps, axis=0)
    act = ref[rng.integers(0, len(ref), 500)] + rng.normal(scale=2e-3, size=(500, 3))
    brute = point_segment_distance(act[:, None, :], ref[None, :-1], ref[None, 1:]).min(axis=1)
    np.testing.assert_allclose(contour_error(ref, act, k_neighbours=2), brute, rtol=1e-12, atol=1e-18)


def test_evaluate_masked_is_evaluate_plus_the_masked_rms():
    """One computation of each error serves the whole report and the masked RMS: the report equals
    :func:`evaluate`'s, and an all-true mask gives the report's own RMS."""
    from ffcomp.sim.metrics import evaluate, evaluate_masked

    t = np.arange(400) * 1e-3
    ref = np.stack([0.05 * np.sin(2 * np.pi * t), 0.05 * np.cos(2 * np.pi * t), np.zeros_like(t)], 1)
    act = ref + 2e-5 * np.stack([np.sin(2 * np.pi * 60 * t), np.zeros_like(t), np.cos(2 * np.pi * 60 * t)], 1)
    rep, (lag_all, cont_all) = evaluate_masked(t, ref, act, np.ones(len(t), bool))
    ev = evaluate(t, ref, act)
    assert (rep.time, rep.lag, rep.contour, rep.lag_s) == (ev.time, ev.lag, ev.contour, ev.lag_s)
    assert lag_all == pytest.approx(rep.lag.rms_norm_um, rel=1e-9)
    assert cont_all == pytest.approx(rep.contour.rms_norm_um, rel=1e-9)
    _, (lag_half, _) = evaluate_masked(t, ref, act, t < 0.2)
    assert lag_half > 0 and lag_half != lag_all
    assert all(np.isnan(evaluate_masked(t, ref, act, np.zeros(len(t), bool))[1]))

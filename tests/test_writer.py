"""The G-code writer's point placement: the batched Douglas-Peucker equals the run-by-run one."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.gcode.writer import _breakpoints_runs, adaptive_breakpoints


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(2, 60), min_size=1, max_size=8), st.integers(0, 2**31 - 1),
       st.sampled_from([1e-4, 5e-3, 0.05]))
def test_batched_breakpoints_equal_run_by_run(lengths, seed, tol):
    rng = np.random.default_rng(seed)
    runs = [np.cumsum(rng.normal(0, 0.02, (n, 3)), axis=0) for n in lengths]
    P = np.concatenate(runs)
    first = np.cumsum([0] + lengths[:-1])
    last = first + np.array(lengths) - 1
    keep = np.zeros(len(P), bool)
    keep[first] = keep[last] = True
    got = np.nonzero(_breakpoints_runs(P, first, last, tol, keep))[0]
    want = np.concatenate([f + adaptive_breakpoints(r, tol) for f, r in zip(first, runs)])
    np.testing.assert_array_equal(got, want)


def test_breakpoints_keep_every_sample_within_tolerance():
    t = np.linspace(0, 1, 400)
    P = np.column_stack([np.sin(7 * t), np.cos(5 * t), 0.01 * t])
    idx = adaptive_breakpoints(P, 1e-3)
    lerp = np.column_stack([np.interp(np.arange(len(P)), idx, P[idx, k]) for k in range(3)])
    assert np.max(np.abs(lerp - P)) <= 1e-3
    assert len(idx) < len(P) / 3


def test_holds_leave_the_nozzle_where_it_was():
    """Sub-micrometre segments become holds (G4): the firmware stays put, so the next segment must
    start from the held point, however many holds pile up (else it would cover more than it is timed for)."""
    from ffcomp.gcode.writer import _settle_holds

    P = np.zeros((8, 3))
    P[1:6, 0] = np.arange(1, 6) * 0.0008  # five sub-micrometre steps: 4 um in all
    P[6:, 0] = [0.1, 0.2]
    i, j = np.arange(7), np.arange(1, 8)
    first = np.r_[True, np.zeros(6, bool)]
    Pr, d, dist, hold = _settle_holds(np.round(P, 4), i, j, first, np.array([0]), np.array([7]))
    assert hold[:5].all() and not hold[5:].any()
    np.testing.assert_allclose(Pr[:6], 0.0)  # held at the start
    assert dist[5] == pytest.approx(0.1)  # the next segment covers the whole way from the held point


def test_fitted_points_bring_the_output_closer_with_the_same_lines(tmp_path, monkeypatch):
    """The least-squares point values (knot_fit) against the samples' own: the re-planned output's
    carriages come closer to the intended commands (self-check RMS) with as many segments."""
    from functools import partialmethod

    from ffcomp.gcode.writer import GcodeWriter
    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
    from ffcomp.profile import default_profile

    ang = np.linspace(0.0, 2 * np.pi, 25)
    src = tmp_path / "circle.gcode"
    src.write_text("\n".join(["G90", "SET_VELOCITY_LIMIT ACCEL=8000", "G1 X30 Y0 Z5 F6000", "G4 P0"]
                             + [f"G1 X{30 * np.cos(a):.3f} Y{30 * np.sin(a):.3f} F9000" for a in ang]) + "\n")
    opts = CompensateOptions(predict=False)
    fitted = compensate_file(str(src), str(tmp_path / "fit.gcode"), default_profile(), opts)
    orig = GcodeWriter.__init__
    monkeypatch.setattr(GcodeWriter, "__init__", partialmethod(orig, fit_points=False))
    plain = compensate_file(str(src), str(tmp_path / "plain.gcode"), default_profile(), opts)
    assert abs(fitted.segments - plain.segments) <= 0.02 * plain.segments
    assert fitted.self_check_rms_um < 0.85 * plain.self_check_rms_um  # measured: 0.99 against 1.23 um
    assert abs(fitted.self_check_drift_ms) < 0.2

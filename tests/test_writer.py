"""The G-code writer's point placement: the batched Douglas-Peucker equals the run-by-run one."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from ffcomp.gcode.breakpoints import adaptive_breakpoints, breakpoints_runs


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
    got = np.nonzero(breakpoints_runs(P, first, last, tol, keep))[0]
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
    from ffcomp.gcode.holds import settle_holds

    P = np.zeros((8, 3))
    P[1:6, 0] = np.arange(1, 6) * 0.0008  # five sub-micrometre steps: 4 um in all
    P[6:, 0] = [0.1, 0.2]
    i, j = np.arange(7), np.arange(1, 8)
    first = np.r_[True, np.zeros(6, bool)]
    Pr, d, dist, hold = settle_holds(np.round(P, 4), i, j, first, np.array([0]), np.array([7]))
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


def test_extrusion_by_length_keeps_totals_and_evens_the_ratio():
    """Within a group (source moves of one ratio) the extrusion is spread by written length: the
    group's total is unchanged and the spread segments share one e/d; holds keep their value, and
    so do a group's first segments after a change of ratio until their own ratio nears the group's
    (the ratio then changes gradually, junction by junction)."""
    from ffcomp.gcode.writer import EDGE_SHARE, by_length

    rng = np.random.default_rng(3)
    n = 60
    group = np.sort(rng.integers(0, 5, n))
    dist = rng.uniform(0.01, 0.3, n)
    hold = rng.random(n) < 0.1
    de = rng.uniform(0.0, 0.05, n)
    out = by_length(de, dist, group, hold)
    np.testing.assert_array_equal(out[hold], de[hold])
    for g in np.unique(group):
        m = group == g
        assert out[m].sum() == pytest.approx(de[m].sum(), rel=1e-12, abs=1e-15)
        ch = m & (out != de)
        if ch.sum() > 1:
            r = out[ch] / dist[ch]
            assert np.ptp(r) < 1e-12 * max(r.max(), 1e-12)
    np.testing.assert_array_equal(by_length(de, np.zeros(n), group, hold), de)
    # a travel (ratio 0) then a print move at 0.1 whose first segments' time ratios ramp up: the ramp
    # is kept up to the first segment within EDGE_SHARE of the group's ratio, the rest is spread
    e = np.r_[0.0, 0.0, 0.005, 0.012, np.tile([0.0193, 0.0195, 0.0191], 40)]
    d = np.full(len(e), 0.2)
    grp = np.r_[0, 0, np.ones(len(e) - 2, int)]
    o = by_length(e, d, grp, np.zeros(len(e), bool))
    rho_g = e[2:].sum() / d[2:].sum()
    assert abs(e[4] / d[4] - rho_g) <= EDGE_SHARE * rho_g < abs(e[3] / d[3] - rho_g)
    np.testing.assert_array_equal(o[:4], e[:4])
    assert np.ptp(o[4:] / d[4:]) < 1e-12 and o.sum() == pytest.approx(e.sum(), rel=1e-12)


def test_ratio_steps_stay_within_the_extruder_junction_limit():
    """A travel (ratio 0) into a print move at 0.1 mm/mm whose first segments' reference-time ratios
    jump 0 -> 0.1 over two junctions at 150 mm/s: Klipper would pass those junctions at
    ``icv / |diff_r|`` = 20 mm/s.  Ramped: every step within ``RATIO_STEP_SHARE * icv / v``, the
    group's total unchanged, its even ratio moved by under 10 %; a group the extruder's own limits
    cap, and one whose ramp would need more than that shift, keep their values."""
    from ffcomp.gcode.extrusion import RATIO_STEP_SHARE, by_length, limit_ratio_steps

    n = 200
    d = np.full(n, 0.15)  # 1 ms segments at 150 mm/s
    v = np.full(n, 150.0)
    e = np.r_[np.zeros(10), 0.005, 0.012, np.full(n - 12, 0.015)]
    grp = np.r_[np.zeros(10, int), np.ones(n - 10, int)]
    hold = np.zeros(n, bool)
    plain = by_length(e, d, grp, hold)
    out = by_length(e, d, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    r = out / d
    assert np.max(np.abs(np.diff(plain / d))) > 0.03  # the case: 20-30 mm/s junctions
    assert np.all(np.abs(np.diff(r)) <= RATIO_STEP_SHARE * 1.0 / 150.0 * (1 + 1e-9))
    assert out[10:].sum() == pytest.approx(e[10:].sum(), rel=1e-12)
    np.testing.assert_array_equal(out[:10], e[:10])
    assert abs(r[-1] / 0.1 - 1) < 0.1 and np.ptp(r[-50:]) < 1e-12
    # capped (a retracting or z-only extruding move): untouched, unless the extruder's caps at the new
    # ratios stay clear of the segments' speed and acceleration
    edge = np.r_[np.zeros(10, bool), True, True, np.zeros(n - 12, bool)]
    cap = np.ones(n, bool)
    np.testing.assert_array_equal(limit_ratio_steps(plain, d, v, grp, hold, edge, 1.0, capped=cap), plain)
    np.testing.assert_array_equal(limit_ratio_steps(plain, d, v, grp, hold, edge, 1.0, capped=cap,
                                                    e_limits=(20.0, 3000.0)), plain)  # 0.1 * 2 * 150 > 20
    np.testing.assert_array_equal(limit_ratio_steps(plain, d, v, grp, hold, edge, 1.0, capped=cap,
                                                    e_limits=(120.0, 3000.0)), out)
    # a short group whose ramp would move its even ratio by more than 10 %: untouched
    m = 30
    np.testing.assert_array_equal(by_length(e[:m], d[:m], grp[:m], hold[:m], speed_mm_s=v[:m], icv_mm_s=1.0),
                                  by_length(e[:m], d[:m], grp[:m], hold[:m]))



def test_a_ratio_step_a_dry_group_cannot_ramp_is_ramped_at_the_end_of_the_group_before(monkeypatch):
    """A retracting z move (-0.2 mm/mm) into a dry one, every junction at 40 mm/s: one step of 0.2
    at the groups' junction caps it at ``icv / 0.2`` = 5 mm/s.  The dry group has no extrusion to
    take up a ramp at its start, so the retracting group's last segments ramp towards 0 instead
    (``extrusion.BACK_RAMP``): every junction within ``RATIO_STEP_SHARE * icv / v``, each group's
    total unchanged, the dry group dry, the retracting group's start (its edge) as it was."""
    from ffcomp.gcode import extrusion
    from ffcomp.gcode.extrusion import RATIO_STEP_SHARE, by_length

    n = 300
    d = np.full(n, 0.04)  # 1 ms segments at 40 mm/s
    v = np.full(n, 40.0)
    e = np.r_[np.zeros(20), -0.002, -0.006, np.full(198, -0.008), np.zeros(80)]
    grp = np.r_[np.zeros(20, int), np.ones(200, int), np.full(80, 2)]
    hold = np.zeros(n, bool)
    cap = np.r_[np.zeros(20, bool), np.ones(200, bool), np.zeros(80, bool)]  # (retracting: capped)
    lim = RATIO_STEP_SHARE * 1.0 / 40.0
    kw = dict(speed_mm_s=v, icv_mm_s=1.0, capped=cap, e_limits=(120.0, 6000.0))
    monkeypatch.setattr(extrusion, "BACK_RAMP", False)
    fwd = by_length(e, d, grp, hold, **kw)
    assert abs(fwd[220] / d[220] - fwd[219] / d[219]) > 0.19  # the case: one step into the dry group
    monkeypatch.setattr(extrusion, "BACK_RAMP", True)
    out = by_length(e, d, grp, hold, **kw)
    r = out / d
    assert np.all(np.abs(np.diff(r)) <= lim * (1 + 1e-9)), np.abs(np.diff(r)).max()
    for g0, g1 in ((0, 20), (20, 220), (220, 300)):
        assert out[g0:g1].sum() == pytest.approx(e[g0:g1].sum(), rel=1e-12)
    assert not out[220:].any() and not out[:20].any()
    start = np.nonzero(np.abs(fwd / d - fwd[100] / d[100]) < 1e-12)[0][0]  # where the forward ramp ends
    assert 25 < start < 40
    np.testing.assert_array_equal(out[:start], fwd[:start])  # the retracting group's start as it was
    assert abs(r[219]) <= lim * 1.0001 and np.ptp(r[50:150]) < 1e-12  # ramped to the dry group; even before
    assert abs(r[100] / (fwd[100] / d[100]) - 1) < 0.1
    # with no step at a group's end it changes nothing
    np.testing.assert_array_equal(by_length(e[:220], d[:220], grp[:220], hold[:220], speed_mm_s=v[:220], icv_mm_s=1.0,
                                            capped=cap[:220], e_limits=(120.0, 6000.0)), fwd[:220])

def test_a_group_cut_between_chunks_ramps_from_the_last_chunks_ratio():
    """One group (a single source move) whose compensated segments' reference-time extrusion runs at
    0.188 mm/mm over its first half and 0.229 over its second (the command's lead changes along it),
    cut between two of the writer's chunks there: each chunk evens its own part, and the junction
    at the cut steps by 0.041, which Klipper passes at ``icv / 0.041`` = 24 mm/s, not the 50 mm/s
    the segments run (a retracting z move on other_delta: 5.3 ms late).  Given the last chunk's last
    segment (``prev``), the second part ramps from its ratio: every step within the junction limit,
    the part's total unchanged.  After a hold (the firmware stops) it does not."""
    from ffcomp.gcode.extrusion import RATIO_STEP_SHARE, by_length

    d = np.full(60, 0.05)  # 1 ms segments at 50 mm/s
    v = np.full(60, 50.0)
    grp, hold = np.zeros(60, int), np.zeros(60, bool)
    a = by_length(0.188 * d, d, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    e_b = 0.229 * d * (1 + 0.01 * np.sin(np.arange(60)))  # (its own segments' reference time)
    plain = by_length(e_b, d, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    prev = (float(a[-1] / d[-1]), float(d[-1]), float(v[-1]))
    assert abs(plain[0] / d[0] - prev[0]) > 0.04  # the case
    out = by_length(e_b, d, grp, hold, speed_mm_s=v, icv_mm_s=1.0, prev=prev)
    r = np.r_[prev[0], out / d]
    assert np.all(np.abs(np.diff(r)) <= RATIO_STEP_SHARE * 1.0 / 50.0 * (1 + 1e-9))
    assert out.sum() == pytest.approx(e_b.sum(), rel=1e-12)
    assert np.ptp(r[-30:]) < 1e-12 and abs(r[-1] / 0.229 - 1) < 0.05
    held = hold.copy()
    held[0] = True
    np.testing.assert_array_equal(by_length(e_b, d, grp, held, speed_mm_s=v, icv_mm_s=1.0, prev=prev),
                                  by_length(e_b, d, grp, held, speed_mm_s=v, icv_mm_s=1.0))


def test_a_group_that_leaves_a_reversal_takes_its_ratio_at_once(monkeypatch):
    """A z move down to rest, then up while retracting (ratio -0.27 mm/mm): the reference-time
    extrusion of the first segments up ramps the ratio over several junctions (-0.04, -0.35, then
    the group's), and Klipper caps each of those junctions at ``icv / |diff_r|`` while the carriage
    speeds up.  The junction at the reversal itself is one the corner rule already holds at a
    crawl (``corner_v_mm_s`` ~0): the group takes its even ratio from its first segment there, its
    total unchanged.  Where the corner rule leaves the junction fast (``inf``), the edge stays
    (with ``EDGE_RETRACTING``; by default a retracting group has no edge: one ratio from its start
    whatever the corner)."""
    from ffcomp.gcode import extrusion
    from ffcomp.gcode.extrusion import by_length

    d = np.r_[np.linspace(0.04, 0.003, 10), 0.0021, 0.0057, np.linspace(0.017, 0.05, 20)]
    e = np.r_[np.zeros(10), -0.00008, -0.00198, -0.2656 * np.linspace(0.017, 0.05, 20)]
    grp = np.r_[np.zeros(10, int), np.ones(22, int)]
    hold = np.zeros(len(d), bool)
    v = d / 1e-3
    cv = np.full(len(d), np.inf)
    cv[10] = 0.05  # the reversal: the corner rule's limit there, mm/s
    kw = dict(speed_mm_s=v, icv_mm_s=1.0)
    out = by_length(e, d, grp, hold, corner_v_mm_s=cv, **kw)
    r = out[10:] / d[10:]
    assert np.ptp(r) < 1e-12 * abs(r[0])  # one ratio from the reversal on
    assert out[10:].sum() == pytest.approx(e[10:].sum(), rel=1e-12)
    np.testing.assert_array_equal(out[:10], e[:10])
    # without the corner limit (or without it at that junction) a retracting group keeps no edge:
    # its first segments do not keep their reference-time values (the ramp to its ratio, if any, is
    # limit_ratio_steps')
    for c in (None, np.full(len(d), np.inf)):
        nod = by_length(e, d, grp, hold, corner_v_mm_s=c, **kw)
        assert nod[10] != e[10] and nod[11] != e[11]
        assert nod[10:].sum() == pytest.approx(e[10:].sum(), rel=1e-12)
    # with an edge for retractions, the first keeps its own value and the ratio ramps from there
    monkeypatch.setattr(extrusion, "EDGE_RETRACTING", True)
    np.testing.assert_array_equal(by_length(e, d, grp, hold, corner_v_mm_s=cv, **kw), out)
    for c in (None, np.full(len(d), np.inf)):
        kept = by_length(e, d, grp, hold, corner_v_mm_s=c, **kw)
        assert kept[10] == e[10] and abs(kept[11] / d[11] - r[0]) > 0.3 * abs(r[0])


def _corner_chain(print_first: bool, cruise_s: float, lag_s: float = 0.003, ratio: float = 0.2,
                  vc: float = 15.0, a: float = 1e4, dt: float = 1e-3):
    """A compensated command through a 90 degree corner between a travel and a print move at
    0.2 mm/mm (or the print move first), sampled every ms: from rest to 100 mm/s, braking to ``vc``
    at the corner, up to 150 mm/s for ``cruise_s`` and back to rest; each segment's extrusion is the
    reference's over its time, the reference lagging the command by ``lag_s`` (as the plan lags its
    compensated command).  Returns P0, P1, D, dist, group, de."""
    v0, v1 = 100.0, 150.0
    tc = 0.02 + (v0 - vc) / a
    tk, vk = np.array([(0, 0), (v0 / a, v0), (0.02, v0), (tc, vc), (tc + (v1 - vc) / a, v1),
                       (tc + cruise_s, v1), (tc + cruise_s + v1 / a, 0)]).T
    tf = np.linspace(0.0, tk[-1], 400001)
    vf = np.interp(tf, tk, vk)
    sf = np.r_[0.0, np.cumsum(0.5 * (vf[1:] + vf[:-1]) * np.diff(tf))]
    t = np.round(np.arange(0.0, tk[-1] + 1e-12, dt), 9)
    s = np.interp(t, tf, sf)
    sc = float(np.interp(tc, tf, sf))
    P = np.zeros((len(t), 3))
    P[:, 0], P[:, 1], P[:, 2] = np.minimum(s - sc, 0.0), np.maximum(s - sc, 0.0), 1.0
    s_ref = np.interp(np.maximum(t - lag_s, 0.0), tf, sf)
    s_ref[-1] = s[-1]  # (the reference ends where the command does)
    e_ref = ratio * (np.minimum(s_ref, sc) if print_first else np.maximum(s_ref - sc, 0.0))
    grp = (t[:-1] >= tc - 1e-9).astype(int)
    dist = np.linalg.norm(np.diff(P, axis=0), axis=1)
    return P[:-1], P[1:], np.full(len(dist), dt), dist, grp, np.diff(e_ref)


def _firmware_late_ms(lim, P0, P1, D, e) -> float:
    """Largest lateness (ms, absolute clock) of the chain as Klipper runs it with the feed solve's
    feeds (an independent re-plan: segment limits, junction rules with the extruder's, lookahead)."""
    from ffcomp.gcode import feed_solve as fs
    from ffcomp.gcode.chain_plan import junction_v2, plan_chain, segment_limits

    none = np.zeros(len(D), bool)
    F = fs.solve_feeds(lim, fs.TimingState(), P0, P1, D, e, none, none, False)
    d = P1 - P0
    dist = np.linalg.norm(d, axis=1)
    vmax, acc = segment_limits(lim, P0, P1, e)
    jv = np.r_[0.0, junction_v2(lim, d / dist[:, None], e / dist, acc, 2 * dist * acc)]
    t = plan_chain(dist, np.minimum(F, vmax) ** 2, acc, jv, 0.0, 0.0)[0]
    return float(np.abs(np.cumsum(t - D)).max()) * 1e3


@pytest.mark.parametrize("print_first,cruise_s,lag_s,was_ms,now_ms", [
    (False, 0.01, 0.003, 1.5, 0.02), (False, 0.02, 0.003, 1.0, 0.02), (False, 0.06, 0.005, 1.2, 0.02),
    (True, 0.02, 0.005, 0.3, 0.12), (False, 0.12, 0.003, None, None)])
def test_a_change_of_ratio_goes_onto_the_junction_where_the_firmware_loses_least(profile, print_first, cruise_s,
                                                                                 lag_s, was_ms, now_ms):
    """A travel into a short print move (or a print move into a travel) through a corner the
    compensated command takes at 15 mm/s: the reference-time extrusion ramps the ratio over the
    segments after the corner while the command speeds up to 150 mm/s, and Klipper caps each of
    those junctions at ``icv / |diff_r|``.  The writer's ramp (:func:`by_length` with its
    junction-limited ramp, which gives up on short moves) ran 1.0-1.6 ms late; the ratio now steps
    once, at the corner, and the chain runs on its clock (judged by the feed solve and an
    independent re-plan), its total extrusion unchanged.  A long move's ramp already kept the
    clock: unchanged."""
    from ffcomp.gcode.chain_plan import ChainLimits, segment_limits
    from ffcomp.gcode.extrusion import by_length, junction_loss_s, place_ratio_steps

    lim = ChainLimits(profile, 1e5, 100.0)  # (the compensated file's header)
    P0, P1, D, dist, grp, de = _corner_chain(print_first, cruise_s, lag_s=lag_s)
    hold = np.zeros(len(D), bool)
    v = dist / D
    was = by_length(de, dist, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    acc = segment_limits(lim, P0, P1, was)[1]
    new = place_ratio_steps(was, dist, v, acc, grp, hold, 1.0)
    assert new.sum() == pytest.approx(de.sum(), rel=1e-12)
    late_was, late_new = _firmware_late_ms(lim, P0, P1, D, was), _firmware_late_ms(lim, P0, P1, D, new)
    if was_ms is None:
        assert late_was < 0.01
        np.testing.assert_array_equal(new, was)
        return
    assert late_was > was_ms and late_new < now_ms, (late_was, late_new)
    # one step between 0 and the move's ratio (within 10 %), at the corner (the slowest junction);
    # into the travel a few segments after it where the print move's last segments take up the
    # reference's extrusion that spills over the corner (their ratio within 10 % then)
    r = new / dist
    dr = np.diff(r)
    corner = int(np.nonzero(grp)[0][0]) - 1
    big = np.nonzero(np.abs(dr) > 0.1)[0]
    assert len(big) == 1 and np.all(np.abs(np.delete(dr, big)) <= 0.02 + 1e-12)
    k = int(big[0])
    assert k == corner if not print_first else corner <= k <= corner + 5
    moving = r[: k + 1][r[: k + 1] > 0] if print_first else r[k + 1:]
    assert np.all(np.abs(moving / 0.2 - 1) <= 0.1 + 1e-12)
    # at the corner the loss model charges it well under 0.1 ms
    jv = min(v[k], v[k + 1])
    assert jv < 60.0
    if not print_first:
        assert float(junction_loss_s(jv, 1.0 / abs(dr[k]), min(acc[k], acc[k + 1]))) < 1e-4


def test_ratio_steps_stay_put_at_holds_capped_moves_and_short_groups(profile):
    """Nothing moves where the firmware stops anyway (a hold at the corner), where the extruder's
    own limits cap the move (a retraction while travelling, extrusion without XY), or where taking
    up the step's extrusion would change a ratio by more than ``max_shift``."""
    from ffcomp.gcode.chain_plan import ChainLimits, segment_limits
    from ffcomp.gcode.extrusion import by_length, place_ratio_steps

    lim = ChainLimits(profile, 1e5, 100.0)
    P0, P1, D, dist, grp, de = _corner_chain(False, 0.02)
    n = len(D)
    v = dist / D
    hold = np.zeros(n, bool)
    corner = int(np.nonzero(grp)[0][0])
    held = hold.copy()
    held[corner] = True
    was = by_length(de, dist, grp, held, speed_mm_s=v, icv_mm_s=1.0)
    acc = segment_limits(lim, P0, P1, was)[1]
    np.testing.assert_array_equal(place_ratio_steps(was, dist, v, acc, grp, held, 1.0), was)
    was = by_length(de, dist, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    np.testing.assert_array_equal(place_ratio_steps(was, dist, v, acc, grp, hold, 1.0, capped=grp == 1), was)
    assert not np.array_equal(place_ratio_steps(was, dist, v, acc, grp, hold, 1.0), was)
    # into a travel the print move's last segments take up the reference's spill over the corner
    # (by 4-10 % here): not if that may not move their ratio by more than 0.1 %
    P0, P1, D, dist, grp, de = _corner_chain(True, 0.02, lag_s=0.005)
    v = dist / D
    was = by_length(de, dist, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    acc = segment_limits(lim, P0, P1, was)[1]
    assert not np.array_equal(place_ratio_steps(was, dist, v, acc, grp, hold, 1.0), was)
    np.testing.assert_array_equal(place_ratio_steps(was, dist, v, acc, grp, hold, 1.0, max_shift=1e-3), was)


@pytest.mark.parametrize("prof", ["default", "other_delta"])
def test_high_flow_segments_keep_the_source_ratio_and_the_clock(tmp_path, prof):
    """At 0.11 mm of filament per mm (a 0.8 mm nozzle) Klipper slows a junction to
    ``instantaneous_corner_velocity / |diff_r|``: the written segments of one source move must keep
    one extrusion ratio, or the re-planned output drifts (it ran 2 ms early on other_delta)."""
    import math
    import re

    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
    from ffcomp.profile import default_profile, load_profile

    ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
    lines = ["G90", "M82", "G92 E0", "SET_VELOCITY_LIMIT ACCEL=10000", "M204 S10000", "G1 X30 Y0 Z0.4 F12000"]
    e, x0, y0 = 0.0, 30.0, 0.0
    for k in range(1, 49):
        a = 2 * math.pi * k / 48
        x, y = 30 * math.cos(a), 30 * math.sin(a)
        e += 0.11 * math.hypot(x - x0, y - y0)
        lines.append(f"G1 X{x:.3f} Y{y:.3f} E{e:.5f} F12000")
        x0, y0 = x, y
    src = tmp_path / "flow.gcode"
    src.write_text("\n".join(lines) + "\n")
    p = default_profile() if prof == "default" else load_profile(ROOT / "samples/profiles/other_delta.toml")
    out = tmp_path / "out.gcode"
    s = compensate_file(str(src), str(out), p, CompensateOptions(predict=False))
    assert abs(s.self_check_drift_ms) < 0.5
    # the written segments' ratios: within 2 % of the source's 0.11 wherever a segment is longer
    # than 20 um (shorter ones are dominated by the 5-decimal rounding of E)
    last, tot, ratios = None, 0.0, []
    for ln in out.read_text().splitlines():
        m = re.match(r"G1 X(\S+) Y(\S+) Z(\S+)(?: E(\S+))?", ln)
        if not m:
            continue
        pt = np.array([float(m.group(i)) for i in (1, 2, 3)])
        if last is not None and m.group(4):
            d = float(np.linalg.norm(pt - last))
            tot += float(m.group(4))
            if d > 0.02:
                ratios.append(float(m.group(4)) / d)
        last = pt
    assert tot == pytest.approx(e, abs=2e-5)
    # after the travel the ratio ramps up over a few segments (by design, see by_length), then holds
    r = np.array(ratios)
    near = np.nonzero(np.abs(r - 0.11) < 0.0022)[0]
    # (over more segments where the command runs fast there: each step within the extruder's junction limit)
    assert 0 < near[0] <= 20 and np.all(np.diff(r[:near[0] + 1]) > 0)
    r = r[near[0]:]
    assert len(r) > 100 and np.all(np.abs(r - 0.11) < 0.0022), (r.min(), r.max())


@given(st.integers(0, 10_000))
@example(929)  # the passes ended without settling: a step of 2.5x the limit at the hand-over
@settings(max_examples=60, deadline=None)
def test_ratio_steps_keep_totals_holds_and_the_limit(seed):
    """Property: on random groups, speeds and holds, the ramped extrusion keeps every group's total
    and every hold's value, and wherever it changed a group, every step inside that group (between
    two moving segments) stays within the junction limit (20 % slack, see below)."""
    from ffcomp.gcode.extrusion import RATIO_STEP_SHARE, by_length

    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 120))
    grp = np.sort(rng.integers(0, 6, n))
    d = rng.uniform(0.005, 0.4, n)
    v = rng.uniform(5.0, 300.0, n)
    hold = rng.random(n) < 0.05
    rho = rng.choice([0.0, 0.03, 0.1, -0.04], size=grp.max() + 1)
    de = rho[grp] * d * rng.uniform(0.6, 1.4, n)
    plain = by_length(de, d, grp, hold)
    out = by_length(de, d, grp, hold, speed_mm_s=v, icv_mm_s=1.0)
    np.testing.assert_array_equal(out[hold], de[hold])
    for g in np.unique(grp):
        m = grp == g
        assert out[m].sum() == pytest.approx(plain[m].sum(), rel=1e-9, abs=1e-12)
        if np.array_equal(out[m], plain[m]):
            continue
        idx = np.nonzero(m)[0]
        for a, b in zip(idx[:-1], idx[1:]):
            if hold[a] or hold[b]:
                continue
            step = abs(out[b] / d[b] - out[a] / d[a])
            # (within 20 %: a ramp that outlasts its group is scaled by up to 10 % to keep the total,
            # and the hand-over to the group's even ratio may add a tenth of the limit)
            assert step <= 1.2 * RATIO_STEP_SHARE / max(v[a], v[b]) + 1e-12, (a, step)


def test_rest_holds_merge_into_their_neighbours():
    """A run's first segment that leaves rest on the plan's time and became a hold, and a run's last
    segment on the plan's rest point that became a hold, are merged into the segment next to them;
    other holds (mid-run, a run without either flag) stay."""
    from ffcomp.gcode.holds import merged_rest_holds

    i = np.arange(8)
    j = i + 1
    srun = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    first = np.r_[True, False, False, False, True, False, False, False]
    hold = np.array([True, False, True, True, False, False, False, True])
    leaves = np.r_[np.ones(4, bool), np.zeros(4, bool)]
    rests = np.r_[np.zeros(4, bool), np.ones(4, bool)]
    i2, j2 = merged_rest_holds(i, j, srun, first, hold, leaves, rests)
    # run 0: its first hold merges forward (0 -> 2); its last hold follows a hold: stays.
    # run 1: its last hold merges back (6 -> 8)
    np.testing.assert_array_equal(i2, [0, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(j2, [2, 3, 4, 5, 6, 8])
    assert merged_rest_holds(i, j, srun, first, hold, np.zeros(8, bool), np.zeros(8, bool)) is None


def test_a_long_first_hold_is_not_merged():
    """A run's first segment that leaves rest as a hold merges forward only where it spans at most
    ``REST_MERGE_MAX_SAMPLES`` samples: a long one is the command standing on the lead (a ``G4``)."""
    from ffcomp.gcode.holds import REST_MERGE_MAX_SAMPLES, merged_rest_holds

    i = np.arange(4)
    j = i + 1
    srun = np.array([0, 0, 1, 1])
    first = np.r_[True, False, True, False]
    hold = np.r_[True, False, True, False]
    leaves = np.ones(4, bool)
    span = np.array([1.0, 1.0, 80.0, 5.0])
    assert REST_MERGE_MAX_SAMPLES is not None and REST_MERGE_MAX_SAMPLES < 80
    i2, j2 = merged_rest_holds(i, j, srun, first, hold, leaves, np.zeros(4, bool), span=span)
    np.testing.assert_array_equal(i2, [0, 2, 3])  # run 0's short hold merges; run 1's 80-sample one stays
    np.testing.assert_array_equal(j2, [2, 3, 4])
    i3, _ = merged_rest_holds(i, j, srun, first, hold, leaves, np.zeros(4, bool))  # no spans: both merge
    np.testing.assert_array_equal(i3, [0, 2])


def test_a_move_that_cannot_leave_rest_in_its_time_takes_the_hold_before_it():
    """``holds.merged_start_holds``: a dry move after dry holds of its run that needs more than
    ``START_HOLD_SHORT`` times its time from rest at its acceleration limit takes over holds before
    it (the last first) until it can; one that can, or a wet one, keeps its holds."""
    from ffcomp.gcode.chain_plan import ChainLimits
    from ffcomp.gcode.holds import merged_start_holds
    from ffcomp.profile import load_profile

    lim = ChainLimits(load_profile("samples/profiles/other_delta.toml"), 1e5, 5.0)  # max_z_accel 3,000
    # points along z: a rest (0 -> 1 -> 2 -> 3 hold within 0.3 um), then 3 um in 1 ms (needs 1.41 ms
    # from rest at 3,000 mm/s^2), then on
    z = np.array([0.0, 0.0001, 0.0002, 0.0003, 0.0033, 0.0100])
    P = np.column_stack([np.zeros(6), np.zeros(6), 5.0 + z])
    i, j = np.arange(5), np.arange(1, 6)
    hold = np.array([True, True, True, False, False])
    srun = np.zeros(5, np.int64)
    D = np.array([5e-3, 5e-3, 1e-3, 1e-3, 1e-3])
    dry = np.ones(5, bool)
    i2, j2 = merged_start_holds(lim, i, j, P, srun, hold, dry, D)
    np.testing.assert_array_equal(i2, [0, 1, 2, 4])  # the 1 ms hold (2 -> 3) went into the move
    np.testing.assert_array_equal(j2, [1, 2, 4, 5])
    wet = dry.copy()
    wet[3] = False
    assert merged_start_holds(lim, i, j, P, srun, hold, wet, D) is None
    slow = D.copy()
    slow[3] = 2e-3  # 3 um in 2 ms: it can
    assert merged_start_holds(lim, i, j, P, srun, hold, dry, slow) is None


def test_holds_that_extrude_merge_into_a_moving_segment():
    """Wet holds (they would be extruder-only lines, a stop of the firmware) merge into the moving
    segment after them, at a run's end into the one before; dry holds (G4) stay."""
    from ffcomp.gcode.holds import merged_wet_holds

    i = np.arange(9)
    j = i + 1
    srun = np.array([0, 0, 0, 0, 0, 1, 1, 1, 1])
    hold = np.array([False, True, True, False, True, False, True, False, True])
    wet = np.array([False, False, True, False, False, False, False, False, True])
    i2, j2 = merged_wet_holds(i, j, srun, hold, wet)
    # run 0: the group 1-2 (one wet) merges into 3 (1 -> 4); the dry hold 4 stays;
    # run 1: the dry hold 6 stays; the wet hold 8 at the run's end merges into 7 (7 -> 9)
    np.testing.assert_array_equal(i2, [0, 1, 4, 5, 6, 7])
    np.testing.assert_array_equal(j2, [1, 4, 5, 6, 7, 9])
    assert merged_wet_holds(i, j, srun, hold, np.zeros(9, bool)) is None


def test_a_first_point_near_the_lead_merges_too():
    """A run's first segment that leaves rest and ends a micrometre or two off the lead (not a hold)
    merges forward where ``near`` says so; without ``near`` it stays."""
    from ffcomp.gcode.holds import merged_rest_holds

    i = np.arange(4)
    j = i + 1
    srun = np.array([0, 0, 1, 1])
    first = np.r_[True, False, True, False]
    hold = np.zeros(4, bool)
    leaves = np.r_[False, False, True, True]
    near = np.r_[True, False, True, False]
    assert merged_rest_holds(i, j, srun, first, hold, leaves, np.zeros(4, bool)) is None
    i2, j2 = merged_rest_holds(i, j, srun, first, hold, leaves, np.zeros(4, bool), near=near)
    np.testing.assert_array_equal(i2, [0, 1, 2])  # run 0 does not leave rest: its near point stays
    np.testing.assert_array_equal(j2, [1, 2, 4])

"""The pin repair: the command equals the plan where a G-code file cannot move it, and the repair
costs less than cutting the command there (checked on the LTI model it solves against, and on the
simulator through the written G-code)."""

import numpy as np
import pytest

from ffcomp.compensate.pin_repair import XY_SHARE, PulseResponses, RepairConfig, pinned_clusters, repair_window
from ffcomp.kinematics import jacobian
from ffcomp.model.lpv import LpvModel
from ffcomp.pipeline.pin_stream import PinStats, pin_repaired
from ffcomp.profile import default_profile

DT = 1e-3


@pytest.fixture(scope="module")
def model():
    return LpvModel.from_profile(default_profile())


def test_pinned_clusters_merge_close_runs():
    pin = np.zeros(100, bool)
    pin[10:20] = pin[25:30] = pin[70:80] = True
    assert pinned_clusters(pin, 10) == [(10, 30), (70, 80)]
    assert pinned_clusters(pin, 3) == [(10, 20), (25, 30), (70, 80)]
    assert pinned_clusters(np.zeros(5, bool), 3) == []


def _response(H, u):
    return np.stack([sum(np.convolve(H[:, i, j], u[:, j]) for j in range(3)) for i in range(3)], 1)


def _hold_window(model, n: int = 200):
    """A smooth 20 um correction (centred at 0.1 s) through a hold pinned on samples 95-129, at the
    bed centre: the pulse responses, plan, command, pins and Jacobian."""
    H = PulseResponses(model, DT).at(np.array([0.0, 0.0, 0.01]))
    t = np.arange(n) * DT
    q = np.zeros((n, 3)) + 0.25
    c = q + 20e-6 * np.exp(-((t - 0.1) / 0.01) ** 2)[:, None] * np.array([1.0, -0.5, -0.5])
    pin = np.zeros(n, bool)
    pin[95:130] = True
    return H, q, c, pin, jacobian(model.geometry, np.array([0.0, 0.0, 0.01]))


def test_repair_holds_the_pins_and_beats_a_cut(model):
    """A smooth correction that runs through a hold: cut at the hold it rings; repaired, the pins hold
    exactly, nothing changes outside the window, and the model's response to the change is several
    times smaller than the cut's."""
    H, q, c, pin, J = _hold_window(model)
    out = repair_window(H, c, q, pin, J, DT, RepairConfig())
    assert np.array_equal(out[pin], q[pin])
    cut = np.where(pin[:, None], q, c)
    e_cut = np.linalg.norm(_response(H, cut - c))
    e_rep = np.linalg.norm(_response(H, out - c))
    assert e_rep < 0.5 * e_cut
    # a pin that already holds needs no change
    same = repair_window(H, q.copy(), q, pin, J, DT)
    assert np.allclose(same, q, atol=1e-12)


def test_printed_samples_weigh_more_in_the_repair(model):
    """The repair of a correction cut by a hold, with the samples before the hold printing: weighted
    ``print_weight`` times there, the model's response on the printed samples (what marks the part)
    falls, the response elsewhere (the hold and after it) rises, and the pins still hold.  Weight 1
    is the unweighted repair, to the last bit."""
    n = 200
    H, q, c, pin, J = _hold_window(model, n)
    printing = np.zeros(n, bool)
    printing[:95] = True

    def errors(cfg, pr):
        out = repair_window(H, c, q, pin, J, DT, cfg, printing=pr)
        assert np.array_equal(out[pin], q[pin])
        e = np.linalg.norm(_response(H, out - c), axis=1)
        return out, float(np.sqrt(np.mean(e[:95] ** 2))), float(np.sqrt(np.mean(e[95:n] ** 2)))

    plain, p0, r0 = errors(RepairConfig(), None)
    same, _, _ = errors(RepairConfig(print_weight=1.0), printing)
    np.testing.assert_array_equal(same, plain)
    _, p3, r3 = errors(RepairConfig(print_weight=3.0), printing)
    assert p3 < 0.7 * p0 and r3 > r0


def test_the_print_weight_keeps_the_nozzle_out_of_the_line_before_a_lift(tmp_path):
    """A 20 mm square printed in three layers on other_delta, each layer change a lift straight after
    the printed line (no retraction) and pinned to the plan: unweighted, the repair reshaped the
    line's end to shorten the lift's lag, and on the held-out truth plant the nozzle dipped below the
    line before each lift.  With the printed samples counting twice (the default) it stays within a
    few um there, and the printed samples' z error falls overall.  (The window ends 3 ms before the
    line does: there the nozzle answers the lift itself, 40-60 um down with either weight, the drive's
    right-half-plane zero.  Until the thirty-fifth round ``simulate --compare`` put the reference
    2.3 ms early, on the output's command rather than its nozzle, and this window read -29 um
    unweighted and -10.7 um weighted over its last 15 ms.)"""
    import dataclasses
    from pathlib import Path

    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
    from ffcomp.pipeline.sim_flow import simulate_gcode
    from ffcomp.profile import load_profile

    root = Path(__file__).resolve().parents[1] / "samples" / "profiles"
    lines = ["G90", "M83", "G28", "G1 X10 Y10 Z0.3 F6000", "M204 S3000"]
    for layer in range(3):
        lines += [f"G1 X{x} Y{y} E0.8 F3600" for x, y in ((-10, 10), (-10, -10), (10, -10), (10, 10))]
        lines.append(f"G1 Z{0.3 * (layer + 2):.1f} F12000")
    src = tmp_path / "sq.gcode"
    src.write_text("\n".join(lines) + "\n")
    truth = load_profile(root / "other_delta_truth.toml")

    def dips(weight: float) -> tuple[float, float]:
        out = tmp_path / f"o{weight}.gcode"
        opts = dataclasses.replace(CompensateOptions(predict=False), repair=RepairConfig(print_weight=weight))
        compensate_file(str(src), str(out), load_profile(root / "other_delta.toml"), opts)
        rep = simulate_gcode(truth, str(src), compare=str(out))
        dz = rep.runs[-1].err_lag_m[:, 2]
        e = rep.reference.e_mm[:len(dz)]
        printing = np.r_[np.diff(e) > 1e-9, False]
        ends = np.nonzero(printing[:-1] & ~printing[1:])[0]
        assert len(ends) == 3
        return (min(float(dz[k - 15:k - 2].min()) for k in ends), float(np.sqrt(np.mean(dz[printing] ** 2))))

    dip1, rms1 = dips(1.0)
    dip2, rms2 = dips(RepairConfig().print_weight)
    assert dip1 < -15e-6  # the case: -21 um
    assert dip2 > -8e-6 and rms2 < 0.85 * rms1  # -2.7 um; 4.99 -> 3.99 um RMS


def test_stream_keeps_chunks_and_order(model):
    """Chunks come out with their lengths and order; repaired rows equal an all-at-once repair."""
    rng = np.random.default_rng(1)
    n = 2500
    q = np.cumsum(rng.normal(size=(n, 3)) * 1e-6, 0) + 0.2
    c = q + np.cumsum(rng.normal(size=(n, 3)) * 2e-7, 0)
    pin = np.zeros(n, bool)
    pin[600:640] = pin[655:700] = pin[2400:2450] = True
    xyz = np.zeros((n, 3))
    xyz[:, 2] = 0.01
    sizes = [137, 400, 1, 900, 1062]

    def chunks():
        a = 0
        for s in sizes:
            yield c[a:a + s], {"q": q[a:a + s], "xyz": xyz[a:a + s], "k": np.arange(a, a + s)}
            a += s

    st = PinStats()
    outs = list(pin_repaired(chunks(), lambda meta: pin[meta["k"]], model, DT, stats=st))
    assert [len(o[0]) for o in outs] == sizes
    k = np.concatenate([o[1]["k"] for o in outs])
    got = np.concatenate([o[0] for o in outs])
    assert np.array_equal(k, np.arange(n))
    assert np.array_equal(got[pin], q[pin])
    assert st.windows == 2 and st.pinned_samples == int(pin.sum())
    # far from every pin nothing changes
    M = int(round(RepairConfig().margin_s / DT))
    far = np.ones(n, bool)
    for a, b in ((600, 700), (2400, 2450)):
        far[max(a - M, 0):b + M] = False
    assert np.array_equal(got[far], c[far])


@pytest.mark.parametrize("pname", ["default", "other_delta"])
def test_gcode_with_pins_tracks_better_than_catch_ups(tmp_path, pname):
    """Layers with retractions and z-hops, judged on the simulator through the re-planned G-code: the
    nozzle stands on the plan's rest point when each retraction starts, and the tracking error is
    well below the catch-up writer's (on the benchmark: 0.48 -> 0.33 and 0.37 -> 0.29)."""
    import sys
    from pathlib import Path

    from ffcomp.pipeline.compensate_flow import CompensateOptions
    from ffcomp.pipeline.output_check import check_gcode_output
    from ffcomp.profile import load_profile

    root = Path(__file__).resolve().parents[1]
    sys.path.insert(0, str(root / "samples"))
    import make_samples as ms

    prof, truth = default_profile(), None
    if pname == "other_delta":
        prof = load_profile(root / "samples/profiles/other_delta.toml")
        truth = load_profile(root / "samples/profiles/other_delta_truth.toml")
    text = "\n".join(["G90", "M82", "G92 E0"] + ms.ACCEL_10K + ms.stress_square(0, 0, layers=2, laps=1).lines) + "\n"
    src = tmp_path / "in.gcode"
    src.write_text(text)
    ratio = {}
    for pin in (True, False):
        out = tmp_path / f"out_{pin}.gcode"
        c = check_gcode_output(prof, src, out, plant_profile=truth,
                               opts=CompensateOptions(predict=False, pin_repair=pin, self_check_drift_ms=1e9))
        ratio[pin] = c.gcode.lag.rms_norm_um / c.none.lag.rms_norm_um
        if pin:
            assert c.summary.pinned_samples > 0 and c.summary.pin_windows > 0
            assert abs(c.summary.self_check_drift_ms) < 0.2
            lines = out.read_text().splitlines()
            rest = [ln for i, ln in enumerate(lines[1:], 1)
                    if ln.startswith("G1 E-0.8") and lines[i - 1].startswith("G1 X")]
            assert rest, "a retraction right after a segment"
            for i, ln in enumerate(lines[1:], 1):
                if ln.startswith("G1 E-0.8") and lines[i - 1].startswith("G1 X"):
                    x, y = (float(w[1:]) for w in lines[i - 1].split()[1:3])
                    assert abs(x + 30) < 2e-4 and abs(y + 30) < 2e-4, lines[i - 1]  # the square's corner
    assert ratio[True] < 0.85 * ratio[False], ratio


@pytest.mark.parametrize("cut", [30, 38, 45, 55, 70])
def test_plan_blend_runs_on_across_chunk_boundaries(cut):
    """The plan's share blends in and out around a masked move whatever the chunking: split into two
    chunks (the second seeing the first's state, the first told how far ahead the next masked
    sample lies) the weights equal the whole array's.  (Cut at a chunk boundary, a z move's settling
    blend jumped 26 um in one sample: 1.0 ms late on cylinder_prusa, other_delta.)"""
    from ffcomp.gcode.chain_plan import ChainLimits
    from ffcomp.pipeline.limited_moves import LimitBound

    m = np.zeros(100, bool)
    m[40:50] = True
    whole = LimitBound._blend(m, 24)
    lb = LimitBound(ChainLimits(default_profile(), 10000.0, 5.0))
    on = np.nonzero(m[cut:])[0]
    ahead = int(on[0]) if on.size and not m[:cut].any() and on[0] < 24 else None
    a = lb._blend_on(m[:cut], 24, "z", ahead)
    b = lb._blend_on(m[cut:], 24, "z", None)
    np.testing.assert_allclose(np.r_[a, b], whole, atol=1e-15)
    assert np.max(np.abs(np.diff(whole))) < 0.07  # a blend, not a step


def test_frame_solution_equals_the_joint_one_when_every_component_is_pinned(profile):
    """The nozzle-frame least squares (per-component pins) spans the same corrections as the joint
    one when all three components share the pins (``Delta = J^-1 delta`` maps the knot spaces onto
    each other), so both give the same command."""
    from ffcomp.compensate.pin_repair import (
        PulseResponses,
        RepairConfig,
        _frame_operator,
        _repair_frames,
        repair_window,
    )
    from ffcomp.kinematics import inverse, jacobian
    from ffcomp.model.lpv import LpvModel

    model = LpvModel.from_profile(profile)
    dt, cfg = 1e-3, RepairConfig()
    pose = np.array([0.02, -0.01, 0.03])
    H = PulseResponses(model, dt, cfg).at(pose)
    J = jacobian(model.geometry, pose)
    n = 90
    rng = np.random.default_rng(3)
    q = inverse(model.geometry, pose) + np.cumsum(rng.normal(0, 2e-6, (n, 3)), 0)
    c = q + rng.normal(0, 5e-6, (n, 3))
    pin = np.zeros(n, bool)
    pin[35:52] = True
    joint = repair_window(H, c, q, pin, J, dt, cfg)
    pins = np.repeat(pin[:, None], 3, 1)
    frame = _repair_frames(_frame_operator(H, pins, J, dt, cfg), c, q, pins, J, cfg)
    frame[pin] = q[pin]
    assert np.max(np.abs(frame - joint)) < 1e-3 * np.max(np.abs(joint - c))


def test_z_only_pins_hold_the_nozzle_z_and_free_x_and_y(profile):
    """``zpin``: on those samples the nozzle's z (``J q``'s z row) equals the plan's and x/y move
    with the compensation (pinned whole, as before, they stay on the plan)."""
    from ffcomp.compensate.pin_repair import PulseResponses, RepairConfig, repair_window
    from ffcomp.kinematics import inverse, jacobian
    from ffcomp.model.lpv import LpvModel

    model = LpvModel.from_profile(profile)
    dt, cfg = 1e-3, RepairConfig()
    pose = np.array([0.0, 0.0, 0.03])
    H = PulseResponses(model, dt, cfg).at(pose)
    J = jacobian(model.geometry, pose)
    n = 120
    t = np.arange(n) * dt
    xyz = np.stack([0.002 * np.clip((t - 0.06) / 0.04, 0, 1) ** 2, 0 * t, 0.03 + 4e-4 * np.clip(t / 0.06, 0, 1)], 1)
    q = inverse(model.geometry, xyz)
    rng = np.random.default_rng(5)
    c = q + rng.normal(0, 1e-5, (n, 3))  # stands for the compensated command: off the plan everywhere
    pin = np.zeros(n, bool)
    pin[10:20] = True  # a retraction
    zpin = np.zeros(n, bool)
    zpin[20:60] = True  # the z-hop after it
    out = repair_window(H, c, q, pin, J, dt, cfg, zpin=zpin)
    assert np.array_equal(out[pin], q[pin])
    dz = (out - q) @ J[2]
    assert np.max(np.abs(dz[zpin])) < 1e-9
    dxy = (out - q) @ J[:2].T
    assert np.max(np.abs(dxy[zpin])) > 1e-6  # x and y keep a correction
    full = repair_window(H, c, q, pin | zpin, J, dt, cfg)
    assert np.max(np.abs((full - q)[zpin])) < 1e-12  # (the whole command pinned, as before)


def test_a_lifts_x_and_y_correction_runs_straight(profile):
    """``lift_xy_accel_factor``: where only the nozzle's z is pinned (a lift), the x/y correction's
    acceleration is penalised that much harder, so the lift's segments keep their direction (Klipper
    slows the short segments of a lift at ``max_z_accel`` wherever they turn: on the fidelity bench's
    z-hop file, with the factor 1, 2.8 ms late); the correction stays, as a nearly straight ramp."""
    from dataclasses import replace

    from ffcomp.compensate.pin_repair import PulseResponses, RepairConfig, repair_window
    from ffcomp.kinematics import inverse, jacobian
    from ffcomp.model.lpv import LpvModel

    model = LpvModel.from_profile(profile)
    dt = 1e-3
    pose = np.array([0.0, 0.0, 0.03])
    H = PulseResponses(model, dt, RepairConfig()).at(pose)
    J = jacobian(model.geometry, pose)
    n = 120
    t = np.arange(n) * dt
    xyz = np.stack([0.002 * np.clip((t - 0.06) / 0.04, 0, 1) ** 2, 0 * t, 0.03 + 4e-4 * np.clip(t / 0.06, 0, 1)], 1)
    q = inverse(model.geometry, xyz)
    c = q + np.random.default_rng(5).normal(0, 1e-5, (n, 3))
    pin = np.zeros(n, bool)
    pin[10:20] = True
    zpin = np.zeros(n, bool)
    zpin[20:60] = True
    curv, ramp = {}, {}
    for f in (1.0, 100.0):
        cfg = replace(RepairConfig(), lift_xy_accel_factor=f)
        dxy = (repair_window(H, c, q, pin, J, dt, cfg, zpin=zpin) - c) @ J[:2].T  # the correction's x, y
        curv[f] = float(np.max(np.abs(np.diff(dxy[20:60], 2, axis=0))))
        ramp[f] = float(np.max(np.abs(dxy[59] - dxy[20])))
    assert curv[100.0] < 0.05 * curv[1.0], curv
    assert ramp[100.0] > 1e-6, ramp  # (x and y still move during the lift)


def test_lead_into_marks_the_end_of_a_travel_into_a_chosen_move():
    """``lead_into``: the samples within ``span_s`` of the end of a travel (no extrusion) whose next
    move the predicate picks (``z_span_s`` for a travel steeper than 45 degrees); none of an
    extruding move's unless ``printed_s`` (its own span) is given, none with ``span_s = 0``."""
    from ffcomp.gcode.moves import PlannedMove
    from ffcomp.pipeline.limited_moves import lead_into

    def mv(i, t0, dur, e=0.0, z1=1.0):
        return PlannedMove(i, i + 1, "move", t0, (0.0, 0.0, 1.0, 0.0), (1.0, 0.0, z1, e), 1.0, (1.0, 0.0, 0.0, 0.0),
                           0.0, 10.0, 0.0, 1000.0, dur / 2, 0.0, dur / 2)

    moves = {0: mv(0, 0.0, 0.010), 1: mv(1, 0.010, 0.010, z1=0.6), 2: mv(2, 0.020, 0.010, e=0.5),
             3: mv(3, 0.030, 0.010, z1=0.6)}
    t = np.arange(0, 40) * 1e-3
    idx = np.arange(40) // 10
    pick = lambda m: m.end_mm[2] != m.start_mm[2]  # noqa: E731  (the z moves: 1 and 3)
    hit = lead_into(idx, moves, t, 0.0025, pick)
    # move 0 (a travel into z move 1): its samples at 8 and 9 ms; move 2 extrudes: none of it
    assert np.nonzero(hit)[0].tolist() == [8, 9]
    assert not lead_into(idx, moves, t, 0.0, pick).any()
    # a printed line (move 2, into z move 3) has its own span: 1.5 ms (its sample at 29 ms)
    both = lead_into(idx, moves, t, 0.0025, pick, printed_s=0.0015)
    assert np.nonzero(both)[0].tolist() == [8, 9, 29]
    assert np.nonzero(lead_into(idx, moves, t, 0.0, pick, printed_s=0.0015))[0].tolist() == [29]
    # but not into a z move that extrudes (the extruder's junction rule governs that corner); a
    # travel still leads into one
    wet = dict(moves)
    wet[1] = mv(1, 0.010, 0.010, z1=0.6, e=0.3)
    wet[3] = mv(3, 0.030, 0.010, z1=0.6, e=0.3)
    assert np.nonzero(lead_into(idx, wet, t, 0.0025, pick, printed_s=0.0015))[0].tolist() == [8, 9]
    # a travel that moves more in z than in XY (move 0 rising 2 mm over 1 mm) takes z_span_s
    steep = dict(moves)
    steep[0] = mv(0, 0.0, 0.010, z1=3.0)
    assert np.nonzero(lead_into(idx, steep, t, 0.0025, pick, z_span_s=0.0015))[0].tolist() == [9]
    assert np.nonzero(lead_into(idx, steep, t, 0.0025, pick))[0].tolist() == [8, 9]
    assert np.nonzero(lead_into(idx, moves, t, 0.0025, pick, z_span_s=0.0015))[0].tolist() == [8, 9]  # (flat)


def test_the_repair_keeps_the_nozzle_z_acceleration_within_the_firmware_limit(model):
    """Next to a pinned z move the repair's soft penalty let the command dip and rise in z faster
    than ``max_z_accel`` allows (the firmware then ran late).  With ``z_limit_m_s2`` the repaired
    command's nozzle z acceleration (``J`` z row times its second difference) stays within the
    limit, or within what the command had there before the repair, on every free sample; the pins
    still hold; a limit that does not bind changes nothing; the model's response to the change
    grows (the price of the limit) but stays well below a plain cut's."""
    pose = np.array([0.0, 0.0, 0.01])
    H = PulseResponses(model, DT).at(pose)
    J = jacobian(model.geometry, pose)
    n = 200
    t = np.arange(n) * DT
    q = np.zeros((n, 3)) + 0.25
    # a common-mode (z) pre-actuation the pins cut off
    c = q + 30e-6 * np.exp(-((t - 0.1) / 0.006) ** 2)[:, None] * np.ones(3)
    pin = np.zeros(n, bool)
    pin[100:140] = True

    def z_acc(x):
        return (np.diff(x, 2, axis=0) @ J[2]) / DT**2  # samples 1 .. n-2

    free = ~pin[1:-1]
    cfg = RepairConfig()
    loose = repair_window(H, c, q, pin, J, DT, cfg)
    peak = float(np.max(np.abs(z_acc(loose)[free])))
    own = np.abs(z_acc(c))
    limit = 0.4 * peak
    assert limit > float(np.max(own[free])) * 0.5  # the limit binds on the repair, not on c itself
    tight = repair_window(H, c, q, pin, J, DT, cfg, z_limit_m_s2=limit)
    assert np.array_equal(tight[pin], q[pin])
    a = np.abs(z_acc(tight))[free]
    assert np.all(a <= np.maximum(limit, own[free] * 1.0001) * (1 + 1e-6))
    assert not np.allclose(tight, loose)
    np.testing.assert_allclose(repair_window(H, c, q, pin, J, DT, cfg, z_limit_m_s2=10 * peak), loose, atol=1e-15)
    e = {k: np.linalg.norm(_response(H, x - c)) for k, x in
         (("loose", loose), ("tight", tight), ("cut", np.where(pin[:, None], q, c)))}
    assert e["loose"] <= e["tight"] < 0.6 * e["cut"]


def test_the_repair_keeps_a_steep_moves_turns_within_the_firmware_limit(model):
    """On a steep move (the nozzle descending at 100 mm/s) the repair of an x/y correction cut by
    pins bent the command sideways harder than Klipper's centripetal junction rule allows there
    (``max_z_accel / |u_z|``: a random file's descent after homing ran 0.55 ms late, 62 um off the
    clock).  With ``z_limit_m_s2`` the repaired command's nozzle x and y accelerations on the free
    samples and the pinned ones next to them (the turn into a pinned lift: a layer change on
    ``cube_prusa.gcode``, other_delta, ran 0.5 ms off the clock there) stay within ``1/sqrt(2)`` of the
    limit over ``|u_z|`` (or what the command had there before), the pins hold, and a limit that does
    not bind changes nothing."""
    pose = np.array([0.0, 0.0, 0.01])
    H = PulseResponses(model, DT).at(pose)
    J = jacobian(model.geometry, pose)
    n = 200
    t = np.arange(n) * DT
    q = 0.25 - 0.1 * t[:, None] * np.ones(3)  # the three carriages down together: z at ~100 mm/s
    c = q + 20e-6 * np.exp(-((t - 0.095) / 0.006) ** 2)[:, None] * np.array([1.0, -0.5, -0.5])
    pin = np.zeros(n, bool)
    pin[100:140] = True
    free = ~pin[1:-1]

    def acc(x, k):
        return (np.diff(x, 2, axis=0) @ J[k]) / DT**2

    # the rows: the free samples and the pinned ones next to them (their second difference moves
    # with the free knots: the turn into a pinned move)
    rows = free | ~pin[:-2] | ~pin[2:]
    assert (rows & ~free).sum() == 2
    cfg = RepairConfig()
    loose = repair_window(H, c, q, pin, J, DT, cfg)
    peak = max(float(np.max(np.abs(acc(loose, k)[free]))) for k in (0, 1))
    limit = 0.3 * peak
    tight = repair_window(H, c, q, pin, J, DT, cfg, z_limit_m_s2=limit)
    assert np.array_equal(tight[pin], q[pin])
    v = np.gradient(tight, axis=0) @ J.T / DT
    cap = XY_SHARE * limit * np.linalg.norm(v, axis=1)[1:-1] / np.abs(v[1:-1, 2])
    for k in (0, 1):
        own = np.abs(acc(c, k))
        assert np.all(np.abs(acc(tight, k))[rows] <= np.maximum(cap, own * 1.0001)[rows] * 1.05)
    assert float(np.max(np.abs(acc(loose, 0)[free]) - np.maximum(cap, np.abs(acc(c, 0)))[free])) > 0  # the case
    edge = rows & ~free
    assert float(np.max(np.abs(acc(loose, 0)[edge]) - np.maximum(cap, np.abs(acc(c, 0)))[edge])) > 0  # and there
    np.testing.assert_allclose(repair_window(H, c, q, pin, J, DT, cfg, z_limit_m_s2=10 * peak), loose, atol=1e-15)


def test_the_plan_standing_still_next_to_a_steep_pin_is_pinned_too():
    """``pin_stream._still_near``: the samples where the plan stands still that adjoin a seed
    through standing samples only, at most ``reach`` away; never across a moving sample."""
    from ffcomp.pipeline.pin_stream import _still_near

    q = np.zeros((30, 3))
    q[:3] = np.arange(3)[:, None] * 1e-3 - 3e-3  # moving up to sample 3, standing on 3 .. 19
    q[20:] = np.arange(1, 11)[:, None] * 1e-3  # moving again from sample 20 on
    seed = np.zeros(30, bool)
    seed[12:15] = True
    got = _still_near(seed, q, 5)
    # (a sample stands still where the plan holds its position on both sides: 4 .. 18)
    assert np.nonzero(got)[0].tolist() == [7, 8, 9, 10, 11, 15, 16, 17, 18]
    got = _still_near(seed, q, 50)
    assert np.nonzero(got)[0].tolist() == list(range(4, 12)) + list(range(15, 19))
    assert not _still_near(np.zeros(30, bool), q, 50).any()


def test_the_plans_ramp_at_max_z_accel_after_a_pin_is_pinned_too():
    """``pin_stream._ramp_near``: the steep samples after a pinned run where the plan's nozzle z
    accelerates at ``max_z_accel`` (from 95 % of it), through such samples only, at most ``reach``
    of them; never before the run, nor across a sample below the limit or of a move it does not bind."""
    from ffcomp.pipeline.pin_stream import _ramp_near

    dt, lim = 1e-3, 3.0
    n = 60
    acc = np.zeros(n)
    acc[5:15] = -lim  # the plan brakes into the pinned run at the limit...
    acc[20:35] = lim  # ...and ramps away from it: 20 .. 34, then cruises
    acc[40:45] = 0.96 * lim  # a later ramp, not adjoining
    v = np.cumsum(acc) * dt
    z = np.cumsum(v) * dt
    z = np.r_[0.0, z[:-1]]  # (the second difference at sample k is then acc[k] dt^2)
    a2 = np.r_[0.0, np.diff(z, 2) / dt**2, 0.0]
    np.testing.assert_allclose(a2[1:-1], acc[1:-1], atol=1e-9)
    seed = np.zeros(n, bool)
    seed[10:20] = True  # the pinned run: 10 .. 19
    steep = np.ones(n, bool)
    got = _ramp_near(seed, steep, z, dt, lim, 40)
    assert np.nonzero(got)[0].tolist() == list(range(20, 35))  # after the run only, up to the cruise
    assert np.nonzero(_ramp_near(seed, steep, z, dt, lim, 5))[0].tolist() == list(range(20, 25))
    steep[30:] = False  # a move max_z_accel does not bind from sample 30 on
    assert np.nonzero(_ramp_near(seed, steep, z, dt, lim, 40))[0].tolist() == list(range(20, 30))
    assert not _ramp_near(seed, steep, z, dt, 10 * lim, 40).any()  # a ramp under the limit
    assert not _ramp_near(np.zeros(n, bool), np.ones(n, bool), z, dt, lim, 40).any()


def test_a_pinned_lift_after_homing_starts_from_a_command_standing_still(tmp_path):
    """A slicer's start (G28, the lift, a retraction, the move to the first layer): the lift is
    pinned (it runs into the retraction); the free command before it pre-actuated it, and the
    repair turned that into a dip and rise of the nozzle by 13 um in a few milliseconds at the top
    of the tower, which the firmware ran 0.21 ms late (cube_cura.gcode, default profile).  The
    plan's standing samples next to the pinned lift are pinned too (``RepairConfig.still_near_steep``).
    (On the source's own plan: with the quiet z moves the lift, which runs into the retraction, is
    planned quiet and the case does not arise.)"""
    from ffcomp.compensate.pin_repair import RepairConfig as RC
    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file

    src = tmp_path / "start.gcode"
    src.write_text("G90\nM83\nG28\nG1 Z5 F5000\nG1 E-0.8 F2100\nG1 Z0.5 F600\nG0 X9 Y-15 F6000\nG1 Z0.3 F600\n"
                   "G1 E0.8 F2100\nG1 X15 Y-9 E0.4 F1800\nG1 X15 Y9 E1\n")

    def drift_ms(on: bool) -> float:
        s = compensate_file(str(src), str(tmp_path / "o.gcode"), default_profile(),
                            CompensateOptions(predict=False, repair=RC(still_near_steep=on), self_check_drift_ms=1e9,
                                              self_check_tol_um=1e9, quiet_z=False))
        return s.self_check_drift_ms

    assert abs(drift_ms(True)) < 0.1  # +0.013 ms
    assert abs(drift_ms(False)) > 0.12  # the case: +0.214 ms (-0.142 since the feed solve's hinge)


def test_standing_pins_never_reach_a_repaired_cluster(model):
    """Two steep pinned runs with the plan standing still between them, the second arriving after
    the first was repaired: the standing samples pinned next to the second
    (``RepairConfig.still_near_steep``, up to 80 of them) stop short of the first one's window.
    Grown into it, the two would merge into a cluster that starts before the repaired one's end,
    which the stream skips as done, and the second run's pins would not hold (this test fails
    without that guard in ``pin_stream``)."""
    n = 600
    q = np.zeros((n, 3)) + 0.2  # the plan stands still throughout ...
    q[:60] += np.linspace(-1e-3, 0, 60)[:, None]  # ... after a first move
    c = q + 20e-6 * np.sin(np.arange(n) * 0.05)[:, None] * np.array([1.0, -0.5, -0.5])
    pin = np.zeros(n, bool)
    pin[100:140] = pin[290:330] = True
    xyz = np.zeros((n, 3))
    xyz[:, 2] = 0.01
    sizes = [200, 80, 60, 60, 60, 60, 60, 20]  # the first run is repaired, and still held, when the second comes

    def chunks():
        a = 0
        for s in sizes:
            yield c[a:a + s], {"q": q[a:a + s], "xyz": xyz[a:a + s], "k": np.arange(a, a + s)}
            a += s

    outs = list(pin_repaired(chunks(), lambda meta: pin[meta["k"]], model, DT, steep_fn=lambda meta: pin[meta["k"]]))
    got = np.concatenate([o[0] for o in outs])
    assert np.array_equal(got[pin], q[pin])


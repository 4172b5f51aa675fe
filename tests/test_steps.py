"""Step streams: streamed writing equals whole-array writing; the streamed read-back check equals
the in-memory reconstruction; compression stays within its tick bound."""

import io

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from ffcomp.steps import (
    STEPPERS,
    FfstepsWriter,
    SampleFile,
    compress_steps,
    expand_queue,
    ffsteps_max_error,
    positions_from_steps,
    read_ffsteps,
    read_plain,
    step_events,
    write_ffsteps,
    write_plain,
    write_plain_header,
    write_plain_rows,
)

SPM = 80.0
DT = 1e-3


def _commands(seed: int, n: int = 3000) -> np.ndarray:
    """Three smooth carriage paths (m) with direction changes and pauses."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    q = np.column_stack([0.1 + 0.004 * np.sin(2 * np.pi * f * t + p)
                         for f, p in zip(rng.uniform(0.5, 3, 3), rng.uniform(0, 6, 3))])
    q[n // 3: n // 3 + 200] = q[n // 3]  # a pause
    return q


def _chunked_events(q: np.ndarray, cuts: list[int]):
    """Step events of ``q`` computed chunk by chunk, as the steps flow does (one sample of overlap)."""
    n0, out = None, []
    for a, b in zip([0] + cuts, cuts + [len(q)]):
        block = q[max(a - 1, 0):b]
        ev, starts = {}, []
        for i, name in enumerate(STEPPERS):
            t, d, s0 = step_events(block[:, i], max(a - 1, 0) * DT, DT, SPM,
                                   None if n0 is None else int(np.rint(block[0, i] * 1e3 * SPM)))
            ev[name] = (t, d)
            starts.append(s0)
        n0 = n0 or tuple(starts)
        out.append(ev)
    return n0, out


@settings(max_examples=12, deadline=None)
@given(st.integers(0, 2**31 - 1), st.lists(st.integers(1, 2999), min_size=0, max_size=6, unique=True))
def test_streamed_ffsteps_equal_whole_array_writing(tmp_path_factory, seed, cuts):
    q = _commands(seed)
    cuts = sorted(cuts)
    n0, chunks = _chunked_events(q, cuts)
    whole = {n: (np.concatenate([c[n][0] for c in chunks]), np.concatenate([c[n][1] for c in chunks]))
             for n in STEPPERS}
    ref = io.StringIO()
    n_ref = write_ffsteps(ref, whole, SPM, n0)
    path = tmp_path_factory.mktemp("s") / "a.ffsteps"
    w = FfstepsWriter(str(path), SPM)
    w.start_steps = n0
    for c in chunks:
        for name, (t, d) in c.items():
            w.push(name, t, d)
    assert w.finish() == n_ref
    assert path.read_text() == ref.getvalue()
    assert not list(path.parent.glob("*.part"))
    # the streamed read-back check equals the in-memory reconstruction
    ts = np.arange(0, len(q), 7) * DT
    rec = positions_from_steps(read_ffsteps(str(path)), ts)
    want = float(np.max(np.abs(rec - q[::7])) * 1e3 * SPM)
    assert abs(ffsteps_max_error(str(path), q[::7], 7 * DT) - want) < 1e-9
    v_steps_s = np.max(np.abs(np.diff(q, axis=0))) / DT * 1e3 * SPM
    assert want <= 0.5 + 5e-6 * v_steps_s + 1e-9  # half a step plus the 5 us tick tolerance at speed


def test_sample_file_round_trip(tmp_path):
    rows = np.random.default_rng(1).normal(size=(1000, 3))
    f = SampleFile(str(tmp_path / "q.bin"))
    for a in range(0, 1000, 137):
        f.append(rows[a:a + 137])
    assert len(f) == 1000
    np.testing.assert_array_equal(f[250:260], rows[250:260])
    np.testing.assert_array_equal(f[0:1000], rows)
    f.close()
    assert not (tmp_path / "q.bin").exists()


def test_streamed_csv_equals_whole_file(tmp_path):
    q = _commands(3)
    n0, chunks = _chunked_events(q, [700, 1500, 2200])
    whole = {n: (np.concatenate([c[n][0] for c in chunks]), np.concatenate([c[n][1] for c in chunks]))
             for n in STEPPERS}
    a = tmp_path / "a.csv"
    write_plain(str(a), whole, SPM, n0)
    b = tmp_path / "b.csv"
    with open(b, "w") as f:
        write_plain_header(f, SPM, n0)
        for c in chunks:
            write_plain_rows(f, c)
    assert a.read_text() == b.read_text()
    s = read_plain(str(b))
    assert s.n_steps() == sum(len(v[0]) for v in whole.values())


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from([1, 5, 50]))
def test_compression_within_tick_bound(seed, max_err):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 400))
    gaps = np.abs(np.cumsum(rng.normal(0, 20, n))) + rng.uniform(50, 3000)
    ticks = (10_000 + np.cumsum(np.maximum(gaps, 1.0))).astype(np.int64)
    first = int(ticks[0]) - 100
    entries = compress_steps(ticks, max_err, first)
    assert sum(c for _, c, _ in entries) == n
    assert np.max(np.abs(expand_queue(first, entries) - ticks)) <= max_err


def test_cli_shape_steps_writes_a_quantisation_aware_stream(capsys, tmp_path):
    """`--shape-steps` reaches the step writer: more steps (the dither), reconstruction within 2 steps."""
    from cli_util import run_json

    src = tmp_path / "sq.gcode"
    src.write_text("G28\nG90\nG1 X0 Y0 Z30 F12000\nG1 X20 F6000\nG1 Y20\nG1 X0\nG1 Y0\n")
    plain = run_json(capsys, "compensate", src, "-o", tmp_path / "a.ffsteps", "--format", "steps")
    shaped = run_json(capsys, "compensate", src, "-o", tmp_path / "b.ffsteps", "--format", "steps",
                      "--shape-steps")
    assert shaped["steps"] > plain["steps"]
    assert plain["max_step_error_steps"] <= 1.0 < shaped["max_step_error_steps"] <= 2.0

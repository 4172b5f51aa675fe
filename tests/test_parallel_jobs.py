"""``--jobs N``: the file compensated in pieces on N processes (ffcomp.pipeline.parallel_flow).

* jobs=1 never enters the parallel code and writes what a run without the option writes;
* jobs=2 on a real slicer file: a valid compensated file (the same source lines in the same order,
  the self-check passing on the whole output), its print time longer by exactly the rest the cuts add;
* an error in a worker surfaces as the same error (file, line) as the serial run's, nothing written;
* a stop signal during a parallel run leaves nothing behind.
"""

from __future__ import annotations

import math
import re
import signal
import sys
from pathlib import Path

import pytest

from ffcomp.errors import FfcompError
from ffcomp.pipeline import parallel_flow
from ffcomp.pipeline.compensate_flow import CompensateOptions, Piece, compensate_file

ROOT = Path(__file__).resolve().parents[1]
CUBE = ROOT / "samples" / "gcode" / "cube_prusa.gcode"

#: lines the writer writes itself (segments, rewritten extruder-only moves, dwells, its comments)
_OWN = re.compile(r"^(G1 |G4 |; ffcomp)")


def _source_lines(path: Path) -> list[str]:
    """The output's lines that are the source's own (passed through verbatim), header and footer off."""
    lines = path.read_text(encoding="utf-8", errors="surrogateescape").splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("M83 ; ffcomp")) + 1
    return [ln for ln in lines[head:] if not _OWN.match(ln) and "; ffcomp: restore" not in ln]


@pytest.fixture(scope="module")
def runs(tmp_path_factory, profile):
    d = tmp_path_factory.mktemp("jobs")
    out = {}
    for key, opts in ((1, CompensateOptions()), (2, CompensateOptions(jobs=2)),
                      ("whole", CompensateOptions(jobs=2, self_check_whole=True))):
        o = d / f"cube_{key}.gcode"
        out[key] = (o, compensate_file(str(CUBE), str(o), profile, opts))
    return out


def test_piece_lines():
    assert parallel_flow.piece_lines(100, 1) == [Piece(None, None)]
    assert parallel_flow.piece_lines(100, 3) == [Piece(None, 33), Piece(33, 67), Piece(67, None)]


def test_jobs_1_is_the_serial_run(tmp_path, profile, monkeypatch):
    """jobs=1 takes the serial path (the parallel module is never called) and writes byte for byte
    what the default options write.  (That the serial path is byte-identical to the code before the
    option existed was checked with ``cmp`` on cube_prusa when it was added.)"""
    src = ROOT / "samples" / "gcode" / "stress_square.gcode"
    a = tmp_path / "a.gcode"
    compensate_file(str(src), str(a), profile, CompensateOptions())

    def boom(*a, **k):
        raise AssertionError("jobs=1 must not use the parallel flow")

    monkeypatch.setattr(parallel_flow, "write_body_parallel", boom)
    b = tmp_path / "b.gcode"
    compensate_file(str(src), str(b), profile, CompensateOptions(jobs=1))
    assert a.read_bytes() == b.read_bytes()


def test_jobs_2_gives_a_valid_file(runs, profile):
    (o1, s1), (o2, s2) = runs[1], runs[2]
    # the same source lines, in the same order (header/footer lines aside, which are ffcomp's)
    assert _source_lines(o1) == _source_lines(o2)
    # ... and they are the source's own lines, in the source's order
    it = iter(CUBE.read_text().splitlines())
    assert all(any(ln == x for x in it) for ln in _source_lines(o2))
    assert len(_source_lines(o2)) > 300
    # the self-check passed (it raises otherwise): each piece re-planned by its worker, and the whole
    # merged output re-planned in one piece as the printer runs it; the cut costs no lateness
    (ow, sw) = runs["whole"]
    assert ow.read_bytes() == o2.read_bytes()
    for s in (s2, sw):
        assert s.self_check_max_um is not None and s.self_check_max_um <= 50.0
        assert abs(s.self_check_drift_ms) < 1.0 and abs(s.self_check_drift_end_ms) < 1.0
    assert sw.self_check_max_um == pytest.approx(s2.self_check_max_um, rel=0.1)
    assert sw.output_print_time_s == pytest.approx(s2.output_print_time_s, abs=2e-3)
    # the piece after the cut starts with a move to the plan's rest point
    assert o2.read_text().count("; ffcomp: piece start (--jobs)") == 1
    # the cut: one piece boundary at a retraction, costing post_s + pre_s of rest, and said so
    note = next(n for n in s2.notes if n.startswith("--jobs 2"))
    m = re.search(r"(\d+) at retractions/dwells, each adding ([\d.]+) s", note)
    holds, rest = int(m[1]), float(m[2])
    assert holds == 1
    extra = s2.output_print_time_s - s1.output_print_time_s
    assert extra == pytest.approx(holds * rest, abs=0.02), extra
    # the same amount of printing: source print time, extrusion, samples held on the plan
    assert s2.print_time_s == pytest.approx(s1.print_time_s, abs=1e-9)
    assert s2.lines_in == s1.lines_in
    assert abs(s2.segments - s1.segments) < 0.01 * s1.segments
    assert s2.rms_after_um == pytest.approx(s1.rms_after_um, rel=0.02)
    assert s2.commands_passed == s1.commands_passed and s2.commands_stopped == s1.commands_stopped
    # extrusion: the relative E of the whole output equals the serial run's
    def e_total(p):
        return sum(float(x) for x in re.findall(r"^G1 [^;\n]*E(-?[\d.]+)", p.read_text(), re.M))

    assert e_total(o2) == pytest.approx(e_total(o1), abs=0.01)


def _bad_copy(tmp_path: Path, frac: float) -> tuple[Path, int]:
    """The cube with a move out of the arms' reach at ``frac`` of its lines."""
    lines = CUBE.read_text().splitlines(True)
    i = next(k for k in range(int(len(lines) * frac), len(lines)) if lines[k].startswith("G1 X"))
    lines.insert(i, "G1 X400 Y0\n")
    p = tmp_path / "bad.gcode"
    p.write_text("".join(lines))
    return p, i + 1


@pytest.mark.parametrize("frac", [0.8])
def test_worker_error_surfaces_cleanly(tmp_path, profile, frac):
    src, line = _bad_copy(tmp_path, frac)
    errs = {}
    for jobs in (1, 2):
        out = tmp_path / f"out{jobs}.gcode"
        with pytest.raises(FfcompError) as ei:
            compensate_file(str(src), str(out), profile, CompensateOptions(jobs=jobs))
        errs[jobs] = ei.value
        assert not out.exists()
    assert type(errs[2]) is type(errs[1])
    assert str(errs[2]) == str(errs[1])
    assert f":{line}" in str(errs[2])
    assert [n for n in __import__("os").listdir(tmp_path) if n.startswith(".ffcomp-")] == []


def _long_with_retractions(path: Path, n_moves: int = 20000) -> Path:
    lines = [";FLAVOR:Klipper", "G28", "G90", "M83", "G1 Z0.3 F3000", "G1 X50 Y0 F6000"]
    x0, y0 = 50.0, 0.0
    for i in range(1, n_moves + 1):
        a = 2 * math.pi * i / 48
        x, y = 50 * math.cos(a), 50 * math.sin(a)
        lines.append(f"G1 X{x:.3f} Y{y:.3f} E{math.hypot(x - x0, y - y0) * 0.033:.5f}")
        x0, y0 = x, y
        if i % 480 == 0:
            lines += ["G1 E-0.8 F2100", f"G1 Z{0.3 + 0.2 * i / 480:.2f}", "G1 E0.8 F2100"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_signal_during_parallel_run_leaves_nothing(tmp_path):
    from test_safe_exits import _digest, _leftovers, _start_and_signal

    src = _long_with_retractions(tmp_path / "in.gcode")
    old = tmp_path / "out.gcode"
    old.write_text("; an old output that must survive\n")
    before = {p: _digest(p) for p in (src, old)}
    cmd = [sys.executable, "-m", "ffcomp", "compensate", str(src), "-o", str(old), "--jobs", "2"]
    rc, err, seen = _start_and_signal(cmd, signal.SIGTERM, tmp_path, "ffcomp: compensating")
    assert seen
    assert rc == 128 + signal.SIGTERM, err
    assert "Traceback" not in err
    assert {p: _digest(p) for p in (src, old)} == before
    assert _leftovers(tmp_path) == []


def _squares_with_m400(path: Path) -> Path:
    """Squares without retractions, an M400 halfway: the only place the toolhead stands still."""
    lines = [";FLAVOR:Klipper", "G28", "G90", "M83", "G1 Z0.3 F3000", "G1 X-20 Y-20 F6000"]
    for i in range(40):
        lines += ["G1 X20 Y-20 E1", "G1 X20 Y20 E1", "G1 X-20 Y20 E1", "G1 X-20 Y-20 E1"]
        if i == 19:
            lines.append("M400")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("name", ["stress_square", "arcs", "stress_circle64", "m400"])
def test_small_files_cut_at_holds_stops_and_homings(tmp_path, profile, name):
    """Cuts at a retraction, at a stop (m400: no cost), and pieces with a homing between them
    (stress_square's second piece starts after the G28 that ends the first): valid outputs, both
    self-checks pass, the print time longer by the rest the cuts add."""
    src = (ROOT / "samples" / "gcode" / f"{name}.gcode" if name != "m400"
           else _squares_with_m400(tmp_path / "m400.gcode"))
    o1, o2, ow = (tmp_path / f"{k}.gcode" for k in ("1", "2", "w"))
    s1 = compensate_file(str(src), str(o1), profile, CompensateOptions())
    s2 = compensate_file(str(src), str(o2), profile, CompensateOptions(jobs=2))
    sw = compensate_file(str(src), str(ow), profile, CompensateOptions(jobs=2, self_check_whole=True))
    assert _source_lines(o1) == _source_lines(o2)
    assert len(s2.pieces) == 2 and s2.pieces[0]["cut"] in ("hold", "stop")
    if name == "m400":
        assert s2.pieces[0]["cut"] == "stop"
    rest = 0.35 if s2.pieces[0]["cut"] == "hold" else 0.0
    for s in (s2, sw):
        assert abs(s.self_check_drift_ms) < 2.0
        assert s.output_print_time_s - s1.output_print_time_s == pytest.approx(rest, abs=0.02)


def test_hook_takes_jobs(tmp_path):
    """The slicer hook (in place) with ``--jobs 2``: the same source lines as the serial hook, cut in
    two pieces, exit 0; ``--jobs -1`` is refused and leaves the file untouched."""
    import subprocess

    src = ROOT / "samples" / "gcode" / "stress_square.gcode"
    a, b, c = (tmp_path / f"{k}.gcode" for k in ("a", "b", "c"))
    for p in (a, b, c):
        p.write_bytes(src.read_bytes())
    base = [sys.executable, "-m", "ffcomp", "hook"]
    r1 = subprocess.run(base + [str(a)], capture_output=True, text=True)
    r2 = subprocess.run(base + [str(b), "--jobs", "2"], capture_output=True, text=True)
    assert r1.returncode == 0 and r2.returncode == 0, r2.stderr
    assert "ffcomp: compensated" in r2.stderr
    assert _source_lines(a) == _source_lines(b)
    assert b.read_bytes() != src.read_bytes()
    r3 = subprocess.run(base + [str(c), "--jobs", "-1"], capture_output=True, text=True)
    assert r3.returncode != 0 and "--jobs" in r3.stderr
    assert c.read_bytes() == src.read_bytes()

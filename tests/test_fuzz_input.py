"""Any byte sequence in, no traceback out (issue 12 item 7): hypothesis over raw bytes and G-code words.

The parser and planner run on many examples (fast); the whole CLI on a few.  Property: either the run
succeeds and every comment and pass-through line comes out byte for byte, or it fails with an ffcomp
error (a clean message and a non-zero exit) and leaves no output behind.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from cli_util import run
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ffcomp.errors import FfcompError
from ffcomp.gcode import GcodePlan
from ffcomp.gcode.parser import parse_gcode
from ffcomp.profile import default_profile

PROFILE = default_profile()
OTHER = str(Path(__file__).resolve().parents[1] / "samples" / "profiles" / "other_delta.toml")

_num = st.one_of(
    st.floats(-150, 150, allow_nan=False).map(lambda v: f"{v:.3f}"),
    st.integers(-5, 20000).map(str),
    st.sampled_from(["nan", "inf", "-inf", "1e309", "", ".", "-", "1O", "0x10", "1e-9", "0.001"]),
)
_word = st.tuples(st.sampled_from(list("XYZEFIJKRPS") + ["x", "Q", "*", "="]), _num).map(lambda t: t[0] + t[1])
_cmd = st.sampled_from(["G0", "G1", "G1", "G1", "G2", "G3", "G4", "G92", "G90", "G91", "M82", "M83", "G28", "G20",
                        "M104", "M106", "M117", "M220", "M221", "M204", "M600", "T1", "G10", "G29", "M400",
                        "SET_VELOCITY_LIMIT", "MY_MACRO", "N1", "g1", ""])
_gcode_line = st.builds(lambda c, ws, tail: (" ".join([c, *ws]) + tail).encode(),
                        _cmd, st.lists(_word, max_size=4),
                        st.sampled_from(["", " ; c", " (x)", "*12"]))
_byte_line = st.binary(max_size=30).map(lambda b: b.replace(b"\n", b" ").replace(b"\r", b" "))
_comment = st.binary(max_size=20).map(lambda b: b";" + b.replace(b"\n", b" ").replace(b"\r", b" "))
_line = st.one_of(_gcode_line, _byte_line, _comment)


def _file(lines: list[bytes]) -> bytes:
    return b"".join(ln + b"\n" for ln in lines)


@settings(max_examples=150, deadline=None)
@given(st.lists(_line, max_size=12), st.booleans(), st.sampled_from(["klipper", "marlin"]))
def test_parser_and_planner_raise_only_ffcomp_errors(lines, lenient, firmware):
    data = _file(lines)
    with tempfile.TemporaryDirectory() as d:
        p = os.path.join(d, "f.gcode")
        with open(p, "wb") as f:
            f.write(data)
        # the records restore the file byte for byte
        recs = list(parse_gcode(p, lenient=True))
        bom = b"\xef\xbb\xbf"  # a byte-order mark at the start is dropped (it is no part of a command)
        assert "".join(r.raw for r in recs).encode("utf-8", "surrogateescape") == data.removeprefix(bom)
        try:
            list(GcodePlan(p, PROFILE, lenient=lenient, firmware=firmware))
        except FfcompError as e:
            assert str(e)


_PREFIX = [b"G28", b"G90", b"M83", b"G1 X0 Y0 Z5 F6000", b"G1 X10 Y0 E0.5 F3000"]
_SUFFIX = [b"G1 X10 Y10 E0.5", b"G1 X0 Y10 E0.5"]


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.one_of(_gcode_line, _comment, _comment, _byte_line), min_size=1, max_size=4), st.booleans(),
       st.booleans())
def test_cli_succeeds_with_lines_intact_or_fails_cleanly(capsys, middle, lenient, other_profile):
    data = _file(_PREFIX + middle + _SUFFIX)
    with tempfile.TemporaryDirectory() as d:
        src, out = os.path.join(d, "in.gcode"), os.path.join(d, "out.gcode")
        with open(src, "wb") as f:
            f.write(data)
        args = [src, "-o", out, "--no-progress", "--no-predict", "--no-self-check"]
        if other_profile:
            args += ["--profile", OTHER]
        code, _, err = run(capsys, *(args + (["--lenient"] if lenient else [])))
        assert "Traceback" not in err
        if code == 0:
            got = open(out, "rb").read()
            for ln in middle:
                if ln.startswith(b";"):
                    assert ln + b"\n" in got  # comments come out byte for byte
        else:
            assert err.strip() and not os.path.exists(out)
            assert not [n for n in os.listdir(d) if n.startswith(".ffcomp-")]
        assert open(src, "rb").read() == data  # the input is never touched

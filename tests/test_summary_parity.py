"""Firmware parity of the header/footer, the flavour check, the closing summary and the progress."""

from __future__ import annotations

import io
import re
from dataclasses import replace
from pathlib import Path

import pytest
from cli_util import run

ROOT = Path(__file__).resolve().parents[1]
SQUARE = ROOT / "samples" / "gcode" / "stress_square.gcode"
FAST = dict(self_check=False, predict=False)


def _limit_words(lines: list[str]) -> dict[str, dict[str, float]]:
    """``{command: {letter: value}}`` of the firmware limit commands among ``lines``."""
    out: dict[str, dict[str, float]] = {}
    for ln in lines:
        code = ln.split(";")[0].strip()
        if not code:
            continue
        cmd, *words = code.split()
        if cmd in ("M201", "M204"):
            out.setdefault(cmd, {}).update({w[0]: float(w[1:]) for w in words})
        elif cmd == "SET_VELOCITY_LIMIT":
            out.setdefault(cmd, {}).update({k: float(v) for k, v in (w.split("=") for w in words)})
    return out


@pytest.mark.parametrize("planner", ["klipper", "marlin"])
@pytest.mark.parametrize("which", ["default", "other"])
def test_footer_restores_every_limit_the_header_raised(tmp_path, planner, which):
    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file
    from ffcomp.profile import default_profile, load_profile

    prof = default_profile() if which == "default" else load_profile(ROOT / "samples/profiles/other_delta.toml")
    prof = prof.with_(limits=replace(prof.limits, planner=planner))
    out = tmp_path / "o.gcode"
    compensate_file(str(SQUARE), str(out), prof, CompensateOptions(**FAST))
    text = out.read_text().splitlines()
    body_start = next(i for i, ln in enumerate(text) if ln.startswith("M83"))
    head = _limit_words(text[:body_start])
    foot = _limit_words(text[-3:])
    assert head and set(head) == set(foot)
    for cmd, words in head.items():
        assert set(words) == set(foot[cmd]), cmd
    lim = prof.limits
    if planner == "marlin":
        e_acc = lim.max_extrude_only_accel_mm_s2
        assert foot["M204"] == {"P": lim.max_accel_mm_s2, "T": lim.max_accel_mm_s2, "R": e_acc}
        assert foot["M201"] == {"X": lim.max_accel_mm_s2, "Y": lim.max_accel_mm_s2, "Z": lim.max_z_accel_mm_s2,
                                "E": e_acc}
    else:
        assert foot["SET_VELOCITY_LIMIT"]["ACCEL"] == lim.max_accel_mm_s2
        assert foot["SET_VELOCITY_LIMIT"]["MINIMUM_CRUISE_RATIO"] == lim.minimum_cruise_ratio


# ------------------------------------------------------------------ flavour

@pytest.mark.parametrize("where", ["head", "tail"])
def test_flavour_is_found_with_its_line(tmp_path, where):
    from ffcomp.gcode.flavour import detect_flavour

    body = [f"G1 X{i % 50} Y0 ; padding the file beyond the head that is read" for i in range(3000)]
    lines = ([";FLAVOR:Marlin"] + body) if where == "head" else (body + ["; gcode_flavor = marlin2"])
    p = tmp_path / "f.gcode"
    p.write_text("\n".join(lines) + "\n")
    fl = detect_flavour(str(p))
    assert fl.family == "marlin" and fl.line == (1 if where == "head" else len(lines))
    assert p.read_text().splitlines()[fl.line - 1] == fl.text
    p.write_text("\n".join(body) + "\n")
    assert detect_flavour(str(p)) is None


@pytest.mark.parametrize("decl,planner,warn", [(";FLAVOR:Marlin", "klipper", True),
                                               ("; gcode_flavor = klipper", "klipper", False),
                                               ("; gcode_flavor = klipper", "marlin", True),
                                               ("; gcode_flavor = marlin2", "marlin", False),
                                               ("; gcode_flavor = reprapfirmware", "klipper", True),
                                               (None, "klipper", False)])
def test_flavour_mismatch_is_a_counted_warning(tmp_path, profile, decl, planner, warn):
    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file

    src = tmp_path / "s.gcode"
    src.write_text((decl + "\n" if decl else "") + SQUARE.read_text())
    prof = profile.with_(limits=replace(profile.limits, planner=planner))
    summ = compensate_file(str(src), str(tmp_path / "o.gcode"), prof, CompensateOptions(**FAST))
    flavour_notes = [n for n in summ.notes if "was sliced for" in n]
    assert len(flavour_notes) == int(warn) and summ.warnings == len(summ.notes)  # every note is counted
    assert summ.firmware == planner
    if warn:
        assert f"{src}:1:" in flavour_notes[0] and f"is for {planner}" in flavour_notes[0]


# ------------------------------------------------------------------ summary table

def test_table_shows_output_firmware_clamps_and_warnings(tmp_path, capsys):
    src = tmp_path / "s.gcode"
    src.write_text(";FLAVOR:Marlin\n" + SQUARE.read_text())
    out = tmp_path / "o.gcode"
    code, text, err = run(capsys, "compensate", src, "-o", out, "--no-progress", "--no-self-check", "--no-predict")
    assert code == 0, err
    flat = re.sub(r"\s+", " ", text.replace("│", " "))
    assert f"output{out}" in re.sub(r"[\s│]", "", text)  # a long path wraps inside its cell
    assert "firmware assumed (profile) klipper (file sliced for Marlin)" in flat
    assert re.search(r"samples clamped to the workspace \(a \d+ correction past the firmware.s limits", flat)
    assert re.search(r"warnings [1-9]\d* \(listed below\)", flat)
    assert "warning:" in err and "sliced for Marlin" in err


# ------------------------------------------------------------------ progress

class _Recorder:
    def __init__(self):
        self.events = []

    def __call__(self, done, total):
        self.events.append(("progress", done, total))

    def stage(self, name, total):
        self.events.append(("stage", name, total))


def test_progress_reports_stages_in_order(tmp_path, profile):
    from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file

    rec = _Recorder()
    compensate_file(str(SQUARE), str(tmp_path / "o.gcode"), profile, CompensateOptions(predict=False),
                    progress=rec)
    stages = [e[1] for e in rec.events if e[0] == "stage"]
    assert stages == ["writing", "self-check"]
    first_stage = next(i for i, e in enumerate(rec.events) if e[0] == "stage")
    done = [e[1] for e in rec.events[:first_stage]]
    assert done == sorted(done) and done and all(e[0] == "stage" for e in rec.events[first_stage:])


def test_bar_completes_each_stage_instead_of_stalling():
    """The line count stops short of 100 % (a slicer's config block follows the last move): a new
    stage completes the previous bar, and the new stage is named."""
    from rich.console import Console
    from rich.progress import Progress

    from ffcomp.cli.compensate_cmd import BarProgress

    bar = Progress(console=Console(file=io.StringIO()))
    p = BarProgress(bar, "x.gcode")
    p(980, 1000)
    assert bar.tasks[0].percentage == pytest.approx(98.0)
    p.stage("self-check", 1000)
    assert bar.tasks[0].finished and bar.tasks[0].percentage == 100.0
    assert bar.tasks[1].description.startswith("self-check") and bar.tasks[1].total is None


def test_plain_progress_lines_with_eta(capsys):
    from ffcomp.cli.compensate_cmd import PlainProgress

    p = PlainProgress("x.gcode")
    for k in range(0, 1001, 50):
        p(k, 1000)
    p.stage("self-check", 1000)
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "ffcomp: compensating x.gcode"
    pct = [int(m.group(1)) for ln in err if (m := re.search(r"compensating\s+(\d+)%", ln))]
    assert pct == list(range(10, 101, 10)) and all("ETA" in ln for ln in err[1:11])
    assert err[-1].startswith("ffcomp: self-check: re-planning the output")

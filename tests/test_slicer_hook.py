"""The real PrusaSlicer runs ffcomp as its post-processing script (skipped without prusa-slicer)."""

import importlib.util
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRUSA = shutil.which("prusa-slicer")


def _make_samples():
    spec = importlib.util.spec_from_file_location("make_samples", ROOT / "samples" / "make_samples.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.skipif(PRUSA is None, reason="prusa-slicer is not installed (.ci/run installs it)")
def test_prusaslicer_post_process_runs_ffcomp(tmp_path):
    ms = _make_samples()
    out = tmp_path / "cube small.gcode"  # a space in the name: PrusaSlicer quotes the path
    hook = f"{sys.executable} -m ffcomp hook --tol-um 8"
    cmd = [PRUSA, "--export-gcode", "--loglevel", "1", *ms.prusa_printer_args(), "--layer-height", "0.3",
           "--first-layer-height", "0.3", "--perimeters", "1", "--fill-density", "0%", "--top-solid-layers", "0",
           "--bottom-solid-layers", "1", "--scale", "30%", "--center", "0,0", "--post-process", hook,
           "--output", str(out), str(ROOT / "samples" / "models" / "cube20.stl")]
    env = dict(os.environ, HOME=str(tmp_path))
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=env)
    assert r.returncode == 0, r.stdout + r.stderr
    text = out.read_text()
    assert text.startswith("; ffcomp ")
    assert "SET_VELOCITY_LIMIT ACCEL=" in text
    assert ";TYPE:" in text  # slicer annotations survive in place
    assert "; ffcomp (baked in): M82" in text or "; ffcomp (baked in): G90" in text
    # a second run on the compensated file is refused and leaves it untouched
    r2 = subprocess.run([sys.executable, "-m", "ffcomp", "hook", str(out)], capture_output=True, text=True)
    assert r2.returncode != 0 and "already compensated" in r2.stderr
    assert out.read_text() == text

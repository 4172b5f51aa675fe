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


def test_cura_script_compensates_the_layers(tmp_path, monkeypatch):
    """The shipped Cura script, run against a stand-in for Cura's ``Script`` base class (Cura itself
    is not installable here): it hands the joined layers to ``ffcomp hook`` and returns the result."""
    import json

    pkg = tmp_path / "fakecura"
    (pkg / "scripts").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "Script.py").write_text(
        "import json\n"
        "class Script:\n"
        "    def __init__(self):\n"
        "        s = json.loads(self.getSettingDataString())['settings']\n"
        "        self.values = {k: v['default_value'] for k, v in s.items()}\n"
        "    def getSettingValueByKey(self, key):\n"
        "        return self.values[key]\n")
    (pkg / "scripts" / "__init__.py").write_text("")
    shutil.copy(ROOT / "ffcomp" / "data" / "FfcompPostProcessing.py", pkg / "scripts")
    monkeypatch.syspath_prepend(str(tmp_path))
    mod = importlib.import_module("fakecura.scripts.FfcompPostProcessing")
    script = mod.FfcompPostProcessing()
    assert json.loads(script.getSettingDataString())["key"] == "FfcompPostProcessing"
    exe = Path(sys.executable).with_name("ffcomp")
    script.values["ffcomp"] = str(exe) if exe.exists() else shutil.which("ffcomp")
    script.values["hold_margin_ms"] = 15.0
    made = []
    real_mkstemp = mod.tempfile.mkstemp

    def mkstemp(*a, **k):
        fd, path = real_mkstemp(*a, **k)
        made.append(path)
        return fd, path

    monkeypatch.setattr(mod.tempfile, "mkstemp", mkstemp)
    src = (ROOT / "samples" / "gcode" / "cube_cura.gcode").read_text()
    parts = src.split(";LAYER:")
    layers = [parts[0]] + [";LAYER:" + p for p in parts[1:]]  # Cura hands over one string per layer
    text = "".join(script.execute(layers))
    assert text.startswith("; ffcomp ") and "SET_VELOCITY_LIMIT ACCEL=" in text
    assert "hold_margin=15ms" in text  # the script's setting reaches the hook
    assert text.count(";LAYER:") == src.count(";LAYER:")  # Cura's annotations survive in place
    assert made and not any(os.path.exists(p) for p in made)  # the script cleans up after itself

"""Benchmark: a slicer's file as a Klipper user makes it, compensated on both profiles.

Run: ``python benchmarks/bench_user_files.py [--slicer PATH] [--keep DIR] [--gcode FILE]`` (needs PrusaSlicer:
``apt-get install prusa-slicer``; about five minutes on one core).  Slices
``samples/models/ringing_tower.stl`` the way most Klipper users' files look, not the way the
committed samples do: no ``G28`` (a ``PRINT_START`` macro homes), firmware retraction (``G10`` /
``G11``), a 0.4 mm z-hop at every travel, 0.2 mm layers, gyroid infill, 100 / 150 / 250 mm/s.  Then
compensates it (self-check limits lifted, so every run is measured) on the default profile and on
``samples/profiles/other_delta.toml``, each as it is (``G10``/``G11`` are stops there: the stream
comes to rest at each) and with a ``[firmware_retraction]`` section of the slicer's values (they
are timed as Klipper's extruder moves), and prints per run the print time, the run's time and
speed, the stops, the largest drift on the absolute clock and at the end (ms), the largest
distance from the intended command at the same instant (um) and the self-check's shape error (um).
``--gcode FILE`` compensates that file instead of slicing (e.g. one ``--keep`` kept, to compare
two versions of ffcomp on the same slice: PrusaSlicer's gyroid is not the same byte for byte from
one run to the next).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "samples"))

import make_samples as ms  # noqa: E402

from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file  # noqa: E402
from ffcomp.profile import FirmwareRetraction, default_profile, load_profile  # noqa: E402

#: the slicer settings that differ from the committed samples' (name -> value)
KLIPPER_USER = {
    "--start-gcode": "PRINT_START BED=60 EXTRUDER=210",
    "--end-gcode": "PRINT_END",
    "--retract-lift": "0.4",
    "--travel-speed": "250",
    "--infill-speed": "150",
    "--perimeter-speed": "100",
}
EXTRA = ["--use-firmware-retraction", "--layer-height", "0.2", "--first-layer-height", "0.25", "--perimeters", "3",
         "--fill-density", "20%", "--fill-pattern", "gyroid"]
#: Klipper's [firmware_retraction] with the slicer's retraction (0.8 mm at 35 mm/s)
FR = FirmwareRetraction(retract_length_mm=0.8, retract_speed_mm_s=35.0, unretract_extra_length_mm=0.0,
                        unretract_speed_mm_s=35.0)
LIFTED = dict(self_check_tol_um=1e9, self_check_drift_ms=1e9)


def slice_tower(exe: str, out: Path) -> Path:
    """``ringing_tower.stl`` sliced with the committed samples' printer and :data:`KLIPPER_USER`."""
    args = ms.prusa_printer_args()
    for k, v in KLIPPER_USER.items():
        args[args.index(k) + 1] = v
    stl = ROOT / "samples" / "models" / "ringing_tower.stl"
    cmd = [exe, "--export-gcode", "--loglevel", "1"] + args + EXTRA
    cmd += ["--center", "0,0", "--output", str(out), str(stl)]
    subprocess.run(cmd, check=True, capture_output=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--slicer", default=None, help="PrusaSlicer executable (default: from PATH)")
    ap.add_argument("--keep", type=Path, default=None, help="keep the sliced file in this folder")
    ap.add_argument("--gcode", type=Path, default=None, help="compensate this file instead of slicing")
    a = ap.parse_args()
    work = Path(a.keep or tempfile.mkdtemp(prefix="bench_user_"))
    work.mkdir(parents=True, exist_ok=True)
    if a.gcode is not None:
        src = a.gcode
    else:
        exe = a.slicer or shutil.which("prusa-slicer") or shutil.which("prusa-slicer-console")
        if exe is None:
            sys.exit("PrusaSlicer not found (apt-get install prusa-slicer)")
        src = slice_tower(exe, work / "tower_klipper_user.gcode")
    n_lines = sum(1 for _ in src.open("rb"))
    print(f"{src.name}: {n_lines} lines, {src.read_text().count(chr(10) + 'G10')} G10\n")
    print("| profile | G10/G11 | print (s) | run (s) | speed | stops | drift max (ms) | drift at end (ms) "
          "| clock error max (um) | self-check max (um) |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, prof in (("default", default_profile()),
                       ("other_delta", load_profile(ROOT / "samples" / "profiles" / "other_delta.toml"))):
        for how, p in (("stops", prof), ("[firmware_retraction]", prof.with_(firmware_retraction=FR))):
            s = compensate_file(str(src), str(work / "out.gcode"), p, CompensateOptions(**LIFTED))
            print(f"| {name} | {how} | {s.print_time_s:.1f} | {s.wall_time_s:.1f} | {s.speed_ratio:.0f}x | "
                  f"{s.commands_stopped} | {s.self_check_drift_ms:+.3f} | {s.self_check_drift_end_ms:+.3f} | "
                  f"{s.self_check_abs_max_um:.1f} | {s.self_check_max_um:.1f} |", flush=True)


if __name__ == "__main__":
    main()

"""Benchmark: how much of the exact commands' gain the compensated G-code keeps, and its timing.

Run: ``python benchmarks/bench_gcode_fidelity.py [--quick]``.  For the default profile and for
``samples/profiles/other_delta.toml`` (compensated with the identified profile, simulated on
``other_delta_truth.toml``), on generated files (a 60 mm square in layers with z-hops and
retractions at the centre, a 40 mm square at (80, 0) (inside both print radii), a 64-segment circle,
a zig-zag, pure z travel, a high-flow circle (a 0.8 mm nozzle's 0.15 mm of filament per mm)): the
lag-aligned and contour RMS of the exact commands and of the G-code as a fraction of the
uncompensated file's, the kept share of the exact commands' reduction (over the whole file, and
over the samples where the plan extrudes while it moves: what marks the part), and the largest
drift of the re-planned output on the absolute clock (ms); then the physical limit (the finest command
the firmware executes, iterated on the model's own plant: :mod:`ffcomp.compensate.limit`) as the
same fraction, and how many times its lag-aligned RMS the exact commands and the G-code leave
(``--no-limit`` skips these columns).  Prints a Markdown table per profile.
``--hold-margin-ms M`` adds M ms of rest before every retraction and after every unretraction
(``CompensateOptions.hold_margin_s``) and ``--quiet-z 1`` plans the z moves next to retractions with
slower, quiet ramps; the reference then includes that time, and two more columns judge the G-code
against the source's own plan, as an independent judge that plans the source file does (there the
added time counts as error).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "samples"))

import make_samples as ms  # noqa: E402

from ffcomp.pipeline.compensate_flow import CompensateOptions, compensate_file  # noqa: E402
from ffcomp.pipeline.output_check import check_gcode_output  # noqa: E402
from ffcomp.profile import default_profile, load_profile  # noqa: E402

HEAD = ["G90", "M82", "G92 E0"]


def _file(limits: list[str], pw: "ms.PathWriter") -> str:
    # no G28: the check compares one compensation stream from the start position
    return "\n".join(HEAD + limits + pw.lines) + "\n"


def high_flow_circle(laps: int = 2) -> "ms.PathWriter":
    """A 0.8 mm nozzle's flow (0.9 mm x 0.4 mm lines: 0.15 mm of filament per mm) on a 48-segment
    circle at 200 mm/s: Klipper's extruder junction rule binds where segment ratios differ."""
    pw = ms.PathWriter(0.9, 0.4)
    pts = ms.circle(0.0, 0.0, 30.0, 48)
    pw.travel(*pts[0], z=0.4, f=12000)
    first = True
    for _ in range(laps):
        for p in list(pts[1:]) + [pts[0]]:
            pw.extrude(float(p[0]), float(p[1]), f=12000 if first else None)
            first = False
    return pw


def zhop_squares(layers: int = 3, side: float = 30.0, gap: float = 50.0, lift: float = 0.4) -> "ms.PathWriter":
    """Two squares ``gap`` apart, printed in turn on every layer, with a slicer's z-hop between them
    (PrusaSlicer's ``retract_lift``): retract, lift ``lift`` mm, travel, lower, unretract."""
    pw = ms.PathWriter(0.45, 0.2)
    h = side / 2
    for layer in range(layers):
        z = 0.2 * (layer + 1)
        pw.comment(f"LAYER:{layer}")
        for i, cx in enumerate((-gap / 2, gap / 2)):
            corners = [(cx - h, -h), (cx + h, -h), (cx + h, h), (cx - h, h)]
            if layer == 0 and i == 0:
                pw.travel(*corners[0], z=z, f=12000)
            else:
                pw.retract(0.8)
                pw.lines.append(f"G1 Z{z - (0.2 if i == 0 else 0.0) + lift:.3f} F6000")
                pw.travel(*corners[0], f=12000)
                pw.lines.append(f"G1 Z{z:.3f} F6000")
                pw.unretract(0.8)
            for k, c in enumerate(corners[1:] + corners[:1]):
                pw.extrude(*c, f=9000 if k == 0 else None)
    return pw


def repair_from_args(pairs: list[str]):
    """A :class:`~ffcomp.compensate.pin_repair.RepairConfig` from ``KEY=VALUE`` strings (``--repair``)."""
    import dataclasses

    from ffcomp.compensate.pin_repair import RepairConfig

    types = {f.name: f.type for f in dataclasses.fields(RepairConfig)}
    kv = dict(r.split("=", 1) for r in pairs)
    conv = {"bool": lambda v: v.lower() in ("1", "true", "yes"), "int": int, "float": float}
    return RepairConfig(**{k: conv[str(types[k])](v) for k, v in kv.items()})


def bench_profiles() -> dict:
    """name -> (the profile compensated with, the plant simulated: None for the profile itself)."""
    return {"default": (default_profile(), None),
            "other_delta": (load_profile(ROOT / "samples/profiles/other_delta.toml"),
                            load_profile(ROOT / "samples/profiles/other_delta_truth.toml"))}


def files(quick: bool) -> dict[str, str]:
    """The benchmark's G-code files (deterministic), name -> text."""
    layers = 2 if quick else 3
    z = ["G1 X0 Y0 Z5 F6000"]
    for _ in range(1 if quick else 3):
        z += ["G1 Z25 F6000", "G1 Z5", "G1 X10 Y0 Z8", "G1 X0 Y0 Z5"]
    out = {
        "square 60 mm, 150 mm/s, layers": _file(ms.ACCEL_10K, ms.stress_square(0, 0, layers=layers, laps=1)),
        "square 40 mm @ (80,0)": _file(ms.ACCEL_10K, ms.stress_square(80.0, 0, side=40.0, layers=layers, laps=1)),
        "circle 64 seg, 200 mm/s, 5000": _file(["SET_VELOCITY_LIMIT ACCEL=5000", "M204 S5000"],
                                               ms.stress_circle(layers=layers, laps=1, feed=12000)),
        "zig-zag 250 mm/s": _file(["SET_VELOCITY_LIMIT VELOCITY=300 ACCEL=10000", "M204 S10000"],
                                  ms.stress_zigzag(length=30.0, layers=1 if quick else 2)),
        "z travel 100 mm/s": "\n".join(HEAD + ms.ACCEL_10K + z) + "\n",
        "high flow circle 0.15 mm/mm": _file(ms.ACCEL_10K, high_flow_circle(laps=1 if quick else 2)),
        "two squares, z-hop travels": _file(ms.ACCEL_10K, zhop_squares(layers=layers)),
    }
    return out


def _f(x: float) -> str:
    return "-" if x != x else f"{x:.2f}"


def _limit_cells(c, none_lag_um: float) -> str:
    """The physical-limit columns of one row (empty without the limit run)."""
    if c.limit is None:
        return ""
    return (f" {c.limit.lag.rms_norm_um / none_lag_um:.4f} | {c.over_limit('exact'):.2f}x "
            f"| {c.over_limit('gcode'):.1f}x |")


def _source_cells(c, moved: bool) -> str:
    """The G-code's lag-aligned and contour ratios judged against the source's own plan (what a
    judge that plans the source file sees: the time the options add counts as error)."""
    if not moved:
        return ""
    if c.source_clock is None:
        return " = | = |"
    n, g = c.source_clock["none"], c.source_clock["gcode"]
    return (f" {g.lag.rms_norm_um / n.lag.rms_norm_um:.3f} | "
            f"{g.contour.rms_norm_um / n.contour.rms_norm_um:.3f} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true", help="shorter files")
    ap.add_argument("--z-mode", default=None, help="CompensateOptions.z_mode (default: the default)")
    ap.add_argument("--pin-holds", default=None, choices=["0", "1"],
                    help="CompensateOptions.pin_repair (1, the default: the command pinned to the plan during "
                         "holds and re-solved around them; 0: the older catch-up writer, --catch-up-holds)")
    ap.add_argument("--repair", action="append", default=[], metavar="KEY=VALUE",
                    help="a RepairConfig field of the pin repair, e.g. edge_weight=0 or pin_z_after_hold=0 "
                         "(repeatable)")
    ap.add_argument("--drift-file", action="append", default=[], type=Path, metavar="GCODE",
                    help="also compensate this file (any file: several streams, homing) and print the "
                         "self-check's drift and deviation from its summary (repeatable)")
    ap.add_argument("--only", default=None, help="only files whose name contains this")
    ap.add_argument("--profiles", default="default,other_delta")
    ap.add_argument("--hold-margin-ms", type=float, default=None,
                    help="CompensateOptions.hold_margin_s in ms (rest added around retractions)")
    ap.add_argument("--no-limit", action="store_true",
                    help="skip the physical-limit columns (the limit's commands cost about 1.5 s of CPU per "
                         "second of motion)")
    ap.add_argument("--quiet-z", default=None, choices=["0", "1"],
                    help="CompensateOptions.quiet_z (1: the z moves next to retractions planned with quiet ramps, and "
                         "the reference with them; 0, the default: as the source plans them)")
    ap.add_argument("--tol-um", type=float, default=None,
                    help="CompensateOptions.tol_um (the writer's point placement tolerance, default 5)")
    a = ap.parse_args()
    profiles = bench_profiles()
    tmp = Path(tempfile.mkdtemp(prefix="bench_fidelity_"))
    extra = {}
    if a.z_mode:
        extra["z_mode"] = a.z_mode
    if a.tol_um is not None:
        extra["tol_um"] = a.tol_um
    if a.hold_margin_ms is not None:
        extra["hold_margin_s"] = a.hold_margin_ms * 1e-3
    if a.quiet_z is not None:
        extra["quiet_z"] = a.quiet_z == "1"
    if a.pin_holds:
        extra["pin_repair"] = a.pin_holds == "1"
    if a.repair:
        extra["repair"] = repair_from_args(a.repair)
    for pname, (prof, truth) in profiles.items():
        if pname not in a.profiles.split(","):
            continue
        print(f"\n### {pname}\n")
        lim_head = "" if a.no_limit else " limit lag | exact / limit | G-code / limit |"
        # options that add time (margins, quiet z moves): the output judged on the source's own plan too
        moved = bool(a.hold_margin_ms) or a.quiet_z == "1"
        src_head = " G-code lag, source clock | G-code contour, source clock |" if moved else ""
        print("| file | exact lag | G-code lag | exact contour | G-code contour | kept lag | kept contour "
              "| kept lag, extruding | kept contour, extruding | drift max (ms) | clock error max (um) |"
              + lim_head + src_head)
        print("|---|---|---|---|---|---|---|---|---|---|---|" + ("" if a.no_limit else "---|---|---|")
              + ("---|---|" if moved else ""))
        for name, text in files(a.quick).items():
            if a.only and a.only not in name:
                continue
            src = tmp / "in.gcode"
            src.write_text(text)
            try:
                c = check_gcode_output(prof, src, tmp / "out.gcode", plant_profile=truth,
                                       opts=CompensateOptions(predict=False, self_check_tol_um=1e9,
                                                              self_check_drift_ms=1e9, **extra),
                                       limit=not a.no_limit)
            except Exception as e:  # a failing case is a row, not the end of the table
                print(f"| {name} | failed: {type(e).__name__}: {str(e)[:80]} |||||||||")
                continue
            n, e, g = c.none, c.exact, c.gcode
            nl = n.lag.rms_norm_um
            print(f"| {name} | {e.lag.rms_norm_um / nl:.3f} | {g.lag.rms_norm_um / nl:.3f} "
                  f"| {e.contour.rms_norm_um / n.contour.rms_norm_um:.3f} | "
                  f"{g.contour.rms_norm_um / n.contour.rms_norm_um:.3f} | {c.kept('lag'):.2f} | "
                  f"{c.kept('contour'):.2f} | {_f(c.kept_extruding('lag'))} | {_f(c.kept_extruding('contour'))} "
                  f"| {c.summary.self_check_drift_ms:+.3f} | {c.summary.self_check_abs_max_um:.1f} |"
                  + _limit_cells(c, nl) + _source_cells(c, moved), flush=True)
        if a.drift_file:
            print("\n| file | drift max (ms) | at (s) | self-check max (um) | clock error max (um) |\n"
                  "|---|---|---|---|---|")
        for f in a.drift_file:
            try:
                s = compensate_file(str(f), str(tmp / "drift.gcode"), prof,
                                    CompensateOptions(predict=False, self_check_drift_ms=1e9, **extra))
            except Exception as e:  # (a file outside this printer's reach) a row, not the end of the table
                print(f"| {f.name} | failed: {type(e).__name__}: {str(e)[:100]} |||", flush=True)
                continue
            print(f"| {f.name} | {s.self_check_drift_ms:+.3f} | {s.self_check_drift_at_s:.3f} | "
                  f"{s.self_check_max_um:.1f} | {s.self_check_abs_max_um:.1f} |", flush=True)


if __name__ == "__main__":
    main()

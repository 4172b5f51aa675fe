"""``ffcomp compensate IN.gcode -o OUT.gcode`` (also the bare ``ffcomp IN.gcode -o OUT.gcode``)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from .common import JobsOpt, JsonOpt, ProfileOpt, app, err_console, load_profile_opt, print_json, resolve_jobs

FORMATS = ("gcode", "steps", "steps-csv")


@app.command("compensate")
def compensate_cmd(
    source: Annotated[Path, typer.Argument(help="G-code file to compensate.")],
    output: Annotated[Optional[str], typer.Option("--output", "-o", help="Output file; '-' for stdout; "
                                                  "default: replace the input in place.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="gcode | steps (compact .ffsteps) | steps-csv.")] = "gcode",
    method: Annotated[str, typer.Option(help="Inverse variant: lpv (default) or lti-centre.")] = "lpv",
    tol_um: Annotated[float, typer.Option("--tol-um", help="G-code point placement tolerance, um.")] = 5.0,
    z_mode: Annotated[str, typer.Option("--z-mode", help="keep: compensated z everywhere; hold: keep planned "
                                        "z on layer moves (firmware with low max_z_accel); auto: planned z on "
                                        "moves that travel in z.")] = "keep",
    pin_holds: Annotated[bool, typer.Option("--pin-holds/--catch-up-holds", help="Keep the command on the plan "
                                            "during extruder-only moves, dwells and z-hops after them, and "
                                            "re-solve it around them (default); or let it move on and catch "
                                            "up after them.")] = True,
    shape_steps: Annotated[bool, typer.Option("--shape-steps/--no-shape-steps", help="Step streams only: "
                                              "choose the steps quantisation-aware (error feedback on a 10x "
                                              "finer grid: the step error moves to ~5 kHz).")] = False,
    plan_where_limited: Annotated[bool, typer.Option(
        "--plan-where-limited/--compensate-where-limited",
        help="Follow the plan where the firmware's limits would make the compensated command run late "
             "(moves bound by the extruder's limits; the z of z-hops right after a retraction).")] = True,
    hold_margin_ms: Annotated[float, typer.Option("--hold-margin-ms", help="Rest (ms) added before every "
                                                  "retraction that follows a move and after every unretraction "
                                                  "that precedes one: the command settles the stop's ringing "
                                                  "and pre-actuates the next move there (a G-code file cannot "
                                                  "move the nozzle during an extruder-only move). 15 keeps "
                                                  "~95 % of the gain on extruded lines at layer changes; the "
                                                  "print takes that much longer per margin. 0: none.")] = 0.0,
    quiet_z: Annotated[bool, typer.Option("--quiet-z/--no-quiet-z", help="Plan the z moves next to "
                                          "retractions (layer changes, z-hop lifts and descents) with ramps "
                                          "one period of the printer's z resonance long, so they leave "
                                          "almost no ringing (a G-code file cannot compensate them: the "
                                          "nozzle stands still in the retractions around them). Klipper "
                                          "only; off by default: the print takes about 20 ms longer per "
                                          "such move, so the output no longer runs on the source's own "
                                          "clock.")] = False,
    self_check: Annotated[bool, typer.Option("--self-check/--no-self-check", help="Re-plan the output and "
                                             "compare with the intended commands.")] = True,
    self_check_tol_um: Annotated[float, typer.Option("--self-check-tol-um", help="Self-check limit, um.")] = 50.0,
    predict: Annotated[bool, typer.Option("--predict/--no-predict", help="Predict the residual vibration "
                                          "before/after with the model (summary).")] = True,
    lenient: Annotated[bool, typer.Option(help="Skip malformed G-code lines (kept as '; ffcomp (skipped):' "
                                          "comments) and count them as warnings.")] = False,
    start: Annotated[Optional[str], typer.Option("--start", help="X,Y,Z (mm): where the toolhead stands before "
                                                 "a file that moves before any G28 (default: the target of "
                                                 "its first move).")] = None,
    unknown_commands: Annotated[str, typer.Option("--unknown-commands", help="Unknown macros and G codes: stop "
                                                  "(the toolhead rests before them; default), pass (copied "
                                                  "as they are) or refuse (an error).")] = "stop",
    jobs: JobsOpt = 1,
    progress: Annotated[bool, typer.Option("--progress/--no-progress", help="Progress bar on stderr.")] = True,
    profile: ProfileOpt = None,
    json: JsonOpt = False,
) -> None:
    """Compensate a G-code file for the printer's vibration (model-based feedforward).

    Writes atomically: on any error the input and any existing output are left untouched.
    """
    from ..compensate.inverse import InverseConfig
    from ..pipeline.compensate_flow import CompensateOptions, compensate_file

    if fmt not in FORMATS:
        raise typer.BadParameter(f"--format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if method not in ("lpv", "lti-centre"):
        raise typer.BadParameter(f"--method must be lpv or lti-centre for files, got {method!r}")
    if z_mode not in ("keep", "hold", "auto"):
        raise typer.BadParameter(f"--z-mode must be keep, hold or auto, got {z_mode!r}")
    if tol_um <= 0:
        raise typer.BadParameter(f"--tol-um must be > 0, got {tol_um}")
    from ..gcode.commands import UNKNOWN_POLICIES

    if unknown_commands not in UNKNOWN_POLICIES:
        raise typer.BadParameter(f"--unknown-commands must be stop, pass or refuse, got {unknown_commands!r}")
    from ..gcode.start import parse_start

    try:
        start_mm = None if start is None else parse_start(start)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None
    if not 0.0 <= hold_margin_ms <= 1000.0:
        raise typer.BadParameter(f"--hold-margin-ms must be between 0 and 1000, got {hold_margin_ms}")
    if hold_margin_ms and fmt != "gcode":
        raise typer.BadParameter("--hold-margin-ms is for G-code output (step streams move during retractions)")
    if quiet_z and fmt != "gcode":
        raise typer.BadParameter("--quiet-z is for G-code output (step streams move during retractions)")
    if jobs != 1 and fmt != "gcode":
        raise typer.BadParameter("--jobs is for G-code output (--format gcode) only")
    jobs = resolve_jobs(jobs)
    prof = load_profile_opt(profile)
    out = str(source) if output is None else (None if output == "-" else output)
    if fmt != "gcode":
        from ..pipeline.steps_flow import steps_file

        if out is None or out == str(source):
            raise typer.BadParameter("--format steps needs an output file (-o FILE)")
        summ = steps_file(str(source), out, prof, method=method, lenient=lenient, csv=(fmt == "steps-csv"),
                          shape=shape_steps)
        _report(summ.to_dict(), json)
        return
    opts = CompensateOptions(method=method, tol_um=tol_um, z_mode=z_mode, self_check=self_check,
                             self_check_tol_um=self_check_tol_um, predict=predict, lenient=lenient,
                             pin_repair=pin_holds, inverse=InverseConfig(method=method), start_mm=start_mm,
                             unknown_policy=unknown_commands, plan_where_limited=plan_where_limited, jobs=jobs,
                             hold_margin_s=hold_margin_ms * 1e-3, quiet_z=quiet_z)
    show = progress and not json and os.environ.get("CI") != "true"
    if show and err_console.is_terminal:
        with Progress(TextColumn("[bold]{task.description}[/]"), BarColumn(), TextColumn("{task.fields[pct]}"),
                      TextColumn("ETA"), TimeRemainingColumn(), TextColumn("elapsed"), TimeElapsedColumn(),
                      console=err_console, transient=True) as bar:
            summ = compensate_file(str(source), out, prof, opts, progress=BarProgress(bar, source.name))
    elif show:
        summ = compensate_file(str(source), out, prof, opts, progress=PlainProgress(source.name))
    else:
        summ = compensate_file(str(source), out, prof, opts)
    _report(summ.to_dict(), json, to_stderr=(out is None))


#: what each stage of :func:`~ffcomp.pipeline.compensate_flow.compensate_file` does, for the bar
STAGES = {"compensating": "compensating", "writing": "writing the output",
          "self-check": "self-check: re-planning the output"}


class BarProgress:
    """A rich progress bar: one row per stage, the first with its percentage and ETA (a stage that
    cannot measure its progress shows a moving bar and its elapsed time)."""

    def __init__(self, bar: Progress, name: str):
        self.bar, self.name = bar, name
        self.task = bar.add_task(f"compensating {name}", total=1, pct="  0%")

    def __call__(self, done: int, total: int) -> None:
        self.bar.update(self.task, completed=done, total=max(total, 1), pct=f"{100 * done / max(total, 1):3.0f}%")

    def stage(self, name: str, total: int) -> None:
        t = self.bar.tasks[-1]
        self.bar.update(self.task, completed=t.total, pct="done")
        self.bar.stop_task(self.task)
        self.task = self.bar.add_task(STAGES.get(name, name), total=None, pct="")


class PlainProgress:
    """Progress as plain lines on stderr (not a terminal: a log, a pipe): each stage, and every 10 %
    of the compensation with its ETA."""

    def __init__(self, name: str):
        self.name, self.t0, self.next_pct = name, time.monotonic(), 10
        self.started = False

    def _say(self, msg: str) -> None:
        sys.stderr.write(f"ffcomp: {msg}\n")
        sys.stderr.flush()

    def __call__(self, done: int, total: int) -> None:
        if not self.started:  # said only once the work runs (a bad output path fails before)
            self.started = True
            self._say(f"compensating {self.name}")
        pct = 100.0 * done / max(total, 1)
        if pct >= self.next_pct and done > 0:
            el = time.monotonic() - self.t0
            eta = el * (total - done) / done
            self._say(f"compensating {pct:3.0f}% (line {done:,} of {total:,}), ETA {eta:.0f} s")
            self.next_pct = (int(pct) // 10 + 1) * 10

    def stage(self, name: str, total: int) -> None:
        self._say(f"{STAGES.get(name, name)} ({time.monotonic() - self.t0:.1f} s elapsed)")


def _report(d: dict, json: bool, to_stderr: bool = False) -> None:
    if json:
        if to_stderr:  # stdout carries the G-code
            import json as _json
            import sys

            sys.stderr.write(_json.dumps(d, indent=2, default=str) + "\n")
        else:
            print_json(d)
        return
    t = Table(title="ffcomp: compensation summary", title_justify="left", show_header=False)
    t.add_column()
    t.add_column(overflow="fold")  # a long output path is shown whole, folded, never cut
    if d.get("output"):
        t.add_row("output", "stdout" if d["output"] == "-" else str(d["output"]))
    if d.get("firmware"):
        fl = d.get("source_flavour")
        t.add_row("firmware assumed (profile)", d["firmware"] + (f"  (file sliced for {fl})" if fl else ""))
    fmt = {
        "rms_before_um": ("predicted vibration RMS, uncompensated", "{:.1f} um"),
        "rms_after_um": ("predicted vibration RMS, compensated", "{:.2f} um"),
        "max_before_um": ("predicted vibration max, uncompensated", "{:.1f} um"),
        "max_after_um": ("predicted vibration max, compensated", "{:.1f} um"),
        "print_time_s": ("print time, source (planned)", "{:.2f} s"),
        "output_print_time_s": ("print time, output (re-planned)", "{:.2f} s"),
        "wall_time_s": ("processing time", "{:.2f} s"),
        "predict_time_s": ("  of which the prediction", "{:.2f} s"),
        "self_check_time_s": ("  of which the self-check", "{:.2f} s"),
        "retime_time_s": ("  of which the feeds' re-timing (Marlin)", "{:.2f} s"),
        "speed_ratio": ("speed (print time / processing time)", "{:.0f}x"),
        "self_check_max_um": ("self-check: max deviation of re-planned carriages", "{:.1f} um"),
        "self_check_rms_um": ("self-check: RMS deviation", "{:.2f} um"),
        "self_check_catch_up_max_um": ("self-check: max deviation in catch-ups after holds", "{:.1f} um"),
        "self_check_drift_ms": ("self-check: largest drift on the absolute clock", "{:+.3f} ms"),
        "self_check_abs_max_um": ("self-check: max deviation at the same absolute time", "{:.1f} um"),
        "retime_before_ms": ("feeds re-timed on the firmware's plan: drift before", "{:.3f} ms"),
        "retime_after_ms": ("  after (largest on the absolute clock)", "{:.3f} ms"),
        "retime_passes": ("  passes", "{}"),
        "header_accel_mm_s2": ("firmware ACCEL the output sets", "{:.0f} mm/s^2"),
        "clamped": ("samples clamped to the workspace (a correction past the firmware's limits: "
                    "z_max after a homing, the rim)", "{}"),
        "pinned_samples": ("samples held on the plan (retractions, dwells, z-hops)", "{}"),
        "pin_windows": ("windows re-solved around them", "{}"),
        "cap_windows": ("stretches brought within the delta cap", "{}"),
        "cap_max_change_um": ("  largest change of the command there", "{:.1f} um"),
        "hold_margins": ("rest margins around retractions (--hold-margin-ms)", "{}"),
        "hold_margin_time_s": ("time they add", "{:.2f} s"),
        "quiet_z_moves": ("z moves planned quiet (--quiet-z)", "{}"),
        "quiet_z_time_s": ("time they add", "{:.2f} s"),
        "lines_in": ("lines in", "{}"),
        "lines_out": ("lines out", "{}"),
        "segments": ("G1 segments written", "{}"),
        "micro_holds": ("short rest-to-rest moves written as holds (within --tol-um)", "{}"),
        "steps": ("steps written", "{}"),
        "max_step_error_steps": ("max reconstruction error", "{:.3f} steps"),
    }
    for k, (label, f) in fmt.items():
        v = d.get(k)
        if v is not None:
            t.add_row(label, f.format(v))
    if d.get("rms_before_um") and d.get("rms_after_um") is not None:
        t.add_row("predicted reduction", f"{(1 - d['rms_after_um'] / d['rms_before_um']) * 100:.1f} %")
    if d.get("commands_passed") is not None and "commands_stopped" in d:
        t.add_row("other lines: passed / baked in / stops / unknown / skipped",
                  f"{d['commands_passed']} / {d['commands_baked']} / {d['commands_stopped']} / "
                  f"{d['commands_unknown']} / {d['lines_skipped']}")
    if d.get("commands_synced"):
        t.add_row("M400 / M18 / M84 (the compensation settles and starts again at each)", f"{d['commands_synced']}")
    if d.get("firmware_retractions"):
        t.add_row("G10/G11 timed with [firmware_retraction]", f"{d['firmware_retractions']}")
    if d.get("input_shaper"):
        t.add_row("input shaper", escape(d["input_shaper"]))
    if "warnings" in d:
        t.add_row("warnings", f"{d['warnings']}" + ("  (listed below)" if d.get("notes") else ""))
    if d.get("stale_temps_removed"):
        t.add_row("stale temp files removed (killed runs)", f"{d['stale_temps_removed']}")
    err_console.print(t) if to_stderr else __import__("rich").get_console().print(t)
    for msg in d.get("notes") or []:
        err_console.print(f"[yellow]warning:[/] {escape(str(msg))}", highlight=False, soft_wrap=True)

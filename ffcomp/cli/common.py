"""Shared pieces of the CLI: the typer app, the rich consoles, option types and error handling."""

from __future__ import annotations

import json
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Annotated, Any, Optional

import numpy as np
import typer
from rich.console import Console
from rich.markup import escape

from ..errors import FfcompError, Interrupted

app = typer.Typer(
    name="ffcomp",
    help="Model-based feedforward vibration compensation for delta 3D printers.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)

ProfileOpt = Annotated[
    Optional[Path],
    typer.Option("--profile", "-p", help="Printer profile TOML (default: the embedded Monoprice Delta Pro)."),
]
JsonOpt = Annotated[bool, typer.Option("--json", help="Print a machine-readable JSON result on stdout.")]
PlotOpt = Annotated[Optional[Path], typer.Option("--plot", help="Write a PNG figure to this file.")]


def load_profile_opt(path: Optional[Path]):
    from ..profile import load_profile

    return load_profile(path)


def _jsonable(o: Any):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, complex):
        return [o.real, o.imag]
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def print_json(obj: Any) -> None:
    """Write ``obj`` as JSON to stdout: numpy arrays become lists, NaN and +-Infinity (not JSON) null."""
    from ..report.json_safe import finite_json

    sys.stdout.write(json.dumps(finite_json(obj), default=_jsonable, indent=2, allow_nan=False) + "\n")
    sys.stdout.flush()


def parse_triple(text: str, what: str = "--at") -> tuple[float, float, float]:
    """``"x,y,z"`` -> floats, with an error naming the option and value."""
    parts = [p for p in text.replace(" ", "").split(",") if p != ""]
    try:
        vals = tuple(float(p) for p in parts)
    except ValueError:
        raise typer.BadParameter(f"{what} expects X,Y,Z in mm, got {text!r}") from None
    if len(vals) != 3:
        raise typer.BadParameter(f"{what} expects three comma-separated numbers X,Y,Z in mm, got {text!r}")
    return vals  # type: ignore[return-value]


#: signals that stop a run cleanly (``finally`` blocks run, temporary files go, exit 128 + signum)
_STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))
_STOPPING = False  # set once a stop signal is being handled: the process is on its way out
_UNCHANGED = "files are replaced only when complete, so the input and any existing output are unchanged"


def _raise_interrupted(signum, frame):
    from ..io_atomic import request_stop

    # a second signal while unwinding must not cut the clean-up short
    for s in _STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    request_stop(signum)  # (kept: an exception raised inside a destructor is swallowed)
    raise Interrupted(signum)


def _install_signal_handlers() -> dict | None:
    """Route SIGINT/SIGTERM/SIGHUP to :class:`Interrupted`; returns the old handlers (``None`` when
    not in the main thread, where handlers cannot be set)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    old = {}
    for s in _STOP_SIGNALS:
        prev = signal.getsignal(s)
        if prev is signal.SIG_IGN and s != signal.SIGINT:  # nohup: keep ignoring
            continue
        old[s] = prev
        signal.signal(s, _raise_interrupted)
    return old


def _interrupted(name: str, code: int) -> None:
    from ..io_atomic import cleanup_temps

    global _STOPPING
    _STOPPING = True
    for s in _STOP_SIGNALS:  # the process is ending: further signals must not cut the clean-up short
        signal.signal(s, signal.SIG_IGN)
    cleanup_temps()
    err_console.print(f"[bold red]interrupted[/] by {name}: stopped before finishing; {_UNCHANGED}; "
                      "temporary files removed", highlight=False, soft_wrap=True)
    sys.exit(code)


def run_app(argv: list[str]) -> None:
    """Run the typer app and turn every way it can end into a message and an honest exit code.

    * :class:`FfcompError`: a red one-line message, its exit code;
    * SIGINT / SIGTERM / SIGHUP: temporary files removed, a message, exit 128 + signum (130 for
      Ctrl-C, 143 for SIGTERM), never 0 (a slicer hook would ship the uncompensated file);
    * any other ``OSError`` (disk full, I/O error): a one-line message naming the file, exit 6.
    """
    from ..io_atomic import request_stop, stop_requested

    global _STOPPING
    _STOPPING = False
    request_stop(None)
    old = _install_signal_handlers()
    try:
        rv = app(args=argv, prog_name="ffcomp", standalone_mode=False)
        if stop_requested() is not None:  # a signal whose exception was swallowed: never exit 0 after it
            raise Interrupted(stop_requested())
        if rv == 130:  # typer turns a KeyboardInterrupt it sees into Exit(130) and *returns* it
            _interrupted("SIGINT", 130)
        if isinstance(rv, int) and rv:
            sys.exit(rv)
    except Interrupted as e:
        _interrupted(e.name, e.exit_code)
    except KeyboardInterrupt:
        _interrupted("SIGINT", 130)
    except FfcompError as e:  # escaped: messages hold "[printer]" and other brackets rich would eat
        err_console.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False, soft_wrap=True)
        sys.exit(e.exit_code)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except typer.Abort:
        _interrupted("aborted", 130)
    except OSError as e:
        where = f"{e.filename}: " if getattr(e, "filename", None) else ""
        err_console.print(f"[bold red]error:[/] {escape(where + str(e.strerror or e))}; {_UNCHANGED}", highlight=False,
                          soft_wrap=True)
        sys.exit(6)
    except Exception as e:  # click usage errors (typer may vendor its own click: duck-type them)
        if hasattr(e, "show") and isinstance(getattr(e, "exit_code", None), int):
            e.show()
            sys.exit(e.exit_code)
        raise
    finally:
        # restored for an in-process caller (tests) unless the run was interrupted: the process is then
        # exiting, and a restored default handler would turn a late second Ctrl-C into a kill by SIGINT
        if not _STOPPING:
            for s, h in (old or {}).items():
                signal.signal(s, h)


def _print_version(value: bool) -> None:
    if value:
        from .. import __version__

        typer.echo(f"ffcomp {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: Annotated[bool, typer.Option("--version", callback=_print_version, is_eager=True,
                                                help="Print the ffcomp version and exit.")] = False) -> None:
    """Model-based feedforward vibration compensation for delta 3D printers."""


#: ``--jobs/-j`` of the commands that compensate G-code (see :func:`resolve_jobs`)
JobsOpt = Annotated[int, typer.Option("--jobs", "-j", help="Worker processes: N > 1 cuts the file into N pieces "
                                      "where the toolhead stands still and compensates them in parallel; 0: one "
                                      "per core.")]


def resolve_jobs(jobs: int) -> int:
    """``--jobs``: 0 is one worker per core this process may use; negative values are refused."""
    if jobs < 0:
        raise typer.BadParameter(f"--jobs must be >= 0 (0: one per core), got {jobs}")
    return jobs or (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1)

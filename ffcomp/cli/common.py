"""Shared pieces of the CLI: the typer app, the rich consoles, option types and error handling."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Annotated, Any, Optional

import numpy as np
import typer
from rich.console import Console

from ..errors import FfcompError

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
    """Write ``obj`` as JSON to stdout (numpy arrays become lists)."""
    sys.stdout.write(json.dumps(obj, default=_jsonable, indent=2) + "\n")
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


def run_app(argv: list[str]) -> None:
    """Run the typer app; an :class:`FfcompError` becomes a red one-line message and its exit code."""
    try:
        app(args=argv, prog_name="ffcomp", standalone_mode=False)
    except FfcompError as e:
        from rich.markup import escape

        err_console.print(f"[bold red]error:[/] {escape(str(e))}", highlight=False, soft_wrap=True)
        sys.exit(e.exit_code)
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except typer.Abort:
        err_console.print("aborted")
        sys.exit(130)
    except Exception as e:  # click usage errors (typer may vendor its own click: duck-type them)
        if hasattr(e, "show") and isinstance(getattr(e, "exit_code", None), int):
            e.show()
            sys.exit(e.exit_code)
        raise

"""ffcomp command line: a thin typer layer over :mod:`ffcomp.pipeline` and the kernels.

Each command group lives in its own small module and registers itself on :data:`app`; every command
parses options, calls one plain function that returns an object, and prints or writes it.
"""

from __future__ import annotations

import gc
import os
import sys

# our matrices are small: BLAS threads only contend (set before numpy loads)
for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

from .common import app, run_app  # noqa: E402  (after the thread settings)

# command modules register themselves on ``app`` when imported
_COMMAND_MODULES = ("compensate_cmd", "model_cmds", "identify_cmd", "plan_cmd", "profile_cmds", "validate_cmds",
                    "sim_cmds", "hook_cmd", "firmware_cmd")


def _load_commands() -> None:
    import importlib

    for name in _COMMAND_MODULES:
        try:
            importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as e:  # a command module not written yet
            if e.name != f"{__name__}.{name}":
                raise


def main(argv: list[str] | None = None) -> None:
    """Console-script entry point; ``ffcomp IN.gcode -o OUT.gcode`` means ``ffcomp compensate ...``."""
    _load_commands()
    # the parser and the planners make millions of short-lived objects (records, moves) and hardly
    # any reference cycles: a large young generation keeps the cyclic collector from scanning them
    # over and over (3% of a compensation's time with the default 700)
    gc.set_threshold(100_000, 50, 100)
    argv = list(sys.argv[1:] if argv is None else argv)
    names = {c.name for c in app.registered_commands} | {g.name for g in app.registered_groups}
    first = next((a for a in argv if not a.startswith("-")), None)
    if first is not None and first not in names and "compensate" in names and (
        first.endswith((".gcode", ".gco", ".g")) or first == "-" or "/" in first or "." in first
    ):
        argv.insert(argv.index(first), "compensate")
    run_app(argv)


__all__ = ["app", "main"]

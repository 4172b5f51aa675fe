"""Run the CLI in-process and capture its exit code and output."""

from __future__ import annotations

import json


def run(capsys, *args) -> tuple[int, str, str]:
    from ffcomp.cli import main

    code = 0
    try:
        main([str(a) for a in args])
    except SystemExit as e:
        code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    out = capsys.readouterr()
    return code, out.out, out.err


def run_json(capsys, *args):
    code, out, err = run(capsys, *args, "--json")
    assert code == 0, err
    return json.loads(out)

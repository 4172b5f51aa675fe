"""The ffcomp error family.

Every error is also a built-in exception type, so callers that do not know ffcomp can still
catch ``ValueError`` or ``OSError``.  Each carries enough context (file, line, key, value) to be
shown to a user as it is; the CLI prints ``str(err)`` and exits with a non-zero status.
"""

from __future__ import annotations


class FfcompError(Exception):
    """Base of all errors ffcomp raises on purpose."""

    exit_code = 1


class ProfileError(FfcompError, ValueError):
    """A printer profile value is missing, malformed or physically impossible.

    Parameters
    ----------
    key : str
        Dotted key in the profile, e.g. ``"geometry.arm_length_mm"``.
    value : object
        The offending value.
    reason : str
        What is wrong with it.
    source : str, optional
        File the profile came from.
    """

    exit_code = 2

    def __init__(self, key: str, value, reason: str, source: str | None = None):
        self.key, self.value, self.reason, self.source = key, value, reason, source
        where = f"{source}: " if source else ""
        super().__init__(f"{where}profile key '{key}' = {value!r}: {reason}")


class MeasurementError(FfcompError, ValueError):
    """A measurement (FRF) file is malformed: names the file, line and value."""

    exit_code = 2

    def __init__(self, path: str, line: int | None, reason: str, text: str | None = None):
        self.path, self.line, self.reason, self.text = path, line, reason, text
        loc = f"{path}:{line}" if line is not None else f"{path}"
        tail = f" (line text: {text!r})" if text is not None else ""
        super().__init__(f"{loc}: {reason}{tail}")


class GcodeError(FfcompError, ValueError):
    """A G-code line cannot be parsed or executed: names the file, line number and text."""

    exit_code = 3

    def __init__(self, path: str, line: int, reason: str, text: str | None = None):
        self.path, self.line, self.reason, self.text = path, line, reason, text
        tail = f": {text.strip()!r}" if text is not None else ""
        super().__init__(f"{path}:{line}: {reason}{tail}")


class KinematicsError(FfcompError, ValueError):
    """A position is outside the reachable workspace (or a carriage set has no pose)."""

    exit_code = 3


class SolverError(FfcompError, RuntimeError):
    """A numerical solver (least squares, OSQP, fit) failed or returned an unusable answer."""

    exit_code = 4


class SelfCheckError(FfcompError, RuntimeError):
    """The re-planned output strays from the intended carriage commands beyond tolerance."""

    exit_code = 5


class OutputError(FfcompError, OSError):
    """An output file cannot be written (missing directory, read-only file system, no permission,
    no space left, a directory named as the file).  Raised before any work where it can be foreseen.

    Parameters
    ----------
    path : str
        The output path (or directory) concerned.
    cause : OSError or int or None
        The underlying error, or its ``errno``.
    reason : str
        What could not be done.
    """

    exit_code = 6

    def __init__(self, path: str, cause, reason: str):
        import os

        code = cause.errno if isinstance(cause, OSError) else cause
        detail = os.strerror(code) if code else ""
        msg = f"{path}: {reason}" + (f": {detail}" if detail and detail.lower() not in reason.lower() else "")
        super().__init__(msg)
        self.errno = code
        self.filename = path
        self.path, self.reason, self.message = path, reason, msg

    def __str__(self) -> str:
        return self.message


class Interrupted(BaseException):
    """A termination signal (SIGINT, SIGTERM, SIGHUP) arrived: unwinds like ``KeyboardInterrupt`` so
    that every ``finally`` runs (temporary files removed, the output left as it was), then the CLI
    exits with ``128 + signum``.  A ``BaseException`` so that ``except Exception`` does not swallow it.
    """

    def __init__(self, signum: int):
        import signal

        self.signum = signum
        self.exit_code = 128 + signum
        try:
            self.name = signal.Signals(signum).name
        except ValueError:
            self.name = f"signal {signum}"
        super().__init__(self.name)

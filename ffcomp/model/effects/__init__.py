"""Physical effects beyond the paper's model, each a small module registered in :data:`EFFECTS`.

An effect adds a few named parameters and acts on the linearised per-pose matrices
(:class:`~ffcomp.model.lpv.PoseMatrices`): mass, damping, stiffness, input coupling, drive filter.
Because the model, the simulator and the compensation all build their dynamics from those
matrices, every stage honours an effect once it is in the profile's ``[[effects]]`` list.

Writing an effect: subclass :class:`Effect`, declare ``name`` and ``params`` (name ->
:class:`Param`), implement ``apply``, and add the class to :data:`EFFECTS` below.

Plug-ins (effects users write, without editing ffcomp): a Python file or an importable module
that subclasses :class:`Effect` and decorates it with :func:`register`; an ``[[effects]]`` entry
names it with ``plugin = "path/to/file.py"`` (relative to the profile's directory or the working
directory) or ``plugin = "package.module"``, and ``ffcomp fit/diagnose/virtual-measure --plugin``
load it for the command line.  Loading a plug-in runs its code: use only files you trust.  See
``docs/effects_example_motor_mount.py``.

Optional hooks used by ``ffcomp diagnose`` / ``ffcomp fit`` (:mod:`ffcomp.loop.fit`):
``fit`` names the parameters fitted by default (empty: all), :attr:`Param.search` the plausible
range the fit starts from and is bounded by, ``summary`` a one-line description and
:meth:`Effect.explain` the fitted values read back in physical words.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...errors import ProfileError

__all__ = ["Param", "Effect", "EFFECTS", "build_effects", "validate_effects", "register", "load_library",
           "load_plugin", "with_plugin_refs"]


@dataclass(frozen=True)
class Param:
    """One effect parameter: default value, unit, admissible range, meaning."""

    default: float
    unit: str
    lo: float = float("-inf")
    hi: float = float("inf")
    doc: str = ""
    #: plausible (lo, hi) for fitting: start grid and bounds of ``ffcomp diagnose``/``fit`` (None: lo, hi)
    search: tuple[float, float] | None = None

    @property
    def fit_range(self) -> tuple[float, float]:
        """Bounds used when fitting: :attr:`search` if given, else ``(lo, hi)``."""
        return self.search if self.search is not None else (self.lo, self.hi)


class Effect:
    """Base class: holds parameter values; ``apply`` returns modified pose matrices."""

    name: ClassVar[str] = ""
    params: ClassVar[dict[str, Param]] = {}
    #: parameters fitted by default (diagnose, fit); empty means all of ``params``
    fit: ClassVar[tuple[str, ...]] = ()
    #: one-line description (the physics) for listings
    summary: ClassVar[str] = ""
    #: start a fit from a grid over the search ranges (False: from the defaults, e.g. scale factors at 1)
    grid: ClassVar[bool] = True
    #: where a plug-in effect was loaded from (written back into ``[[effects]]`` as ``plugin``)
    plugin: ClassVar[str | None] = None
    #: parameters held fixed when the base dynamics are refitted with the effect (they would be
    #: degenerate with it, e.g. tower A's scale factors with the base m, k, c)
    base_fixed: ClassVar[tuple[str, ...]] = ()

    @classmethod
    def fit_params(cls) -> tuple[str, ...]:
        return tuple(cls.fit) if cls.fit else tuple(cls.params)

    @classmethod
    def primary(cls) -> str:
        """The parameter ``NAME=VALUE`` sets (first fitted parameter)."""
        return cls.fit_params()[0]

    def __init__(self, **values):
        unknown = set(values) - set(self.params)
        if unknown:
            raise ValueError(f"effect {self.name!r} has no parameter(s) {sorted(unknown)}; "
                             f"known: {sorted(self.params)}")
        self.values = {k: float(values.get(k, p.default)) for k, p in self.params.items()}
        for k, v in self.values.items():
            p = self.params[k]
            if not (p.lo <= v <= p.hi):
                raise ValueError(f"effect {self.name!r} parameter {k} = {v} outside [{p.lo}, {p.hi}] {p.unit}")

    def __getattr__(self, item):
        try:
            return self.__dict__["values"][item]
        except KeyError:
            raise AttributeError(item) from None

    def apply(self, mats, model):  # pragma: no cover - abstract
        raise NotImplementedError

    def to_dict(self) -> dict:
        return {"name": self.name, **self.values}

    def explain(self, model) -> str:
        """The parameter values in words (override to say what they mean physically)."""
        return ", ".join(f"{k} = {v:.4g} {self.params[k].unit}".rstrip() for k, v in self.values.items())

    def __repr__(self) -> str:
        vals = ", ".join(f"{k}={v:g}" for k, v in self.values.items())
        return f"{self.name}({vals})"


#: name -> Effect subclass
EFFECTS: dict[str, type[Effect]] = {}


def register(cls: type[Effect]) -> type[Effect]:
    EFFECTS[cls.name] = cls
    return cls


def _load_library() -> None:
    import importlib
    import pkgutil

    for mod in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{mod.name}")


def load_library() -> dict[str, type[Effect]]:
    """Import every effect module and return :data:`EFFECTS`."""
    _load_library()
    return EFFECTS


_PLUGINS: dict[str, list[str]] = {}


def load_plugin(ref: str, base_dir=None) -> list[str]:
    """Import a plug-in and return the names of the effects it registered.

    Parameters
    ----------
    ref : str
        A ``.py`` file (absolute, or relative to ``base_dir`` or the working directory) or the
        dotted name of an importable module (an installed package).
    base_dir : str or Path, optional
        Directory relative file paths are tried against first (the profile's).

    Raises
    ------
    ValueError
        The file or module cannot be found or imported (the message names it).
    """
    import importlib
    import importlib.util
    import sys
    from pathlib import Path

    _load_library()
    ref = str(ref)
    before = dict(EFFECTS)
    if ref.endswith(".py") or "/" in ref or "\\" in ref:
        cands = [Path(ref)] if Path(ref).is_absolute() else (
            ([Path(base_dir) / ref] if base_dir else []) + [Path.cwd() / ref])
        path = next((c for c in cands if c.is_file()), None)
        if path is None:
            raise ValueError(f"effect plug-in {ref!r}: no such file (tried {', '.join(str(c) for c in cands)})")
        key = str(path.resolve())  # cached by the file it resolves to, not by the (relative) name
        if key in _PLUGINS:
            return _PLUGINS[key]
        modname = "ffcomp_plugin_" + "".join(ch if ch.isalnum() else "_" for ch in path.stem) + f"_{len(_PLUGINS)}"
        spec = importlib.util.spec_from_file_location(modname, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[modname] = module
        try:
            spec.loader.exec_module(module)
        except Exception as e:  # the user's code: report it with the file
            del sys.modules[modname]
            raise ValueError(f"effect plug-in {path}: {type(e).__name__}: {e}") from e
    else:
        key = ref
        if key in _PLUGINS:
            return _PLUGINS[key]
        try:
            importlib.import_module(ref)
        except ImportError as e:
            raise ValueError(f"effect plug-in {ref!r}: cannot import it ({e})") from e
    new = [n for n, c in EFFECTS.items() if before.get(n) is not c]
    if not new:
        raise ValueError(f"effect plug-in {ref!r} registered no effect (decorate an Effect subclass with "
                         "@ffcomp.model.effects.register)")
    for n in new:
        EFFECTS[n].plugin = key  # a file by its absolute path: the profile that names it may live anywhere
    _PLUGINS[key] = new
    return new


def with_plugin_refs(specs) -> tuple:
    """Effect entries with ``plugin = ...`` added for effects that came from a plug-in."""
    out = []
    for e in specs:
        e = dict(e)
        cls = EFFECTS.get(e.get("name"))
        if cls is not None and cls.plugin and "plugin" not in e:
            e["plugin"] = cls.plugin
        out.append(e)
    return tuple(out)


def build_effects(specs, base_dir=None) -> list[Effect]:
    """Instantiate effects from profile entries ``{"name": ..., param: value}`` (``plugin`` loaded first)."""
    _load_library()
    out = []
    for i, spec in enumerate(specs):
        spec = dict(spec)
        ref = spec.pop("plugin", None)
        if ref is not None:
            try:
                load_plugin(ref, base_dir)
            except ValueError as e:
                raise ProfileError(f"effects[{i}].plugin", ref, str(e)) from e
        name = spec.pop("name")
        if name not in EFFECTS:
            raise ProfileError(f"effects[{i}].name", name, f"unknown effect (known: {', '.join(sorted(EFFECTS))})")
        try:
            out.append(EFFECTS[name](**spec))
        except (ValueError, TypeError) as e:
            raise ProfileError(f"effects[{i}]", spec, str(e)) from e
    return out


def validate_effects(profile) -> None:
    """Raise :class:`ProfileError` if any ``[[effects]]`` entry is unknown or out of range."""
    from pathlib import Path

    base_dir = Path(profile.source).parent if profile.source and not str(profile.source).startswith("<") else None
    try:
        build_effects(profile.effects, base_dir)
    except ProfileError as e:
        raise ProfileError(e.key, e.value, e.reason, profile.source) from None

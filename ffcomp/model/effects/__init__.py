"""Physical effects beyond the paper's model, each a small module registered in :data:`EFFECTS`.

An effect adds a few named parameters and acts on the linearised per-pose matrices
(:class:`~ffcomp.model.lpv.PoseMatrices`): mass, damping, stiffness, input coupling, drive filter.
Because the model, the simulator and the compensation all build their dynamics from those
matrices, every stage honours an effect once it is in the profile's ``[[effects]]`` list.

Writing an effect: subclass :class:`Effect`, declare ``name`` and ``params`` (name ->
:class:`Param`), implement ``apply``, and add the class to :data:`EFFECTS` below.

Optional hooks used by ``ffcomp diagnose`` / ``ffcomp fit`` (:mod:`ffcomp.loop.fit`):
``fit`` names the parameters fitted by default (empty: all), :attr:`Param.search` the plausible
range the fit starts from and is bounded by, ``summary`` a one-line description and
:meth:`Effect.explain` the fitted values read back in physical words.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from ...errors import ProfileError

__all__ = ["Param", "Effect", "EFFECTS", "build_effects", "validate_effects", "register", "load_library"]


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


def build_effects(specs) -> list[Effect]:
    """Instantiate effects from profile entries ``{"name": ..., param: value}``."""
    _load_library()
    out = []
    for i, spec in enumerate(specs):
        spec = dict(spec)
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
    try:
        build_effects(profile.effects)
    except ProfileError as e:
        raise ProfileError(e.key, e.value, e.reason, profile.source) from None

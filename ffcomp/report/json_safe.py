"""JSON that parsers accept: NaN and +-Infinity (not JSON) become ``null``; numpy types become Python."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["finite_json"]


def finite_json(obj: Any) -> Any:
    """A copy of ``obj`` (dicts, lists, tuples, numpy arrays and scalars) with non-finite floats as None."""
    if isinstance(obj, dict):
        return {str(k): finite_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return finite_json(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj

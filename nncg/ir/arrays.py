"""Constant data of both IRs compared as data: IR equality includes the weights."""

from __future__ import annotations

import numpy as np


def same_arrays(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    """Whether two name -> array maps hold the same arrays (dtype, shape and values; NaN equals NaN)."""
    return a.keys() == b.keys() and all(
        a[k].dtype == b[k].dtype and a[k].shape == b[k].shape and np.array_equal(a[k], b[k], equal_nan=True) for k in a
    )

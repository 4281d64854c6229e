"""BatchNormalization at inference as a per-channel scale and shift: the formula fold-batchnorm folds
into the producing Conv and the lowering applies when nothing can absorb it."""

from __future__ import annotations

import numpy as np

from .graph import Node


def scale_shift_of_batchnorm(constants: dict[str, np.ndarray], node: Node) -> tuple[np.ndarray, np.ndarray]:
    """BatchNorm as y = x * scale + shift, with scale = gamma / sqrt(var + eps)."""
    gamma, beta, mean, var = (constants[name].astype(np.float64) for name in node.inputs[1:5])
    scale = gamma / np.sqrt(var + node.attrs.epsilon)
    return scale.astype(np.float32), (beta - mean * scale).astype(np.float32)

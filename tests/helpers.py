"""Shared test helpers: check a compiled model against onnxruntime with nncg.verify."""

from __future__ import annotations

from typing import Any

import onnx

from nncg.ir.target import Target
from nncg.verify import VerifyReport, verify


def check_against_onnxruntime(
    model_proto: onnx.ModelProto,
    compiled: Any,
    *,
    sanitize: bool = False,
    tolerance: float = 1e-4,
    seed: int = 0,
    opt: str = "-O2",
) -> VerifyReport:
    """Compile and run `compiled`, compare with onnxruntime; fails with the report's table."""
    report = verify(model_proto, compiled, seed=seed, tolerance=tolerance, sanitize=sanitize, opt=opt)
    assert report.ok, report.format()
    return report


def target(*widths: int, registers: int = 16, fma: bool = False) -> Target:
    """A target with these vector widths (widest first) and registers, for pass tests."""
    return Target("test", tuple(widths), registers, fma)

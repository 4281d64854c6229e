"""Shared test helpers: building small ONNX models, checking a compiled model against onnxruntime
with nncg.verify, and running the command line."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

import nncg
from nncg.backends.ansi_c import AnsiC
from nncg.backends.scalar_math import helper_definitions, helper_name
from nncg.host_cpu import TARGET_CPU_FLAGS, cpu_flags
from nncg.ir.target import Target
from nncg.verify import VerifyReport, verify

# A float32 tensor's shape (dims may be names; None: unknown), or a ValueInfoProto for any other type.
Shape = Sequence[int | str] | None
ValueSpec = Shape | onnx.ValueInfoProto

RNG = np.random.default_rng(1234)
ROOT = Path(__file__).resolve().parent.parent
NNCG_CLI = (sys.executable, "-m", "nncg")  # run from ROOT: this checkout's nncg, not an installed one
CLI_TIMEOUT_S = 600


def onnx_model(
    nodes: Iterable[onnx.NodeProto],
    *,
    inputs: Mapping[str, ValueSpec],
    outputs: Mapping[str, ValueSpec] | Sequence[str] = ("y",),
    initializers: Mapping[str, Any] | None = None,
    opset: int = 13,
    ir_version: int = 8,
) -> onnx.ModelProto:
    """A model of `nodes` in graph "test".

    `inputs` and `outputs` map each name to a float32 shape or a ValueInfoProto; outputs given as
    names are float32 of unknown shape. `initializers` map names to arrays, which keep their dtype."""
    graph = helper.make_graph(
        list(nodes),
        "test",
        _value_infos(inputs),
        _value_infos(outputs),
        [numpy_helper.from_array(np.asarray(array), name) for name, array in (initializers or {}).items()],
    )
    return helper.make_model(graph, opset_imports=[helper.make_opsetid("", opset)], ir_version=ir_version)


def _value_infos(values: Mapping[str, ValueSpec] | Sequence[str]) -> list[onnx.ValueInfoProto]:
    specs = values if isinstance(values, Mapping) else dict.fromkeys(values)
    return [_value_info(name, spec) for name, spec in specs.items()]


def _value_info(name: str, spec: ValueSpec) -> onnx.ValueInfoProto:
    if not isinstance(spec, onnx.ValueInfoProto):
        return helper.make_tensor_value_info(name, TensorProto.FLOAT, spec)
    if spec.name != name:
        raise ValueError(f"value {name!r} is given a ValueInfoProto named {spec.name!r}")
    return spec


def weights(*shape: int) -> np.ndarray:
    """Fixed-seed float32 weights of this shape, scaled by the fan-in (the product of all but the first dim)."""
    return (RNG.standard_normal(shape) / np.sqrt(np.prod(shape[1:]) or 1)).astype(np.float32)


HOST = set(cpu_flags())


def missing_flags(target: str) -> set[str]:
    """The CPU flags `target`'s code needs that this host lacks (empty: it runs here)."""
    return set(TARGET_CPU_FLAGS.get(target, ())) - HOST


def skip_unless_host_runs(target: str) -> None:
    """Skips the test when this host's CPU cannot run `target`'s code (avx512 on an AVX2-only core)."""
    missing = missing_flags(target)
    if missing:
        import pytest

        pytest.skip(f"the host CPU lacks {', '.join(sorted(missing))}")


def check_against_onnxruntime(
    model_proto: onnx.ModelProto,
    compiled: Any,
    *,
    sanitize: bool = False,
    tolerance: float = 1e-4,
    seed: int = 0,
    opt: str = "-O2",
) -> VerifyReport:
    """Compile and run `compiled`, compare with onnxruntime; fails with the report's table (skips where
    the host cannot run the target's code)."""
    skip_unless_host_runs(compiled.target)
    report = verify(model_proto, compiled, seed=seed, tolerance=tolerance, sanitize=sanitize, opt=opt)
    assert report.ok, report.format()
    return report


def compile_and_check(model_proto: onnx.ModelProto, target: str, unroll: Any = 1, sanitize: bool = False) -> Any:
    """Compile with the IR verified after every pass, then check against onnxruntime; the CompiledModel."""
    compiled = nncg.compile(model_proto, target=target, unroll=unroll, verify_ir=True)
    check_against_onnxruntime(model_proto, compiled, sanitize=sanitize)
    return compiled


def kernel_ops(compiled: Any) -> list[str]:
    """The op of every kernel in the generated C, in order (from the `/* layer: Op */` comments)."""
    return re.findall(r"^/\* \w+: (\w+) \*/$", compiled.source, re.M)


def target(*widths: int, registers: int = 16, fma: bool = False) -> Target:
    """A target with these vector widths (widest first) and registers, for pass tests."""
    return Target("test", tuple(widths), registers, fma)


def nncg_onnx(*args: object, umask: int | None = None) -> subprocess.CompletedProcess:
    """Run the command line with these arguments from the repository root (under `umask` when
    given); its exit status and output as text."""
    preexec = None if umask is None else (lambda: os.umask(umask))
    command = [*NNCG_CLI, *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=CLI_TIMEOUT_S, preexec_fn=preexec)


def scalar_math_values(fn: str, x: np.ndarray, workdir: Path) -> np.ndarray:
    """The generated scalar helper of math function `fn` (backends/scalar_math.py) applied to each x,
    built with the ansi-c target's strict C89 flags."""
    lines = [
        "#include <stdio.h>",
        "#include <math.h>",
        *helper_definitions({fn}),
        "",
        "int main(void)",
        "{",
        "    float v;",
        "    while (fread(&v, sizeof v, 1, stdin) == 1) {",
        f"        v = {helper_name(fn)}(v);",
        "        fwrite(&v, sizeof v, 1, stdout);",
        "    }",
        "    return 0;",
        "}",
    ]
    source, exe = Path(workdir) / f"{fn}.c", Path(workdir) / fn
    source.write_text("\n".join(lines) + "\n")
    subprocess.run(["gcc", "-O2", *AnsiC.strict_cflags, str(source), "-o", str(exe), "-lm"], check=True)
    out = subprocess.run([str(exe)], input=x.astype(np.float32).tobytes(), capture_output=True, check=True).stdout
    return np.frombuffer(out, np.float32)

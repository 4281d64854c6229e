"""Per-layer verification (`--verify --per-layer`), the paper's debugging workflow: every layer's
output of the generated C against onnxruntime's, so a wrong result is traced to the first layer
that goes wrong.

The C is a debug build (compile(..., expose_layers=True)) whose function also writes every value
the program stores; onnxruntime gets the same tensors as extra graph outputs. Only tensors that
still exist after the passes are compared: the ONNX nodes NNCG fused away (BatchNorm folded into a
Conv, an activation applied at its producer's store, cancelled transposes) are reported in the row
of the next compared tensor, as fused."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import onnx
from onnx import TensorProto, helper

from .compiler import compile as compile_model
from .errors import NncgError
from .frontend import load_model
from .frontend.names import node_names
from .frontend.shapes import infer
from .quant_steps import tensor_steps
from .safe_text import capped, escaped, terminal_line
from .verify import ErrorStat, compare, random_inputs, reference_outputs, requirement, run_compiled


@dataclass(frozen=True)
class LayerStat:
    """One compared tensor: the ONNX nodes (name, op type) whose work it holds, in graph order (the
    last produces it; more than one: fused), and its errors."""

    nodes: tuple[tuple[str, str], ...]
    stat: ErrorStat

    @property
    def fused(self) -> bool:
        return len(self.nodes) > 1

    def exceeds(self, tolerance: float) -> bool:
        return not self.stat.passes(tolerance)

    def cells(self, steps: bool = False) -> tuple[str, ...]:
        """The row's cells; `steps` adds max steps and identical (a quantised model's table)."""
        layer = capped(escaped("+".join(name for name, _ in self.nodes)))
        op = capped(escaped("+".join(op for _, op in self.nodes))) + (" (fused)" if self.fused else "")
        s = self.stat
        cells = (layer, op, capped(escaped(s.name)), str(s.shape), f"{s.max_abs:.3g}", f"{s.max_rel:.3g}")
        return cells + (s.step_cells() if steps else ())

    def excess(self, tolerance: float) -> str:
        """How this layer's error breaks its rule, for the FAIL line."""
        s = self.stat
        if s.max_steps is not None:
            return f"max steps {s.max_steps:.3g} > 1"
        return f"max rel err {s.max_rel:.3g} > {tolerance:g}"


@dataclass(frozen=True)
class LayerReport:
    """The outcome of verify_per_layer(): one row per compared tensor, in execution order."""

    name: str
    target: str
    layers: tuple[LayerStat, ...]
    tolerance: float
    seed: int

    @property
    def first_failure(self) -> LayerStat | None:
        """The first layer (in execution order) whose error exceeds the tolerance or is not comparable."""
        return next((layer for layer in self.layers if layer.exceeds(self.tolerance)), None)

    @property
    def ok(self) -> bool:
        return self.first_failure is None

    def format(self) -> str:
        steps = any(layer.stat.quantized for layer in self.layers)
        rows = [
            ("layer", "op", "tensor", "shape", "max abs err", "max rel err")
            + (("max steps", "identical") if steps else ())
        ]
        rows += [layer.cells(steps) for layer in self.layers]
        widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
        lines = [f"verify per layer {self.name} (target {self.target}, seed {self.seed})"]
        lines += ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
        lines += [f"{row.cells()[2]}: {terminal_line(row.stat.problem)}" for row in self.layers if row.stat.problem]
        failure = self.first_failure
        if failure is None:
            rule = requirement([layer.stat for layer in self.layers], self.tolerance)
            lines.append(f"PASS: every layer's {rule}")
        else:
            layer, op, tensor = failure.cells()[:3]
            lines.append(
                f"FAIL: first layer above tolerance: {layer} ({op}), tensor {tensor}: {failure.excess(self.tolerance)}"
            )
        return "\n".join(lines)


def verify_per_layer(
    model: str | os.PathLike | bytes | onnx.ModelProto,
    target: str = "ansi-c",
    *,
    seed: int = 0,
    tolerance: float = 1e-4,
    cc: str | None = None,
    sanitize: bool = False,
    opt: str = "-O2",
    extra_cflags: Sequence[str] = (),
    runner: Sequence[str] = (),
    input_shapes: dict[str, tuple[int, ...]] | None = None,
    **compile_options: Any,
) -> LayerReport:
    """Compiles the debug build of `model` for `target` (compile_options go to nncg.compile) and
    compares every layer's output with onnxruntime's on the same fixed-seed inputs (see verify_layers)."""
    compiled = compile_model(model, target, input_shapes=input_shapes, expose_layers=True, **compile_options)
    opts = dict(seed=seed, tolerance=tolerance, cc=cc, sanitize=sanitize, opt=opt, extra_cflags=extra_cflags)
    return verify_layers(load_model(model, input_shapes), compiled, runner=runner, **opts)


def verify_layers(
    model: onnx.ModelProto,
    compiled: Any,
    *,
    seed: int = 0,
    tolerance: float = 1e-4,
    cc: str | None = None,
    sanitize: bool = False,
    opt: str = "-O2",
    extra_cflags: Sequence[str] = (),
    runner: Sequence[str] = (),
) -> LayerReport:
    """Runs `compiled`, a debug build of `model` (compile(..., expose_layers=True)), and onnxruntime on
    the same inputs; compares every exposed output that is an ONNX tensor computed by a node."""
    model_outputs = len(model.graph.output)
    if len(compiled.outputs) <= model_outputs:
        raise NncgError(f"{compiled.name} exposes no layers: compile it with expose_layers=True")
    producers = {out for node in model.graph.node for out in node.output if out}
    exposed = [i for i, p in enumerate(compiled.outputs) if i >= model_outputs and p.name in producers]
    names = [compiled.outputs[i].name for i in exposed]
    inputs = random_inputs(compiled.inputs, seed)
    outputs = run_compiled(
        compiled, inputs, cc=cc, sanitize=sanitize, opt=opt, extra_cflags=extra_cflags, runner=runner
    )
    references = reference_outputs(with_outputs(model, names), compiled.inputs, inputs, names)
    stats = compare([outputs[i] for i in exposed], references, names, tensor_steps(model))
    covered = covered_nodes(model.graph, names)
    layers = tuple(LayerStat(covered[stat.name], stat) for stat in stats)
    return LayerReport(compiled.name, compiled.target, layers, tolerance, seed)


def with_outputs(model: onnx.ModelProto, names: Sequence[str]) -> onnx.ModelProto:
    """A copy of `model` that also outputs the tensors `names`, typed by ONNX shape inference."""
    inferred = {v.name: v for v in infer(model).graph.value_info}
    extended = onnx.ModelProto()
    extended.CopyFrom(model)
    present = {v.name for v in model.graph.output}
    for name in (n for n in names if n not in present):
        extended.graph.output.append(inferred.get(name) or helper.make_tensor_value_info(name, TensorProto.FLOAT, None))
    return extended


def covered_nodes(graph: onnx.GraphProto, compared: Sequence[str]) -> dict[str, tuple[tuple[str, str], ...]]:
    """Compared tensor -> the ONNX nodes (name, op type; graph order) whose work it holds: its producer
    and, walking back through runtime tensors that are not compared (fused away), their producers.
    Each node goes to the first compared tensor (in `compared` order, execution order) reaching it."""
    names = node_names(graph)
    producer = {out: i for i, node in enumerate(graph.node) for out in node.output if out}
    runtime = _runtime_tensors(graph)
    stops = set(compared)
    claimed: set[int] = set()
    covered = {}
    for tensor in compared:
        found, stack = [], [producer[tensor]]
        while stack:
            index = stack.pop()
            if index in claimed:
                continue
            claimed.add(index)
            found.append(index)
            stack += [producer[i] for i in graph.node[index].input if i in runtime and i not in stops and i in producer]
        covered[tensor] = tuple((names[i], graph.node[i].op_type) for i in sorted(found))
    return covered


def _runtime_tensors(graph: onnx.GraphProto) -> set[str]:
    """Tensors that depend on a graph input (not folded to constants at compile time)."""
    initializers = {t.name for t in graph.initializer}
    runtime = {v.name for v in graph.input if v.name not in initializers}
    for node in graph.node:
        if any(name in runtime for name in node.input):
            runtime.update(out for out in node.output if out)
    return runtime

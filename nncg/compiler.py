"""The whole pipeline behind one call: import ONNX, run the passes, print C with a backend.

compiled = nncg.compile("robot.onnx", target="ssse3", unroll="1")
compiled.write("build/")          # build/robot.c, build/robot.h
"""

from __future__ import annotations

import hashlib
import os
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import onnx

from . import __version__
from .arguments import check_compile_arguments, check_write_arguments
from .backends import get_backend, get_target
from .backends.weights import external_weights, weights_blob
from .bench.macs import macs_by_layer
from .cmake import CMAKE_LISTS, cmake_file
from .errors import NncgError
from .frontend import import_onnx, load_model
from .frontend.io_quantization import io_quantization
from .frontend.keras_export import is_keras_model, is_keras_path, keras_layout, keras_to_onnx
from .frontend.layout import graph_layout, model_layout, with_input_layout
from .frontend.load import read_model
from .frontend.torch_export import DEFAULT_EXPORTER, export_onnx, is_torch_module
from .ir.c_names import program_name
from .ir.graph import Graph
from .ir.loops import Program
from .limits import check_program_limits
from .lowering.band_plan import describe_plan, layer_bound_bytes, plan_layers, whole_activation_bytes
from .options import CompileOptions
from .output_files import write_files
from .passes import PassManager, parse_pipeline
from .passes.expose_layers import with_exposed_layers
from .passes.unroll import CODE_BUDGET
from .safe_text import c_comment, capped, shown

if TYPE_CHECKING:
    import keras
    import torch


@dataclass(frozen=True)
class Param:
    """A parameter of the generated function: the ONNX tensor name, its C name, shape and element
    type (numpy's name: float32; int8 or uint8 for quantized values; int32 for ArgMax/ArgMin
    indices and the sums of a ConvInteger or MatMulInteger)."""

    name: str
    c_name: str
    shape: tuple[int, ...]
    dtype: str = "float32"


@dataclass(frozen=True)
class CompileRecord:
    """What --report shows beyond the C: the final program (its memory plan), the graph `lower`
    received (the graph passes' choices are in its node attributes), the program register-block
    received (its cost model's input), and the imported model's operators and parameter count."""

    program: Program
    lowered: Graph | None = None
    before_register_block: Program | None = None
    operators: tuple[tuple[str, int], ...] = ()  # (graph IR op as imported, nodes), most frequent first
    parameters: int = 0


@dataclass(frozen=True)
class CompiledModel:
    name: str
    target: str
    source: str
    header: str
    inputs: tuple[Param, ...]
    outputs: tuple[Param, ...]
    cflags: tuple[str, ...]
    strict_cflags: tuple[str, ...]
    pipeline: str
    layer_macs: tuple[tuple[str, int], ...] = ()  # (layer C name, multiply-accumulates), from the graph
    arena_bytes: int = 0  # NAME_ARENA_BYTES: the planned activation memory
    weights: bytes | None = None  # NAME.weights when the weights live in a file (the caller passes them)
    activation_bytes: int = 0  # all activation buffers side by side, without the plan's reuse
    record: CompileRecord | None = field(default=None, compare=False, repr=False)  # for --report

    @property
    def macs(self) -> int:
        return sum(m for _, m in self.layer_macs)

    def write(self, directory: str | os.PathLike, cmake: bool = False) -> tuple[Path, ...]:
        """Writes NAME.c, NAME.h (and NAME.weights; with `cmake`, a CMakeLists.txt defining the static
        library NAME, see nncg/cmake.py) all or nothing (see output_files); failures raise NncgError."""
        check_write_arguments(directory, cmake)
        return write_files(directory, self.files(directory, cmake))

    def files(self, directory: str | os.PathLike, cmake: bool = False) -> dict[str, bytes]:
        """What `write` writes into `directory`, by file name (a caller can add its own to the set)."""
        files = {f"{self.name}.c": self.source.encode(), f"{self.name}.h": self.header.encode()}
        if self.weights is not None:
            files[f"{self.name}.weights"] = self.weights
        if cmake:
            files[CMAKE_LISTS] = cmake_file(self, Path(directory))
        return files


def compile(
    model: str | os.PathLike | bytes | onnx.ModelProto | torch.nn.Module | keras.Model,
    target: str = "ansi-c",
    unroll: str | int | None = "auto",
    name: str | None = None,
    input_shapes: dict[str, tuple[int, ...]] | None = None,
    pipeline: str | None = None,
    print_ir_after_all: TextIO | None = None,
    verify_ir: bool = True,
    profile: bool = False,
    weights: str = "auto",
    code_budget: int | None = CODE_BUDGET,
    example_inputs: torch.Tensor | tuple[torch.Tensor, ...] | None = None,
    exporter: str = DEFAULT_EXPORTER,
    expose_layers: bool = False,
    input_layout: str | None = None,
    memory: str = "speed",
    ram_budget: int | None = None,
    requantize: str = "float",
) -> CompiledModel:
    """Compiles a model to C for `target`: ONNX (a file path, bytes or an onnx.ModelProto), a
    torch.nn.Module, exported in eval mode for inputs shaped like `example_inputs` (a float32 tensor or
    a tuple of them) by torch.onnx.export's `exporter`, "dynamo" (torch.export; needs onnxscript) or
    "torchscript" (see nncg/frontend/torch_export.py), or a keras.Model, .keras/.h5 file or SavedModel
    folder, converted by tf2onnx (needs the keras extra; see nncg/frontend/keras_export.py).
    `input_layout` ("nchw" or "nhwc"; None: the model's own, NHWC for Keras) is the layout the C
    function takes its 4-D inputs in (see nncg/frontend/layout.py). `unroll` is "auto" (small loops unrolled, see the
    unroll pass), a level (int: the paper's levels) or None/"none" for no unrolling; `pipeline`
    replaces the default pass pipeline entirely; `profile` adds per-layer timers to the generated
    code (for `--profile`; they need POSIX clock_gettime); `weights` is embed (static const arrays),
    bin (NAME.weights, passed by pointer) or auto (bin when large); `code_budget` caps the
    statements of the unrolled program (None: the paper's levels exactly); `expose_layers` makes the
    debug build of verify_per_layer: every layer's output, as a graph value after the passes, is an
    extra output of the function after the model's own (see passes/expose_layers.py). `memory` (speed,
    balanced, min) trades speed for activation memory, running chains of layers in bands of rows;
    `ram_budget` (bytes) asks for the fastest plan whose arena fits, and is refused with the
    smallest arena any plan reaches when none does (see nncg/lowering/band_plan.py). `requantize`
    ("float" or "fixed") is how an int8 model's integer layers scale their int32 results: onnxruntime's
    float arithmetic, or integers only (see nncg/lowering/requantize.py)."""
    check_compile_arguments(
        model, target, unroll, name, input_shapes, pipeline, print_ir_after_all, verify_ir, profile, weights,
        code_budget, example_inputs, exporter, expose_layers, input_layout, memory, ram_budget, requantize,
    )  # fmt: skip
    options = CompileOptions.of(unroll, weights, code_budget, pipeline, memory, ram_budget, requantize)
    backend = get_backend(target)
    source = model
    from_torch = is_torch_module(model)
    model, header_layout = onnx_model(model, input_layout, example_inputs, exporter)
    graph = import_onnx(model, input_shapes)
    integer_io = any(v.name in graph.dtypes for v in (*graph.inputs, *graph.outputs))
    io_quant = io_quantization(load_model(model, input_shapes)) if integer_io else {}

    def build(options: CompileOptions) -> CompiledModel:
        manager = PassManager(
            options.pass_pipeline(backend.target), backend.target, verify=verify_ir,
            print_ir_after_all=print_ir_after_all, keep_inputs=("lower", "register-block"),
        )  # fmt: skip
        program = manager.run(_with_name(graph, c_name))
        if expose_layers:
            program = with_exposed_layers(program)
        described = f"target={target} pipeline={manager.pipeline}" + (
            f" torch-exporter={exporter}" if from_torch else ""
        )
        if input_layout:
            described += f" input-layout={input_layout}"
        if input_shapes:
            shapes = ",".join(f"{capped(k)}={'x'.join(map(str, v))}" for k, v in input_shapes.items())
            described += " input-shape=" + shapes
        compiled = emit(
            program, target, described, _sha256(model), manager.pipeline, profile, header_layout,
            io_quantization=io_quant,
        )  # fmt: skip
        record = CompileRecord(
            program,
            manager.inputs.get("lower"),
            manager.inputs.get("register-block"),
            tuple(Counter(node.op for node in graph.nodes).most_common()),
            sum(int(array.size) for array in graph.constants.values()),
        )
        return replace(compiled, layer_macs=tuple(macs_by_layer(graph).items()), record=record)

    c_name = program_name(name or _default_name(source, graph.name))
    compiled = build(options)
    if ram_budget is None or compiled.arena_bytes <= ram_budget:
        return compiled
    # The planner's estimate fell short (alignment, fragmentation): aim lower once, then at the minimum.
    tighter = 2 * ram_budget - compiled.arena_bytes
    retries = (replace(options, ram_budget=tighter),) if tighter > 0 else ()
    for retry in (*retries, replace(options, memory="min", ram_budget=None)):
        compiled = build(retry)
        if compiled.arena_bytes <= ram_budget:
            return compiled
    raise NncgError(
        f"the RAM budget of {ram_budget} bytes cannot be met: the smallest activation arena is "
        f"{compiled.arena_bytes} bytes (--memory min)"
    )


@dataclass(frozen=True)
class MemoryFigures:
    """The arena's yardsticks, from the graph lower received: the layer-by-layer bound (the most a
    layer computed whole needs), all activations side by side, and the band plan lower chose."""

    layer_bound_bytes: int
    all_activation_bytes: int
    plan: str


def memory_figures(compiled: CompiledModel) -> MemoryFigures | None:
    """None when the compile record has no graph (a program printed by emit alone)."""
    graph = compiled.record.lowered if compiled.record else None
    if graph is None:
        return None
    lower = next(spec for spec in parse_pipeline(compiled.pipeline) if spec.name == "lower")
    params = dict(lower.params)
    memory, budget = params.get("memory", "speed"), int(params.get("budget", 0))
    plan = plan_layers(graph, memory, budget, get_target(compiled.target), params.get("requantize", "float"))
    return MemoryFigures(layer_bound_bytes(graph), whole_activation_bytes(graph), describe_plan(plan.groups))


def onnx_model(model, input_layout: str | None = None, example_inputs=None, exporter: str = DEFAULT_EXPORTER):
    """What compile() imports: `model` as ONNX (a torch or Keras model exported, a Keras file converted;
    an ONNX source as it is unless `input_layout` changes it) and the layout its header names for the
    4-D inputs (None: as in ONNX). Raises NncgError."""
    keras = is_keras_model(model) or is_keras_path(model)
    if is_torch_module(model):
        model = export_onnx(model, example_inputs, exporter)
    elif keras:
        model = keras_to_onnx(model)
    if input_layout is not None:
        proto = model if isinstance(model, onnx.ModelProto) else read_model(model)
        own = model_layout(proto, keras_layout() if keras else "nchw")
        if own != input_layout:  # else a path stays a path: its name and hash
            model = with_input_layout(proto, input_layout, own)
        return model, input_layout
    if keras:  # the graph may not show it (one channel and a Reshape); Keras says it then
        return model, model_layout(model, keras_layout())
    shows_nhwc = isinstance(model, onnx.ModelProto) and graph_layout(model) == "nhwc"  # (a path is not read twice)
    return model, ("nhwc" if shows_nhwc else None)


def emit(
    program: Program,
    target: str,
    options: str = "",
    model_sha256: str = "",
    pipeline: str = "",
    profile: bool = False,
    input_layout: str | None = None,
    requantize: str = "float",
    io_quantization: Mapping[str, tuple[float, int]] | None = None,
) -> CompiledModel:
    """Prints a lowered program (run through a PassManager, which ends it with plan-memory) with the
    backend of `target`; `profile` adds per-layer timers; `input_layout` is what the header says of
    the 4-D inputs' layout (None: as in ONNX); `io_quantization` (ONNX name -> scale, zero point) its
    integer inputs' and outputs' NAME_X_SCALE and NAME_X_ZERO_POINT."""
    backend = get_backend(target)
    if program.arena is None:
        raise NncgError("the program has no memory plan: run its pipeline through a PassManager (ends in plan-memory)")
    check_program_limits(program)
    details = [options] + ([f"model sha256={model_sha256}"] if model_sha256 else [])
    first_line = f"/* Generated by NNCG {__version__}; {c_comment('; '.join(d for d in details if d))} */"
    header_name = f"{program.name}.h"
    params = {b.name: b for b in program.buffers if b.role in ("input", "output")}

    def param(role: str) -> tuple[Param, ...]:
        return tuple(Param(b.onnx_name, b.name, b.shape, str(b.dtype)) for b in params.values() if b.role == role)

    return CompiledModel(
        name=program.name,
        target=target,
        source=backend.source(program, first_line, header_name, profile),
        header=backend.header(program, first_line, input_layout, io_quantization),
        inputs=param("input"),
        outputs=param("output"),
        cflags=backend.cflags,
        strict_cflags=backend.strict_cflags,
        pipeline=pipeline,
        arena_bytes=program.arena.floats * 4,
        weights=weights_blob(program) if external_weights(program) else None,
        activation_bytes=program.arena.activation_floats * 4,
        record=CompileRecord(program),
    )


def _with_name(graph, name):
    return replace(graph, name=name)


def _default_name(model, graph_name: str) -> str:
    if isinstance(model, (str, os.PathLike)):
        return Path(model).stem
    return graph_name or "model"


def _sha256(model) -> str:
    if isinstance(model, (str, os.PathLike)):
        try:  # read a second time: the file may have gone meanwhile
            data = Path(model).read_bytes()
        except OSError as exc:
            raise NncgError(f"cannot read model file {shown(os.fspath(model), 240)}: {exc.strerror or exc}") from None
    elif isinstance(model, (bytes, bytearray, memoryview)):
        data = bytes(model)
    else:
        data = model.SerializeToString(deterministic=True)
    return hashlib.sha256(data).hexdigest()

"""Verification: compile the generated C into a small test program, run it on fixed-seed inputs
and compare with onnxruntime."""

from __future__ import annotations

import math
import os
import re
import shutil
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import onnx

from nncg.c_harness import harness_source
from nncg.errors import NncgError
from nncg.host_cpu import check_host_runs
from nncg.quant_steps import ALLOWED_STEPS, Step, steps_apart, tensor_steps, within_allowed_steps
from nncg.safe_text import capped, escaped, terminal_line
from nncg.tools import output_head, run_tool

SANITIZE_FLAGS = (
    "-fsanitize=address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
)
COMPILE_TIMEOUT_S = 600
RUN_TIMEOUT_S = 600
_SANITIZER_REPORT = re.compile(r"Sanitizer|runtime error:")


class VerificationError(NncgError):
    """The generated C did not compile cleanly, crashed, or broke the calling contract. The message
    keeps the lines of the compiler's or program's output (each made printable)."""

    def __init__(self, message: object = ""):
        Exception.__init__(self, "\n".join(terminal_line(line) for line in str(message).split("\n")))


@dataclass(frozen=True)
class ErrorStat:
    """How far one output is from the reference; `problem` is set when the numbers are not comparable
    (and when integers differ: they are compared exactly).

    max_rel is max|out - ref| / max(max|ref|, 1e-12): the error relative to the output's scale.
    Element-wise relative error is meaningless where the reference crosses zero (any rounding
    difference next to a zero is an "infinite" relative error), so one scale per output is used.

    A quantised output (nncg.quant_steps: a DequantizeLinear's or a QuantizeLinear's) also has
    max_steps, its largest difference in quantisation steps, and the share of identical elements;
    it is judged by those, not by max_rel.
    """

    name: str
    shape: tuple[int, ...]
    max_abs: float
    max_rel: float
    problem: str | None = None
    # an integer output (ArgMax's indices, quantized values, int32 sums), compared exactly: any difference fails
    indices: bool = False
    max_steps: float | None = None
    identical: float | None = None  # 0 to 1, with max_steps

    @property
    def quantized(self) -> bool:
        return self.max_steps is not None

    def passes(self, tolerance: float) -> bool:
        """Comparable, and within one quantisation step (a quantised output) or `tolerance` (max_rel)."""
        if self.problem is not None:
            return False
        if self.max_steps is not None:
            return within_allowed_steps(self.max_steps)
        return self.max_rel <= tolerance

    def step_cells(self) -> tuple[str, str]:
        """max steps and identical, as the report tables print them ("-" for a float output)."""
        if self.max_steps is None or self.identical is None:
            return "-", "-"
        return f"{self.max_steps:.3g}", f"{100 * self.identical:.2f} %"


def requirement(stats: Sequence[ErrorStat], tolerance: float) -> str:
    """The pass rule the outputs in `stats` are judged by, for the verdict line."""
    steps = f"quantised outputs within {ALLOWED_STEPS} quantisation step of onnxruntime's"
    if all(s.quantized for s in stats):
        return steps
    if any(s.quantized for s in stats):
        return f"{steps}, others max rel err <= {tolerance:g}"
    return f"max rel err <= {tolerance:g}"


@dataclass(frozen=True)
class VerifyReport:
    """The outcome of verify(): per-output errors against onnxruntime and the tolerance applied."""

    name: str
    target: str
    stats: tuple[ErrorStat, ...]
    tolerance: float
    seed: int

    @property
    def ok(self) -> bool:
        """True when every output passes (ErrorStat.passes)."""
        return all(s.passes(self.tolerance) for s in self.stats)

    @property
    def requirement(self) -> str:
        return requirement(self.stats, self.tolerance)

    def format(self) -> str:
        """A small aligned table (output, shape, max abs err, max rel err; max steps and identical for a
        quantised model) and a PASS/FAIL line."""
        steps = any(s.quantized for s in self.stats)
        rows = [("output", "shape", "max abs err", "max rel err") + (("max steps", "identical") if steps else ())]
        rows += [
            (_shown(s.name), str(s.shape), f"{s.max_abs:.3g}", f"{s.max_rel:.3g}") + (s.step_cells() if steps else ())
            for s in self.stats
        ]
        widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
        lines = [f"verify {self.name} (target {self.target}, seed {self.seed})"]
        lines += ["  ".join(cell.ljust(w) for cell, w in zip(row, widths)).rstrip() for row in rows]
        lines += [f"{_shown(s.name)}: {terminal_line(s.problem)}" for s in self.stats if s.problem is not None]
        verdict = "PASS" if self.ok else "FAIL"
        lines.append(f"{verdict}: {self.requirement} required")
        return "\n".join(lines)


def _shown(name: str) -> str:
    """An output's ONNX name for the report's table: printable, capped."""
    return capped(escaped(name))


def find_c_compiler(cc: str | None = None) -> str:
    """Return `cc` if it is on PATH; with no `cc`, the first of cc, gcc, clang on PATH."""
    if cc is not None:
        if shutil.which(cc) is None:
            raise NncgError(f"C compiler {cc!r} not found on PATH; install it or pass another compiler")
        return cc
    for candidate in ("cc", "gcc", "clang"):
        if shutil.which(candidate) is not None:
            return candidate
    raise NncgError("no C compiler found (looked for cc, gcc, clang on PATH); install gcc or clang")


def random_inputs(inputs: Sequence[Any], seed: int = 0) -> list[np.ndarray]:
    """Fixed-seed arrays, one per input (objects with `.shape` and maybe `.dtype`), in order:
    float32 standard-normal, or an integer type's values drawn uniformly over its whole range."""
    rng = np.random.default_rng(seed)
    return [_random_array(rng, tuple(spec.shape), np.dtype(getattr(spec, "dtype", "float32"))) for spec in inputs]


def _random_array(rng: np.random.Generator, shape: tuple[int, ...], dtype: np.dtype) -> np.ndarray:
    if dtype.kind == "f":
        return rng.standard_normal(shape, dtype=np.float32)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, shape, dtype=dtype, endpoint=True)


def input_array(spec: Any, array: np.ndarray) -> np.ndarray:
    """`array` as the input's dtype (float32 unless the spec says otherwise), C-contiguous."""
    return np.ascontiguousarray(array, dtype=np.dtype(getattr(spec, "dtype", "float32")))


def write_input(path: Path, spec: Any, array: np.ndarray) -> None:
    """An input file for the test programs: raw little-endian elements of the input's dtype."""
    data = input_array(spec, array)
    data.astype(data.dtype.newbyteorder("<")).tofile(path)


def _element_count(shape: Sequence[int]) -> int:
    return math.prod(int(d) for d in shape)


def _run_tool(cmd: list[str], cwd: Path, what: str) -> None:
    """Run one compiler or linker step; any error or warning raises with its output."""
    run_tool(cmd, what, cwd=cwd, timeout=COMPILE_TIMEOUT_S, reject_warnings=True, error=VerificationError)


def _check_inputs(compiled: Any, inputs: Sequence[np.ndarray]) -> None:
    if len(inputs) != len(compiled.inputs):
        raise VerificationError(f"{compiled.name} takes {len(compiled.inputs)} inputs, got {len(inputs)}")
    for spec, array in zip(compiled.inputs, inputs):
        if tuple(np.shape(array)) != tuple(spec.shape):
            raise VerificationError(
                f"input {spec.name!r} must have shape {tuple(spec.shape)}, got {tuple(np.shape(array))}"
            )
        _check_integers(spec, np.asarray(array))


def _check_integers(spec: Any, array: np.ndarray) -> None:
    """An integer input takes integers of its type's range, so that nothing is rounded or wrapped."""
    dtype = np.dtype(getattr(spec, "dtype", "float32"))
    if dtype.kind == "f":
        return
    info = np.iinfo(dtype)
    if array.dtype.kind not in "iu":
        raise VerificationError(f"input {spec.name!r} is {dtype}: pass integers, not {array.dtype}")
    if array.size and (array.min() < info.min or array.max() > info.max):
        raise VerificationError(f"input {spec.name!r} is {dtype}: its values must lie in {info.min}..{info.max}")


def _build(
    compiled: Any,
    workdir: Path,
    cc: str,
    opt: str,
    flags: Sequence[str],
    sanitize: bool,
    single_invocation: bool = False,
) -> Path:
    """Write the model and harness into workdir, compile both and link; returns the program path.

    `single_invocation` compiles and links both files with one compiler call (faster for many
    tiny models); the default compiles each file on its own, so a failure names the file."""
    c_path, h_path = compiled.write(workdir)[:2]
    (workdir / "harness.c").write_text(harness_source(compiled))  # inputs and outputs as files
    compile_flags = [opt, *compiled.strict_cflags, *compiled.cflags, *flags]
    if sanitize:
        compile_flags += SANITIZE_FLAGS
    include = f"-I{Path(h_path).parent}"
    if single_invocation:
        _run_tool(
            [cc, *compile_flags, include, str(c_path), "harness.c", "-o", "harness", "-lm"],
            workdir,
            f"building {Path(c_path).name} with harness.c",
        )
        return workdir / "harness"
    obj = f"{compiled.name}.o"
    _run_tool(
        [cc, *compile_flags, "-c", str(c_path), "-o", obj],
        workdir,
        f"compiling {Path(c_path).name}",
    )
    _run_tool(
        [cc, *compile_flags, include, "-c", "harness.c", "-o", "harness.o"],
        workdir,
        "compiling harness.c",
    )
    link_flags = [opt, *compiled.cflags, *flags, *(SANITIZE_FLAGS if sanitize else ())]
    _run_tool([cc, *link_flags, obj, "harness.o", "-o", "harness", "-lm"], workdir, "linking harness")
    return workdir / "harness"


def _execute(program: Path, args: list[str], workdir: Path, sanitize: bool, runner: Sequence[str] = ()) -> None:
    """Run the test program (under `runner`, e.g. an emulator, when given); a crash, nonzero exit or
    any sanitizer report raises."""
    env = dict(os.environ)
    env.setdefault("ASAN_OPTIONS", "abort_on_error=0:detect_leaks=1")
    env.setdefault("UBSAN_OPTIONS", "print_stacktrace=1:halt_on_error=1")
    command = [*runner, str(program), *args]
    proc = run_tool(command, "test program", cwd=workdir, env=env, timeout=RUN_TIMEOUT_S, error=VerificationError)
    if sanitize and _SANITIZER_REPORT.search(proc.stderr):
        report = output_head(proc.stderr)
        raise VerificationError(f"test program produced a sanitizer report: {' '.join(command)}\n{report}")


def run_compiled(
    compiled: Any,
    inputs: list[np.ndarray],
    *,
    cc: str | None = None,
    opt: str = "-O2",
    extra_cflags: Sequence[str] = (),
    sanitize: bool = False,
    workdir: str | os.PathLike[str] | None = None,
    runner: Sequence[str] = (),
) -> list[np.ndarray]:
    """Compile the model with a test harness, run it once on `inputs`; returns the outputs.

    `cc=None` picks the first of cc, gcc, clang on PATH (a cross compiler works too: `runner` is
    the command that runs its program, e.g. ("qemu-arm",)). The generated file is compiled with the
    target's strict flags; `sanitize` builds with ASan+UBSan and fails on any report. Files are
    kept in `workdir` when given, else in a temporary directory that is removed afterwards.
    """
    _check_inputs(compiled, inputs)
    cc = find_c_compiler(cc)
    build = (cc, opt, extra_cflags, sanitize, runner)
    if workdir is None:
        with tempfile.TemporaryDirectory(prefix="nncg-verify-") as tmp:
            return _build_and_run(compiled, inputs, Path(tmp), *build)
    Path(workdir).mkdir(parents=True, exist_ok=True)
    return _build_and_run(compiled, inputs, Path(workdir).resolve(), *build)


class BuiltModel:
    """A compiled model built into the test program once, to be run on many inputs.

    Files live in `workdir`, which the caller owns; `run` is not reentrant (it reuses the files).
    """

    def __init__(
        self, compiled: Any, program: Path, workdir: Path, sanitize: bool = False, runner: Sequence[str] = ()
    ) -> None:
        self.compiled = compiled
        self.program = program
        self.workdir = workdir
        self.sanitize = sanitize
        self.runner = tuple(runner)

    def run(self, inputs: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Run the program once on `inputs` (in the model's input order); returns the outputs."""
        _check_inputs(self.compiled, inputs)
        if not self.runner:
            check_host_runs(self.compiled.target)
        in_files = [f"input{i}.bin" for i in range(len(inputs))]
        out_files = [f"output{i}.bin" for i in range(len(self.compiled.outputs))]
        for name, spec, array in zip(in_files, self.compiled.inputs, inputs):
            write_input(self.workdir / name, spec, array)
        _execute(self.program, in_files + out_files, self.workdir, self.sanitize, self.runner)
        return [_read_output(self.workdir / name, spec) for name, spec in zip(out_files, self.compiled.outputs)]


def build_model(
    compiled: Any,
    workdir: str | os.PathLike[str],
    *,
    cc: str | None = None,
    opt: str = "-O2",
    extra_cflags: Sequence[str] = (),
    sanitize: bool = False,
    single_invocation: bool = False,
    runner: Sequence[str] = (),
) -> BuiltModel:
    """Build the model with the test harness in `workdir` (created if needed) for repeated runs.

    `cc`, `opt`, `extra_cflags`, `sanitize` and `runner` are as for run_compiled; `single_invocation`
    compiles and links with one compiler call."""
    cc = find_c_compiler(cc)
    path = Path(workdir)
    path.mkdir(parents=True, exist_ok=True)
    path = path.resolve()
    program = _build(compiled, path, cc, opt, extra_cflags, sanitize, single_invocation)
    return BuiltModel(compiled, program, path, sanitize, runner)


def _build_and_run(
    compiled: Any,
    inputs: Sequence[np.ndarray],
    workdir: Path,
    cc: str,
    opt: str,
    flags: Sequence[str],
    sanitize: bool,
    runner: Sequence[str],
) -> list[np.ndarray]:
    program = _build(compiled, workdir, cc, opt, flags, sanitize)
    return BuiltModel(compiled, program, workdir, sanitize, runner).run(inputs)


def _read_output(path: Path, spec: Any) -> np.ndarray:
    """An output file: little-endian elements of the output's dtype (spec.dtype)."""
    dtype = np.dtype(getattr(spec, "dtype", "float32"))
    data = np.fromfile(path, dtype=dtype.newbyteorder("<"))
    shape = tuple(spec.shape)
    if data.size != _element_count(shape):
        raise VerificationError(f"output {spec.name!r}: expected {_element_count(shape)} values, got {data.size}")
    return data.astype(dtype).reshape(shape)


def reference_session(model: onnx.ModelProto, optimize: bool = True, log_level: int = 3):
    """An onnxruntime CPU session for reference outputs: one thread, exact integer products. On x86
    without VNNI (SSE4.1, AVX2, AVX-512F) onnxruntime's uint8 x int8 kernels add pairs of products in
    int16, which saturates (a 3x3 QDQ conv on a Zen 3 core: outputs 108 steps off); the session option
    session.x64quantprecision rewrites them to its exact uint8 x uint8 kernels. ConvInteger of int8 x
    and uint8 weights saturates with or without it (Zen 3): it gets weights of x's signedness here
    (_same_signed_conv_integer_weights). Where the option's rewrite breaks the model (int8 x int8
    QLinearConv becomes a node no kernel runs; shared TFLite weights make it fail) the session goes
    without it: its int8 x int8 kernels sign-extend to int16 first and do not saturate."""
    import onnxruntime as ort  # imported here: only verification needs it, not compiling

    model = _same_signed_conv_integer_weights(model)

    def session(exact: bool):
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.log_severity_level = 4 if exact else log_level  # a failed first try is no error
        if not optimize:
            options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
        if exact:
            options.add_session_config_entry("session.x64quantprecision", "1")
        return ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])

    try:
        return session(exact=True)
    except Exception:  # onnxruntime raises its own exception types; without the option it may still run
        return session(exact=False)


def _same_signed_conv_integer_weights(model: onnx.ModelProto) -> onnx.ModelProto:
    """The model with each ConvInteger whose constant weights' type differs from x's (uint8 x int8 or
    int8 x uint8) taking them as x's type, w and its zero point both moved by 128: the same products
    (w - w_zero_point is unchanged), which onnxruntime's kernels of one signedness sum without
    saturating."""
    eight_bit = (onnx.TensorProto.INT8, onnx.TensorProto.UINT8)
    inits = {t.name: t for t in model.graph.initializer}
    convs = [
        k for k, n in enumerate(model.graph.node)
        if n.op_type == "ConvInteger" and n.domain in ("", "ai.onnx") and len(n.input) > 1
        and n.input[1] in inits and inits[n.input[1]].data_type in eight_bit
        and (len(n.input) < 4 or not n.input[3] or n.input[3] in inits)
    ]  # fmt: skip
    if not convs:
        return model
    try:
        typed = onnx.shape_inference.infer_shapes(model)
    except Exception:  # onnx raises several types; a model it cannot type is run as it is
        return model
    elem = {v.name: v.type.tensor_type.elem_type for v in (*typed.graph.input, *typed.graph.value_info)}
    out = onnx.ModelProto.FromString(model.SerializeToString())
    taken = set(inits) | {x for n in out.graph.node for x in (*n.input, *n.output)}
    for k in convs:
        node = out.graph.node[k]
        x_type, w_type = elem.get(node.input[0]), inits[node.input[1]].data_type
        if x_type not in eight_bit or x_type == w_type:
            continue
        zero = inits.get(node.input[3]) if len(node.input) > 3 and node.input[3] else None
        weights = onnx.numpy_helper.to_array(inits[node.input[1]])
        arrays = {1: weights, 3: onnx.numpy_helper.to_array(zero) if zero else np.zeros((), weights.dtype)}
        shift, dtype = (128, np.uint8) if x_type == onnx.TensorProto.UINT8 else (-128, np.int8)
        inputs = [*node.input] + [""] * (4 - len(node.input))
        for slot, array in arrays.items():
            name = f"{node.input[1]}_as_{np.dtype(dtype).name}_{k}_{slot}"
            while name in taken:
                name += "_"
            taken.add(name)
            shifted = (array.astype(np.int16) + shift).astype(dtype)
            out.graph.initializer.append(onnx.numpy_helper.from_array(shifted, name))
            inputs[slot] = name
        del node.input[:]
        node.input.extend(inputs)
    return out


def reference_outputs(
    model: onnx.ModelProto,
    compiled_inputs: Sequence[Any],
    inputs: Sequence[np.ndarray],
    output_names: Sequence[str] | None = None,
) -> list[np.ndarray]:
    """onnxruntime (CPU, no graph optimizations) on the same inputs; the graph's outputs in graph order,
    or the named ones (graph outputs all) in that order."""
    feed = {spec.name: input_array(spec, array) for spec, array in zip(compiled_inputs, inputs)}
    try:
        session = reference_session(model, optimize=False)
        return [np.asarray(out) for out in session.run(None if output_names is None else list(output_names), feed)]
    except Exception as exc:  # onnxruntime raises its own exception types
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise VerificationError(f"onnxruntime cannot run this model for comparison: {first}") from None


def _error_stat(name: str, out: np.ndarray, ref: np.ndarray, step: Step | None = None) -> ErrorStat:
    """Errors of one output (in quantisation steps too when it has a `step`); elements where the
    reference is NaN are not compared."""
    shape = tuple(out.shape)
    if out.shape != ref.shape:
        return ErrorStat(name, shape, math.inf, math.inf, f"shape {shape} != reference shape {tuple(ref.shape)}")
    if step is not None:
        return _quantized_stat(name, out, ref, step)
    if out.dtype.kind in "iu" or ref.dtype.kind in "iu":
        return _integer_stat(name, out, ref)
    return _float_stat(name, out, ref)


def _float_stat(name: str, out: np.ndarray, ref: np.ndarray) -> ErrorStat:
    shape = tuple(out.shape)
    out64, ref64 = out.astype(np.float64), ref.astype(np.float64)
    ref_nan = np.isnan(ref64)
    bad_nan = int(np.count_nonzero(np.isnan(out64) & ~ref_nan))
    if bad_nan:
        problem = f"{bad_nan} NaN elements where the reference is not NaN (unwritten or invalid output)"
        return ErrorStat(name, shape, math.inf, math.inf, problem)
    # Equal elements (same infinities included) have zero error; inf - finite stays inf.
    diff = np.where(out64 == ref64, 0.0, np.abs(out64 - ref64))[~ref_nan]
    finite_ref = np.abs(ref64[np.isfinite(ref64)])
    max_abs = float(diff.max()) if diff.size else 0.0
    scale = max(float(finite_ref.max()) if finite_ref.size else 0.0, 1e-12)
    return ErrorStat(name, shape, max_abs, max_abs / scale)


def _quantized_stat(name: str, out: np.ndarray, ref: np.ndarray, step: Step) -> ErrorStat:
    """A quantised output: float (dequantised) against float, integers against integers."""
    if (out.dtype.kind in "iu") != (ref.dtype.kind in "iu"):
        problem = f"{out.dtype} output where the reference is {ref.dtype}"
        return ErrorStat(name, tuple(out.shape), math.inf, math.inf, problem)
    stat = _float_stat(name, out, ref)
    if stat.problem is not None:
        return stat
    apart = steps_apart(step, out, ref)
    max_steps = float(apart.max()) if apart.size else 0.0
    identical = float(np.mean(out == ref)) if out.size else 1.0
    return replace(stat, max_steps=max_steps, identical=identical)


def _integer_stat(name: str, out: np.ndarray, ref: np.ndarray) -> ErrorStat:
    """Integers (ArgMax's int32 indices against onnxruntime's int64, quantized values, int32 sums)
    must be equal: any difference is a problem."""
    shape = tuple(out.shape)
    if out.dtype.kind not in "iu" or ref.dtype.kind not in "iu":
        return ErrorStat(name, shape, math.inf, math.inf, f"{out.dtype} output where the reference is {ref.dtype}")
    differ = int(np.count_nonzero(out.astype(np.int64) != ref.astype(np.int64)))
    if differ:
        worst = float(np.abs(out.astype(np.int64) - ref.astype(np.int64)).max())
        problem = f"{differ} of {out.size} indices differ from the reference"
        return ErrorStat(name, shape, worst, math.inf, problem, indices=True)
    return ErrorStat(name, shape, 0.0, 0.0, indices=True)


def compare(
    outputs: Sequence[np.ndarray],
    references: Sequence[np.ndarray],
    names: Sequence[str] | None = None,
    steps: Mapping[str, Step] | None = None,
) -> list[ErrorStat]:
    """Per-output max abs and max rel error (see ErrorStat), shape and NaN checks; for the outputs
    named in `steps` (nncg.quant_steps.tensor_steps), the error in quantisation steps too."""
    if len(outputs) != len(references):
        raise VerificationError(f"{len(outputs)} outputs but {len(references)} reference outputs")
    names = list(names) if names is not None else [f"output{i}" for i in range(len(outputs))]
    steps = steps or {}
    return [_error_stat(n, np.asarray(o), np.asarray(r), steps.get(n)) for n, o, r in zip(names, outputs, references)]


def _check_interface(model: onnx.ModelProto, compiled: Any) -> None:
    """The C function's parameters must be the graph's inputs then outputs, in graph order."""
    initializers = {init.name for init in model.graph.initializer}
    graph_inputs = [v.name for v in model.graph.input if v.name not in initializers]
    graph_outputs = [v.name for v in model.graph.output]
    compiled_inputs = [spec.name for spec in compiled.inputs]
    compiled_outputs = [spec.name for spec in compiled.outputs]
    if compiled_inputs != graph_inputs or compiled_outputs != graph_outputs:
        raise VerificationError(
            f"{compiled.name} has inputs {compiled_inputs} and outputs {compiled_outputs}, "
            f"but the model has inputs {graph_inputs} and outputs {graph_outputs}"
        )


def verify(
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
) -> VerifyReport:
    """Run the compiled C and onnxruntime on the same fixed-seed inputs and compare every output:
    a quantised one in quantisation steps (within one passes), any other by max_rel <= `tolerance`.

    `cc`, `extra_cflags` and `runner` build and run it elsewhere, e.g. a cross compiler under qemu."""
    _check_interface(model, compiled)
    inputs = random_inputs(compiled.inputs, seed)
    outputs = run_compiled(
        compiled, inputs, cc=cc, sanitize=sanitize, opt=opt, extra_cflags=extra_cflags, runner=runner
    )
    references = reference_outputs(model, compiled.inputs, inputs)
    stats = compare(outputs, references, [spec.name for spec in compiled.outputs], tensor_steps(model))
    return VerifyReport(compiled.name, compiled.target, tuple(stats), tolerance, seed)

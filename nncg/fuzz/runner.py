"""One fuzz case: check the model is valid (onnx checker + onnxruntime), compile it with the
options, build and run the C, compare with onnxruntime; the result is one outcome class."""

from __future__ import annotations

import math
import re
import resource
import signal
import time
import traceback
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np
import onnx

from .. import compile as compile_model
from ..errors import NncgError
from ..verify import (
    VerificationError,
    compare,
    random_inputs,
    reference_outputs,
    reference_session,
    run_compiled,
    verify,
)
from .options import CROSS, Options
from .ties import has_nearest_resize_tie

OUTCOMES = (
    "pass",
    "mismatch",  # outputs differ from onnxruntime beyond the tolerance
    "crash",  # NNCG raised something other than NncgError (or its IR verifier failed): an internal error
    "refused",  # NncgError on a model onnxruntime runs, also with the default options
    "refused-option",  # NncgError only with these options: a pass refusing a per-layer choice
    "build-fail",  # the C does not compile cleanly with the target's strict flags
    "run-fail",  # the program crashed or exited nonzero
    "sanitizer",  # ASan/UBSan reported
    "timeout",  # NNCG or the C compiler took too long
    "code-size",  # the C is far larger than the model and options call for
    "ill-conditioned",  # a mismatch on a model whose output float rounding alone moves past the tolerance
    "onnxruntime-differs",  # a mismatch where NNCG agrees with the ONNX reference implementation (onnx.reference)
    "resize-tie",  # a mismatch on a model whose nearest Resize maps a pixel exactly half-way (nncg/fuzz/ties.py)
    "invalid",  # onnxruntime or the checker rejects the model: a generator bug, NNCG not blamed
)
BUGS = ("mismatch", "crash", "refused", "build-fail", "run-fail", "sanitizer", "timeout", "code-size")
SHRINKABLE = tuple(kind for kind in BUGS if kind != "timeout")  # a timeout takes minutes per try: saved as found

# The project's tolerance (nncg-onnx --verify, tests/helpers.py): max abs error relative to the
# output's largest magnitude. Float32 rounding in any evaluation order stays ~1e-6 for these sizes.
TOLERANCE = 1e-4
COMPILE_SECONDS = 60  # NNCG's own compile: anything near this is a finding (typically < 2 s)
BUILD_CPU_SECONDS = 90  # gcc -O2 build and run of the test program, CPU time (typically < 10 s)
SANITIZER_SLOWDOWN = 3  # ASan+UBSan instrumentation: gcc and the program take about 2-3x as long
HARD_SECONDS = 600  # the case is abandoned
NOISE_ULPS = 4  # input perturbation (in float32 ulps) that estimates the model's rounding sensitivity


@dataclass(frozen=True)
class Outcome:
    """What one case gave: its class (OUTCOMES), the message, the worst error, the C's size."""

    kind: str
    message: str = ""
    max_rel: float = 0.0
    c_bytes: int = 0
    seconds: float = 0.0

    @property
    def is_bug(self) -> bool:
        return self.kind in BUGS

    def signature(self) -> str:
        """The outcome class plus a normalised message, so shrinking keeps to the same failure."""
        if self.kind in ("refused", "refused-option", "build-fail", "sanitizer", "crash", "run-fail"):
            return f"{self.kind}: {normalise(self.message)}"
        return self.kind


def normalise(message: str) -> str:
    """The message's first meaningful line with names, numbers and paths taken out."""
    lines = [line for line in message.splitlines() if line.strip()]
    key = next((line for line in lines if "error:" in line or "ERROR:" in line or "runtime error" in line), "")
    text = key or (lines[0] if lines else "")
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "'_'", text)
    text = re.sub(r"/\S+", "PATH", text)
    text = re.sub(r"\b\w*\d\w*\b", "N", text)
    return text[:120]


class CaseTimeout(BaseException):
    """Raised by the alarm; a BaseException so no `except Exception` in the code under test eats it."""


@contextmanager
def deadline(seconds: float) -> Iterator[None]:
    """Raises CaseTimeout in the main thread after `seconds` (subprocess.run kills its child then)."""

    def fire(signum, frame):
        raise CaseTimeout()

    previous = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def validate(model: onnx.ModelProto, declared: dict[str, tuple[int, ...]] | None = None) -> str | None:
    """Why the model is not valid (checker, onnxruntime, declared shapes, non-finite outputs), or None."""
    try:
        onnx.checker.check_model(model)
    except onnx.checker.ValidationError as exc:
        return f"onnx checker: {str(exc).splitlines()[0]}"
    try:
        outputs = _onnxruntime_outputs(model)
    except Exception as exc:  # onnxruntime raises its own exception types
        return f"onnxruntime: {str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__}"
    for value, out in zip(model.graph.output, outputs):
        if declared and tuple(out.shape) != tuple(declared.get(value.name, out.shape)):
            expected = list(declared[value.name])
            return f"output {value.name}: onnxruntime gives {list(out.shape)}, the generator expected {expected}"
        if not np.all(np.isfinite(out)):
            return f"output {value.name} is not finite"
    return None


def _onnxruntime_outputs(model: onnx.ModelProto) -> list[np.ndarray]:
    """The model run by onnxruntime on verify's inputs, with its log off (rejections are counted, not printed)."""
    initializers = {t.name for t in model.graph.initializer}
    inputs = [v for v in model.graph.input if v.name not in initializers]
    shapes = [tuple(d.dim_value for d in v.type.tensor_type.shape.dim) for v in inputs]
    arrays = random_inputs([np.empty(s, np.float32) for s in shapes], 0)
    return reference_session(model, log_level=4).run(None, {v.name: a for v, a in zip(inputs, arrays)})


def run_case(model: onnx.ModelProto, options: Options, size_limit: int | None = None) -> Outcome:
    """Compile, build, run and compare one case; never raises (except KeyboardInterrupt)."""
    start = time.monotonic()
    try:
        with deadline(HARD_SECONDS):
            outcome = _run(model, options, size_limit, start)
    except CaseTimeout:
        outcome = Outcome("timeout", f"abandoned after {HARD_SECONDS} s")
    return Outcome(outcome.kind, outcome.message, outcome.max_rel, outcome.c_bytes, time.monotonic() - start)


def _run(model: onnx.ModelProto, options: Options, size_limit: int | None, start: float) -> Outcome:
    try:
        compiled = compile_model(model, verify_ir=True, **options.compile_kwargs())
    except NncgError as exc:
        return _refusal(model, options, str(exc))
    except Exception as exc:  # an internal error: the point of fuzzing is to find these
        return Outcome("crash", _crash_message(exc))
    c_bytes = len(compiled.source)
    compile_seconds = time.monotonic() - start
    if compile_seconds > COMPILE_SECONDS:
        return Outcome("timeout", f"nncg.compile took {compile_seconds:.0f} s", c_bytes=c_bytes)
    if size_limit is not None and c_bytes > size_limit:
        return Outcome("code-size", f"{c_bytes} bytes of C, limit {size_limit} for this model", c_bytes=c_bytes)
    built = _children_cpu_seconds()
    outcome = _verify(model, compiled, options)
    build_seconds = _children_cpu_seconds() - built
    if outcome.kind == "pass" and build_seconds > BUILD_CPU_SECONDS * (SANITIZER_SLOWDOWN if options.sanitize else 1):
        message = f"building and running {c_bytes} bytes of C took {build_seconds:.0f} s of CPU"
        return Outcome("timeout", message, c_bytes=c_bytes)
    return Outcome(outcome.kind, outcome.message, outcome.max_rel, c_bytes)


def _children_cpu_seconds() -> float:
    """CPU time of this process's finished children (the compiler, the test program): unlike the
    wall clock it does not grow when other jobs share the machine."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _verify(model: onnx.ModelProto, compiled, options: Options) -> Outcome:
    cross = CROSS.get(options.target)
    where = {"cc": cross[0], "extra_cflags": cross[1], "runner": cross[2]} if cross else {}
    try:
        report = verify(model, compiled, tolerance=TOLERANCE, sanitize=options.sanitize, **where)
    except VerificationError as exc:
        return _verification_failure(str(exc))
    except Exception as exc:
        return Outcome("crash", _crash_message(exc))
    worst = max((s.max_rel for s in report.stats), default=0.0)
    if report.ok:
        return Outcome("pass", max_rel=worst)
    problems = "; ".join(
        f"{s.name}: max rel {s.max_rel:.3g}" + (f" ({s.problem})" if s.problem else "") for s in report.stats
    )
    comparable = all(s.problem is None or s.indices for s in report.stats)  # indices that differ are numbers too
    if comparable and rounding_sensitivity(model, compiled) * 10 > TOLERANCE:
        return Outcome("ill-conditioned", problems, worst)
    if agrees_with_onnx_reference(model, compiled, where):
        return Outcome("onnxruntime-differs", problems, worst)
    if has_nearest_resize_tie(model):
        return Outcome("resize-tie", problems, worst)
    return Outcome("mismatch", problems, worst)


def _verification_failure(message: str) -> Outcome:
    first = message.splitlines()[0] if message else ""
    if first.startswith(("compiling", "building", "linking")):
        kind = "timeout" if "timed out" in first else "build-fail"
    elif "sanitizer report" in first or "Sanitizer" in message or "runtime error:" in message:
        kind = "sanitizer"
    elif first.startswith("test program"):
        kind = "timeout" if "timed out" in first else "run-fail"
    elif first.startswith("onnxruntime cannot run"):
        kind = "invalid"
    elif "expected" in first and "values, got" in first:
        kind = "run-fail"
    else:
        kind = "mismatch"  # the C function's interface differs from the model's
    return Outcome(kind, message)


def _refusal(model: onnx.ModelProto, options: Options, message: str) -> Outcome:
    if message.startswith("IR is malformed"):
        return Outcome("crash", message)
    if options.default_layers:
        return Outcome("refused", message)
    try:
        compile_model(model, **Options(target=options.target).compile_kwargs())
    except NncgError:
        return Outcome("refused", message)
    except Exception as exc:
        return Outcome("crash", _crash_message(exc))
    return Outcome("refused-option", message)


def _crash_message(exc: BaseException) -> str:
    """Exception type and text, and the innermost NNCG frame (where the internal error surfaced)."""
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if "/nncg/" in f.filename.replace("\\", "/")]
    where = (
        f" at {frames[-1].filename.rsplit('/nncg/', 1)[-1]}:{frames[-1].lineno} in {frames[-1].name}" if frames else ""
    )
    text = str(exc).splitlines()[0] if str(exc) else ""
    return f"{type(exc).__name__}: {text}{where}"


def agrees_with_onnx_reference(model: onnx.ModelProto, compiled, where: dict) -> bool:
    """Whether NNCG's outputs match onnx's reference implementation (where onnxruntime and the
    ONNX spec disagree, NNCG may follow the spec). False when the reference cannot run the model."""
    from onnx.reference import ReferenceEvaluator

    inputs = random_inputs(compiled.inputs, 0)
    try:
        outputs = run_compiled(compiled, inputs, **where)
        feed = {spec.name: x for spec, x in zip(compiled.inputs, inputs)}
        references = ReferenceEvaluator(model).run(None, feed)
    except Exception:  # the reference lacks some modes (tf_half_pixel_for_nn) and ops
        return False
    stats = compare(outputs, [_as_float32_unless_indices(np.asarray(r)) for r in references])
    return all(s.problem is None and s.max_rel <= TOLERANCE for s in stats)


def _as_float32_unless_indices(array: np.ndarray) -> np.ndarray:
    return array if array.dtype.kind in "iu" else array.astype(np.float32)


def rounding_sensitivity(model: onnx.ModelProto, compiled) -> float:
    """How far onnxruntime's own outputs move (relative to their scale) when the inputs move by a few
    float32 ulps: float rounding anywhere in the graph moves results about as much, so a mismatch
    below ~10x this is not evidence of a bug. Indices that move (an ArgMax near a tie) are infinitely
    sensitive."""
    inputs = random_inputs(compiled.inputs, 0)
    rng = np.random.default_rng(1)
    nudged = [x * (1 + rng.uniform(-1, 1, x.shape).astype(np.float32) * NOISE_ULPS * 2.0**-23) for x in inputs]
    base = reference_outputs(model, compiled.inputs, inputs)
    moved = reference_outputs(model, compiled.inputs, [x.astype(np.float32) for x in nudged])
    stats = compare(moved, base)
    return max((s.max_rel for s in stats if math.isfinite(s.max_rel) or s.indices), default=0.0)

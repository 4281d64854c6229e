"""The pass manager: named passes, pipelines as text that round-trips, IR printing as an instrument.

A pipeline is `name{key=value,...},name,...`, e.g. `fold-batchnorm,lower,vectorize,unroll{level=1}`: the
text records choices; hardware facts (vector widths, registers) come from the `Target` the manager
hands to the passes that declare they need it. Graph passes run before `lower`, loop passes after it;
a finishing pass (plan-memory) runs last and is appended when a lowering pipeline lacks it (the
pipeline text then shows it). The manager checks each pass gets the IR it expects, that no loop
mark (vectorized, unrolled) survives the pipeline, verifies the IR after each pass when asked, and
names the pass in every error raised inside it."""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TextIO

from ..errors import NncgError
from ..ir.graph import Graph
from ..ir.kinds import LoopKind
from ..ir.loops import Loop, Program, walk_stmts
from ..ir.target import Target
from ..ir.text import graph_to_text, program_to_text
from ..ir.verify import verify_ir

STAGES = {"graph": Graph, "lower": Graph, "loop": Program}


@dataclass(frozen=True)
class Tunable:
    """A per-layer choice of a pass that --tune measures; the pass records choices as `layers=`.

    candidates(ir, target): layer -> the values worth timing, from the IR the pass receives.
    format_value: a value as the pass's `layers=` parameter spells it.
    whole_model: the choice changes other layers' time too (their input layout): builds are timed
    as whole models, layer i taking its last value in builds k > i (layers in graph order)."""

    candidates: Callable[[Graph | Program, Target], dict[str, tuple]]
    format_value: Callable[[object], str] = str
    whole_model: bool = False


@dataclass(frozen=True)
class PassInfo:
    name: str
    stage: str  # "graph" (Graph -> Graph), "lower" (Graph -> Program), "loop" (Program -> Program)
    run: Callable
    params: dict[str, Callable[[str], object]]  # parameter name -> parser of its text
    doc: str
    target: bool = False  # run(ir, target=..., **params): it needs the hardware facts
    finishing: bool = False  # runs last; appended to a lowering pipeline that lacks it
    tunable: Tunable | None = None  # what --tune may choose per layer (through the `layers` parameter)
    priced: bool = False  # run(ir, target=...) when there is a target: it prices its choices for it


REGISTRY: dict[str, PassInfo] = {}


def register(
    name: str,
    stage: str,
    run: Callable,
    *,
    target: bool = False,
    finishing: bool = False,
    tunable: Tunable | None = None,
    priced: bool = False,
    **params: Callable[[str], object],
) -> None:
    if tunable is not None and "layers" not in params:
        raise ValueError(f"pass {name} is tunable but has no `layers` parameter to record the choices")
    doc = (sys.modules[run.__module__].__doc__ or "").strip()
    first = doc.splitlines()[0] if doc else ""
    REGISTRY[name] = PassInfo(name, stage, run, params, first, target, finishing, tunable, priced)


@dataclass(frozen=True)
class PassSpec:
    name: str
    params: tuple[tuple[str, str], ...] = ()

    def __str__(self) -> str:
        if not self.params:
            return self.name
        return f"{self.name}{{{','.join(f'{k}={v}' for k, v in self.params)}}}"


_SPEC = re.compile(r"\s*([a-z][a-z0-9-]*)\s*(?:\{([^{}]*)\})?\s*(?:,|$)")


def parse_pipeline(text: str) -> tuple[PassSpec, ...]:
    """`a,b{k=v}` -> (PassSpec('a'), PassSpec('b', (('k', 'v'),))); unknown names are errors."""
    specs, pos = [], 0
    text = text.strip()
    while pos < len(text):
        match = _SPEC.match(text, pos)
        if not match or match.end() == pos:
            raise NncgError(f"cannot parse pipeline at '{text[pos:]}': expected name or name{{key=value,...}}")
        name, body = match.group(1), match.group(2)
        params = tuple(_parse_param(name, item) for item in body.split(",") if item.strip()) if body else ()
        specs.append(_checked(PassSpec(name, params)))
        pos = match.end()
    return tuple(specs)


def format_pipeline(specs) -> str:
    return ",".join(str(s) for s in specs)


def _parse_param(pass_name: str, item: str) -> tuple[str, str]:
    key, sep, value = item.partition("=")
    if not sep:
        raise NncgError(f"pass {pass_name}: parameter '{item.strip()}' must be key=value")
    return key.strip(), value.strip()


def _checked(spec: PassSpec) -> PassSpec:
    info = REGISTRY.get(spec.name)
    if info is None:
        raise NncgError(f"unknown pass '{spec.name}'; passes: {', '.join(sorted(REGISTRY))}")
    for key, value in spec.params:
        if key not in info.params:
            raise NncgError(f"pass {spec.name} has no parameter '{key}' (it takes: {', '.join(info.params) or 'none'})")
        try:
            info.params[key](value)
        except (TypeError, ValueError) as exc:
            raise NncgError(f"pass {spec.name}: bad value '{value}' for {key}: {exc}") from None
    return spec


class PassManager:
    """Runs passes in order. Instruments get (pass spec, IR after it); `verify` (on by default: it
    costs about a tenth of the compile time) checks the IR after every pass (nncg/ir/verify.py).

    `target` gives the passes that need hardware facts (vectorize, register-block, ...) their
    Target; `finish` appends the finishing passes a lowering pipeline lacks (off only to inspect the
    IR part-way, as --tune does); `keep_inputs` names passes whose input IR `inputs` keeps (what
    --report reads the passes' choices from)."""

    def __init__(
        self,
        pipeline: str | tuple[PassSpec, ...],
        target: Target | None = None,
        verify: bool = True,
        print_ir_after_all: TextIO | None = None,
        finish: bool = True,
        keep_inputs: tuple[str, ...] = (),
    ):
        specs = parse_pipeline(pipeline) if isinstance(pipeline, str) else tuple(_checked(s) for s in pipeline)
        self.specs = _with_finishing_passes(specs) if finish else _in_order(specs)
        self.target = target
        self.verify = verify
        self.keep_inputs = keep_inputs
        self.inputs: dict[str, Graph | Program] = {}
        self.instruments: list[Callable[[PassSpec, object], None]] = []
        if print_ir_after_all is not None:
            self.instruments.append(
                lambda spec, ir: print(f"// ----- IR after {spec}\n{ir_to_text(ir)}", file=print_ir_after_all)
            )
        needy = [spec.name for spec in self.specs if REGISTRY[spec.name].target]
        if needy and target is None:
            raise NncgError(
                f"passes {', '.join(needy)} need a target: PassManager(pipeline, target=nncg.get_target('ssse3'))"
            )

    @property
    def pipeline(self) -> str:
        return format_pipeline(self.specs)

    def run(self, ir: Graph | Program) -> Graph | Program:
        for spec in self.specs:
            if spec.name in self.keep_inputs:
                self.inputs[spec.name] = ir
            ir = self._run_one(spec, ir)
            if self.verify:
                problems = verify_ir(ir)
                if problems:
                    raise NncgError(f"IR is malformed after pass {spec}: " + "; ".join(problems[:5]))
            for instrument in self.instruments:
                instrument(spec, ir)
        if isinstance(ir, Program) and self.specs and REGISTRY[self.specs[-1].name].finishing:
            _check_no_marks(ir, self.specs[-1])
        return ir

    def _run_one(self, spec: PassSpec, ir: Graph | Program) -> Graph | Program:
        info = REGISTRY[spec.name]
        if not isinstance(ir, STAGES[info.stage]):
            where = "after" if info.stage == "loop" else "before"
            expected, got = _ir_kind(STAGES[info.stage]), _ir_kind(type(ir))
            raise NncgError(f"pass {spec} works on the {expected} but gets the {got}; put it {where} lower")
        kwargs = {k: info.params[k](v) for k, v in spec.params}
        if info.target or (info.priced and self.target is not None):
            kwargs["target"] = self.target
        try:
            return info.run(ir, **kwargs)
        except NncgError as exc:
            message = str(exc).removeprefix(f"{spec.name}: ")
            if message.startswith(f"pass {spec.name}"):
                raise
            raise type(exc)(f"pass {spec.name}: {message}") from None
        except Exception as exc:
            raise RuntimeError(f"pass {spec.name} failed: {type(exc).__name__}: {exc}") from exc


def _in_order(specs: tuple[PassSpec, ...]) -> tuple[PassSpec, ...]:
    """The specs, refused when a finishing pass is not last."""
    for i, spec in enumerate(specs[:-1]):
        if REGISTRY[spec.name].finishing:
            raise NncgError(f"pass {spec.name} must run last, but {specs[i + 1].name} follows it")
    return specs


def _with_finishing_passes(specs: tuple[PassSpec, ...]) -> tuple[PassSpec, ...]:
    """A pipeline that lowers ends with the finishing passes; those it lacks are appended."""
    specs = _in_order(specs)
    if not any(REGISTRY[s.name].stage == "lower" for s in specs):
        return specs
    present = {s.name for s in specs}
    missing = [info.name for info in REGISTRY.values() if info.finishing and info.name not in present]
    return specs + tuple(PassSpec(name) for name in missing)


def _check_no_marks(program: Program, last: PassSpec) -> None:
    """No loop leaves the pipeline still marked for a pass that materialises it."""
    for kernel in program.kernels:
        marked = [s for s in walk_stmts(kernel.body) if isinstance(s, Loop) and s.kind != LoopKind.SERIAL]
        if marked:
            loop = marked[0]
            raise NncgError(
                f"after pass {last.name}, loop '{loop.var}' of layer {kernel.name} is still marked {loop.kind}: "
                "the pass that marked it must also materialise it"
            )


def ir_to_text(ir: Graph | Program) -> str:
    return graph_to_text(ir) if isinstance(ir, Graph) else program_to_text(ir)


def _ir_kind(cls) -> str:
    return "graph IR" if cls is Graph else "loop-nest IR"

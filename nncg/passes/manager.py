"""The pass manager: named passes, pipelines as text that round-trips, IR printing as an instrument.

A pipeline is `name{key=value,...},name,...`, e.g. `fold-batchnorm,lower,vectorize{lanes=4},unroll{level=1}`.
Graph passes run before `lower`, loop passes after it; the manager checks each pass gets the IR it
expects, verifies the IR after each pass when asked, and names the pass in every error."""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import TextIO

from ..errors import NncgError
from ..ir.graph import Graph
from ..ir.loops import Program
from ..ir.text import graph_to_text, program_to_text
from ..ir.verify import verify_ir

STAGES = {"graph": Graph, "lower": Graph, "loop": Program}


@dataclass(frozen=True)
class PassInfo:
    name: str
    stage: str  # "graph" (Graph -> Graph), "lower" (Graph -> Program), "loop" (Program -> Program)
    run: Callable
    params: dict[str, Callable[[str], object]]  # parameter name -> parser of its text
    doc: str


REGISTRY: dict[str, PassInfo] = {}


def register(name: str, stage: str, run: Callable, **params: Callable[[str], object]) -> None:
    doc = (sys.modules[run.__module__].__doc__ or "").strip()
    REGISTRY[name] = PassInfo(name, stage, run, params, doc.splitlines()[0] if doc else "")


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
    """Runs passes in order. Instruments get (pass spec, IR after it); `verify` checks the IR."""

    def __init__(
        self, pipeline: str | tuple[PassSpec, ...], verify: bool = False, print_ir_after_all: TextIO | None = None
    ):
        self.specs = parse_pipeline(pipeline) if isinstance(pipeline, str) else tuple(_checked(s) for s in pipeline)
        self.verify = verify
        self.instruments: list[Callable[[PassSpec, object], None]] = []
        if print_ir_after_all is not None:
            self.instruments.append(
                lambda spec, ir: print(f"// ----- IR after {spec}\n{ir_to_text(ir)}", file=print_ir_after_all)
            )

    @property
    def pipeline(self) -> str:
        return format_pipeline(self.specs)

    def run(self, ir: Graph | Program) -> Graph | Program:
        for spec in self.specs:
            info = REGISTRY[spec.name]
            if not isinstance(ir, STAGES[info.stage]):
                where = "after" if info.stage == "loop" else "before"
                expected, got = _ir_kind(STAGES[info.stage]), _ir_kind(type(ir))
                raise NncgError(f"pass {spec} works on the {expected} but gets the {got}; put it {where} lower")
            kwargs = {k: info.params[k](v) for k, v in spec.params}
            ir = info.run(ir, **kwargs)
            if self.verify:
                problems = verify_ir(ir)
                if problems:
                    raise NncgError(f"IR is malformed after pass {spec}: " + "; ".join(problems[:5]))
            for instrument in self.instruments:
                instrument(spec, ir)
        return ir


def ir_to_text(ir: Graph | Program) -> str:
    return graph_to_text(ir) if isinstance(ir, Graph) else program_to_text(ir)


def _ir_kind(cls) -> str:
    return "graph IR" if cls is Graph else "loop-nest IR"

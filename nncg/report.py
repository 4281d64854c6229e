"""`--report`: NAME.report.html (one self-contained page: CSS and plots inline, nothing fetched) and
NAME.report.md (for CI logs) beside NAME.c. They show the model (inputs, outputs, operators,
parameters, MACs, target, pipeline), one row per layer (kernel) with what the passes chose and where
its output lives in the arena, the arena's timeline, the object's section sizes, and the results of
--verify, --benchmark and --profile when those ran. Every model-derived text is escaped for the
format (safe_text.html_text, markdown_text). Without timings the files are byte-identical for the
same model and options; they are written together, all or nothing (output_files)."""

from __future__ import annotations

import base64
import html
import importlib
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .bench.benchmark import SPEEDUP_NOTE
from .bench.harness import ObjectSizes, object_sizes
from .bench.macs import node_macs
from .compiler import CompiledModel, CompileRecord, memory_figures
from .errors import NncgError
from .ir.graph import ConvAttrs, DenseAttrs, Graph, Node, QConvAttrs
from .ir.kinds import BufferRole, ConvAlgorithm, VectorAxis
from .ir.loops import Kernel, Loop, Program, Store, walk_stmts
from .lowering.context import layer_names
from .output_files import write_files
from .passes import REGISTRY, parse_pipeline
from .passes.plan_memory import FLOAT_BYTES, kernel_access, lifetimes
from .passes.register_block import chosen_blocks
from .safe_text import html_text, markdown_text
from .tools import run_tool

TEXT_LIMIT = 2000  # characters of a long outside text (the pipeline) shown


class ReportError(NncgError):
    """The report cannot be made (matplotlib missing, a model compiled without its record)."""


@dataclass(frozen=True)
class Measurements:
    """What --verify (nncg.verify.VerifyReport), --benchmark (bench.benchmark.BenchResult) and
    --profile (a list of bench.benchmark.LayerTime) returned; None where it did not run."""

    verify: object | None = None
    benchmark: object | None = None
    profile: list | None = None


@dataclass(frozen=True)
class BufferSpan:
    """An arena buffer: bytes from its offset, live from layer `first` to layer `last`."""

    name: str
    offset: int
    size: int
    first: int
    last: int


@dataclass(frozen=True)
class LayerRow:
    index: int
    name: str  # the kernel's C name (NAME_<name> in the C)
    op: str
    shape: tuple[int, ...]  # of its output
    parameters: int  # the model's weights this layer uses (after folding), 0 for a helper kernel
    macs: int
    weight_bytes: int  # the arrays it reads from the C file or NAME.weights (inlined literals are code)
    choices: tuple[str, ...]
    writes: tuple[BufferSpan | str, ...]  # arena buffers it writes, or the caller's buffer's role


@dataclass(frozen=True)
class ObjectSize:
    """Section sizes of NAME.o, or why there are none; `command` is how it was built."""

    sizes: ObjectSizes | None
    command: str


def require_plots():
    """The plot module; ReportError (one line, what to install) when matplotlib is missing."""
    try:
        return importlib.import_module(f"{__package__}.report_plot")
    except ImportError as exc:
        raise ReportError(
            f"--report draws its plots with matplotlib, which cannot be imported ({exc}): pip install matplotlib"
        ) from None


def write_report(
    compiled: CompiledModel,
    directory: str | os.PathLike,
    measurements: Measurements | None = None,
    cc: str | None = None,
) -> tuple[Path, ...]:
    """Writes NAME.report.html and NAME.report.md into `directory`, all or nothing; `cc` builds NAME.c
    for the section sizes (default: cc, gcc or clang on PATH; none found: the report says so)."""
    plots = require_plots()
    if compiled.record is None:
        raise ReportError("the model has no compile record: make it with nncg.compile or nncg.emit")
    measurements = measurements or Measurements()
    rows = layer_rows(compiled)
    spans = buffer_spans(compiled.record.program)
    size = object_size(compiled, cc)
    images = {"memory": plots.memory_timeline(spans, len(rows), compiled.arena_bytes)}
    if measurements.profile:
        profile = measurements.profile
        images["profile"] = plots.layer_times([r.layer for r in profile], [r.us for r in profile])
    if measurements.benchmark is not None:
        images["benchmark"] = plots.runtimes(*benchmark_times(measurements.benchmark))
    files = {
        f"{compiled.name}.report.html": html_page(compiled, rows, size, measurements, images).encode(),
        f"{compiled.name}.report.md": markdown_page(compiled, rows, size, measurements).encode(),
    }
    return write_files(directory, files)


# ---------------------------------------------------------------------------- what the report shows


def layer_rows(compiled: CompiledModel) -> list[LayerRow]:
    record = compiled.record
    program = record.program
    nodes = _nodes_by_layer(record.lowered)
    blocks = _register_blocks(compiled, record)
    spans = {span.name: span for span in buffer_spans(program)}
    rows = []
    for index, kernel in enumerate(program.kernels):
        node = nodes.get(kernel.name)
        access = kernel_access(kernel)
        constants = [b for b in map(program.buffer, sorted(access.reads)) if b.role == BufferRole.CONSTANT]
        written = [program.buffer(name) for name in sorted(access.writes)]
        rows.append(
            LayerRow(
                index=index,
                name=kernel.name,
                op=node.op if node else kernel.op,
                shape=record.lowered.shape(node.outputs[0]) if node else (written[0].shape if written else ()),
                parameters=_parameters(record.lowered, node) if node else 0,
                macs=node_macs(record.lowered, node) if node else 0,
                weight_bytes=sum(b.size for b in constants) * FLOAT_BYTES,
                choices=layer_choices(kernel, node, blocks.get(kernel.name)),
                writes=tuple(spans.get(b.name, f"{b.role} {b.name}") for b in written),
            )
        )
    return rows


def buffer_spans(program: Program) -> list[BufferSpan]:
    """Every arena buffer with its place and lifetime (plan-memory's), in order of first use."""
    spans = lifetimes(program)
    return sorted(
        (
            BufferSpan(b.name, b.offset * FLOAT_BYTES, b.size * FLOAT_BYTES, *spans[b.name])
            for b in program.role(BufferRole.INTERNAL)
            if b.name in spans and b.offset is not None
        ),
        key=lambda s: (s.first, s.offset, s.name),
    )


def layer_choices(kernel: Kernel, node: Node | None, block: tuple[int, int] | None) -> tuple[str, ...]:
    """What the passes chose for one layer, in pipeline order: graph passes (in the node's attributes),
    then vectorize (lanes of its stores), register-block and unroll (loops left)."""
    choices = list(_graph_choices(node.attrs)) if node else []
    lanes = sorted({s.value.lanes for s in walk_stmts(kernel.body) if isinstance(s, Store)} - {1}, reverse=True)
    choices.append(f"vectors of {'+'.join(map(str, lanes))} lanes" if lanes else "scalar")
    if block:
        choices.append(f"register block {block[0]}x{block[1]} (pixels x channel vectors)")
    loops = sum(isinstance(s, Loop) for s in walk_stmts(kernel.body))
    choices.append(f"{loops} loop{'s' * (loops != 1)} left after unroll" if loops else "fully unrolled")
    return tuple(choices)


def _graph_choices(attrs) -> list[str]:
    choices = []
    if isinstance(attrs, ConvAttrs):
        if attrs.algorithm == ConvAlgorithm.WINOGRAD:
            padded = f", GEMMs padded to {attrs.gemm_channels} channels" if attrs.gemm_channels else ""
            choices.append(f"winograd F(2x2,3x3){padded}")
        elif attrs.panel:
            block = f" x {attrs.ci_block} input channels" if attrs.ci_block else ""
            choices.append(f"cache-blocked: panels of {attrs.panel} output channels{block}")
        else:
            choices.append("direct")
        if attrs.channel_block:
            choices.append(f"depthwise in channel blocks of {attrs.channel_block}")
        if attrs.vector_axis == VectorAxis.PIXELS:
            choices.append("vectorised over pixels")
        if attrs.residual:
            choices.append("fused residual add")
    if isinstance(attrs, QConvAttrs) and attrs.algorithm == ConvAlgorithm.WINOGRAD:
        choices.append("integer winograd F(2x2,3x3)")
    if isinstance(attrs, DenseAttrs) and attrs.panel:
        streams = f", each read in {attrs.streams} reduction streams" if attrs.streams > 1 else ""
        choices.append(f"weights packed in panels of {attrs.panel} columns{streams}")
    activation = getattr(attrs, "activation", None)
    if activation is not None:
        choices.append(f"fused {activation}")
    return choices


def _nodes_by_layer(graph: Graph | None) -> dict[str, Node]:
    """Kernel name -> the graph node it computes (a kernel no node has, such as a copy, is absent)."""
    if graph is None:
        return {}
    _, names = layer_names(graph)
    return {names[node.name]: node for node in graph.nodes}


def _register_blocks(compiled: CompiledModel, record: CompileRecord) -> dict[str, tuple[int, int]]:
    """Layer -> the block register-block chose, asked of the pass with the pipeline's own `layers`."""
    if record.before_register_block is None:
        return {}
    from .backends import get_target

    specs = [s for s in parse_pipeline(compiled.pipeline) if s.name == "register-block"]
    params = {k: REGISTRY["register-block"].params[k](v) for k, v in specs[0].params} if specs else {}
    return chosen_blocks(record.before_register_block, get_target(compiled.target), params.get("layers"))


def _parameters(graph: Graph, node: Node) -> int:
    return sum(int(graph.constants[name].size) for name in set(node.inputs) if graph.is_constant(name))


def object_size(compiled: CompiledModel, cc: str | None) -> ObjectSize:
    """NAME.c built with `cc -O2 -c` and the target's flags, measured with binutils' size."""
    from .verify import find_c_compiler

    try:
        compiler = find_c_compiler(cc)
    except NncgError as exc:
        return ObjectSize(None, f"not measured: {exc}")
    command = [compiler, "-O2", *compiled.cflags, "-c", f"{compiled.name}.c", "-o", f"{compiled.name}.o"]
    with tempfile.TemporaryDirectory(prefix="nncg-report-") as tmp:
        compiled.write(tmp)
        try:
            run_tool(command, f"compiling {compiled.name}.c", cwd=tmp)
            return ObjectSize(object_sizes(Path(tmp) / f"{compiled.name}.o"), " ".join(command))
        except NncgError as exc:  # its one line keeps the compiler's output after an escaped newline
            head = str(exc).partition("\\n")[0]
            return ObjectSize(None, f"not measured for target {compiled.target} on this host: {head}")


def benchmark_times(result) -> tuple[list[str], list[float]]:
    return (
        ["NNCG", "onnxruntime (IOBinding)", "onnxruntime (run)"],
        [result.nncg_us, result.ort_bound_us, result.ort_run_us],
    )


def model_facts(compiled: CompiledModel) -> list[tuple[str, str]]:
    """(what, value) of the model section; values are outside text, escaped by the page."""
    record = compiled.record
    weights = "embedded in the C file" if compiled.weights is None else f"in {compiled.name}.weights, passed by pointer"
    return [
        ("target", compiled.target),
        ("pipeline", compiled.pipeline),
        ("operators (as imported)", ", ".join(f"{op} x{count}" for op, count in record.operators)),
        ("parameters", f"{record.parameters:,}"),
        ("MACs per inference", f"{compiled.macs:,}"),
        ("arena (planned activation memory)", f"{compiled.arena_bytes:,} bytes"),
        ("activations without reuse", f"{compiled.activation_bytes:,} bytes"),
        *memory_facts(compiled),
        ("weights", weights),
    ]


def memory_facts(compiled: CompiledModel) -> list[tuple[str, str]]:
    """The arena's yardsticks and the band plan (nncg.compiler.memory_figures)."""
    figures = memory_figures(compiled)
    if figures is None:
        return []
    return [
        ("layer-by-layer bound (largest layer computed whole)", f"{figures.layer_bound_bytes:,} bytes"),
        ("all activations side by side", f"{figures.all_activation_bytes:,} bytes"),
        ("memory plan", figures.plan),
    ]


def _shape(shape: tuple[int, ...]) -> str:
    return "x".join(map(str, shape)) or "scalar"


def _written(item: BufferSpan | str) -> str:
    if isinstance(item, str):
        return item
    return f"{item.name} @ {item.offset:,} ({item.size:,} B, layers {item.first}-{item.last})"


def _layer_cells(row: LayerRow) -> list[str]:
    return [
        str(row.index), row.name, row.op, _shape(row.shape), f"{row.parameters:,}", f"{row.macs:,}",
        f"{row.weight_bytes:,}", "; ".join(row.choices), "; ".join(map(_written, row.writes)),
    ]  # fmt: skip


LAYER_HEADER = [
    "#", "layer", "op", "output shape", "parameters", "MACs", "weight bytes", "passes chose",
    "writes (arena offset, size, live layers)",
]  # fmt: skip


def _size_cells(size: ObjectSize) -> list[list[str]]:
    s = size.sizes
    if s is None:
        return []
    return [[str(s.text), str(s.rodata), str(s.data), str(s.bss), str(s.text + s.rodata), str(s.data + s.bss)]]


SIZE_HEADER = ["text", "rodata", "data", "bss", "flash (text+rodata)", "RAM (data+bss: the arena is in bss)"]


def _verify_header(report) -> list[str]:
    """The outputs' table header; a quantised model's has its errors in quantisation steps too."""
    steps = ["max steps", "identical"] if any(s.quantized for s in report.stats) else []
    return ["output", "shape", "max abs err", "max rel err", *steps, "problem"]


def _verify_cells(report) -> list[list[str]]:
    steps = any(s.quantized for s in report.stats)
    return [
        [
            s.name,
            _shape(s.shape),
            f"{s.max_abs:.3g}",
            f"{s.max_rel:.3g}",
            *(s.step_cells() if steps else ()),
            s.problem or "",
        ]
        for s in report.stats
    ]


def _verify_verdict(report) -> str:
    verdict = "PASS" if report.ok else "FAIL"
    return f"{verdict}: {report.requirement} required (seed {report.seed})"


def _benchmark_cells(result) -> list[list[str]]:
    peak = "n/a" if result.percent_of_peak is None else f"{result.percent_of_peak:.1f} ({result.peak_isa})"
    return [[
        f"{result.nncg_us:.2f}", f"{result.ort_bound_us:.2f}", f"{result.ort_run_us:.2f}", f"{result.speedup:.2f}x",
        f"{result.gflops:.2f}", peak, f"{result.max_rel_err:.1e}",
    ]]  # fmt: skip


BENCHMARK_HEADER = ["NNCG µs", "ORT µs (IOBinding)", "ORT run µs", "speed-up", "GFLOP/s", "% of peak", "max rel err"]


def _profile_cells(rows) -> list[list[str]]:
    return [[r.layer, f"{r.us:.2f}", f"{r.percent:.1f}", f"{r.macs:,}", f"{r.gflops:.2f}"] for r in rows]


PROFILE_HEADER = ["layer", "µs", "%", "MACs", "GFLOP/s"]


# ---------------------------------------------------------------------------- HTML

CSS = """body{font:14px/1.45 system-ui,sans-serif;margin:24px;color:#222;max-width:1400px}
h1{font-size:22px}h2{font-size:18px;margin-top:28px;border-bottom:1px solid #ccc}
table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #ccc;padding:3px 7px;vertical-align:top}
th{background:#f0f0f0;text-align:left}td.num{text-align:right}tr:nth-child(even) td{background:#fafafa}
img{max-width:100%;border:1px solid #ddd}code{background:#f4f4f4;padding:1px 3px;word-break:break-all}
.fail{color:#b00;font-weight:bold}.pass{color:#070;font-weight:bold}"""


def html_page(compiled, rows, size, measurements, images) -> str:
    name = html_text(compiled.name)
    parts = [
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8" />',
        f"<title>NNCG report: {name}</title><style>{CSS}</style></head><body>",
        f"<h1>NNCG report: {name}</h1>",
        "<h2>Model</h2>",
        _html_table(["what", "value"], [list(fact) for fact in model_facts(compiled)], TEXT_LIMIT, numbers=False),
        "<h3>Inputs and outputs</h3>",
        _html_table(["role", "ONNX name", "C name", "shape"], _params(compiled)),
        "<h2>Layers</h2>",
        _html_table(LAYER_HEADER, [_layer_cells(r) for r in rows], limit=TEXT_LIMIT),
        "<h2>Memory</h2>",
        f"<p>Arena: {compiled.arena_bytes:,} bytes; each bar is a buffer over the layers it is live in.</p>",
        _html_image(images["memory"], "arena buffers over layers and bytes live per layer"),
        "<h2>Object size</h2>",
        f"<p><code>{html_text(size.command, TEXT_LIMIT)}</code></p>",
        _html_table(SIZE_HEADER, _size_cells(size)) if size.sizes else "",
        *_html_measurements(measurements, images),
        "</body></html>\n",
    ]
    return "\n".join(part for part in parts if part)


def _html_measurements(measurements: Measurements, images: dict[str, bytes]) -> list[str]:
    parts = []
    if measurements.verify is not None:
        report = measurements.verify
        verdict = "pass" if report.ok else "fail"
        parts += [
            "<h2>Verify (against onnxruntime)</h2>",
            _html_table(_verify_header(report), _verify_cells(report)),
            f'<p class="{verdict}">{html_text(_verify_verdict(report))}</p>',
        ]
    if measurements.benchmark is not None:
        parts += [
            "<h2>Benchmark</h2>",
            _html_table(BENCHMARK_HEADER, _benchmark_cells(measurements.benchmark)),
            f"<p>{html_text(SPEEDUP_NOTE)}</p>",
            _html_image(images["benchmark"], "NNCG and onnxruntime times"),
        ]
    if measurements.profile:
        parts += [
            "<h2>Profile</h2>",
            _html_image(images["profile"], "time per layer"),
            _html_table(PROFILE_HEADER, _profile_cells(measurements.profile)),
        ]
    return parts


def _params(compiled: CompiledModel) -> list[list[str]]:
    return [
        [role, p.name, p.c_name, _shape(p.shape)]
        for role, params in (("input", compiled.inputs), ("output", compiled.outputs))
        for p in params
    ]


def _html_table(header: list[str], rows: list[list[str]], limit: int = 200, numbers: bool = True) -> str:
    """`numbers`: right-align the cells that are numbers (a column of them)."""
    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join(
        "<tr>" + "".join(_html_cell(cell, limit, numbers) for cell in row) + "</tr>\n" for row in rows
    )  # fmt: skip
    return f"<table>\n<thead><tr>{head}</tr></thead>\n<tbody>\n{body}</tbody></table>"


def _html_cell(text: str, limit: int, numbers: bool) -> str:
    numeric = numbers and text.replace(",", "").replace(".", "").isdigit()
    opening = '<td class="num">' if numeric else "<td>"
    return f"{opening}{html_text(text, limit)}</td>"


def _html_image(png: bytes, alt: str) -> str:
    data = base64.b64encode(png).decode("ascii")
    return f'<p><img alt="{html_text(alt)}" src="data:image/png;base64,{data}" /></p>'


# ---------------------------------------------------------------------------- Markdown


def markdown_page(compiled, rows, size, measurements) -> str:
    lines = [
        f"# NNCG report: {markdown_text(compiled.name)}",
        "",
        "Plots: see the HTML report beside this file.",
        "",
        "## Model",
        "",
        _md_table(["what", "value"], [list(fact) for fact in model_facts(compiled)], limit=TEXT_LIMIT),
        "",
        _md_table(["role", "ONNX name", "C name", "shape"], _params(compiled)),
        "",
        "## Layers",
        "",
        _md_table(LAYER_HEADER, [_layer_cells(r) for r in rows], limit=TEXT_LIMIT),
        "",
        "## Object size",
        "",
        markdown_text(size.command, TEXT_LIMIT),
        "",
    ]
    if size.sizes:
        lines += [_md_table(SIZE_HEADER, _size_cells(size)), ""]
    lines += _md_measurements(measurements)
    return "\n".join(lines)


def _md_measurements(measurements: Measurements) -> list[str]:
    lines = []
    if measurements.verify is not None:
        report = measurements.verify
        lines += [
            "## Verify (against onnxruntime)", "",
            _md_table(_verify_header(report), _verify_cells(report)), "",
            markdown_text(_verify_verdict(report)), "",
        ]  # fmt: skip
    if measurements.benchmark is not None:
        table = _md_table(BENCHMARK_HEADER, _benchmark_cells(measurements.benchmark))
        lines += ["## Benchmark", "", table, "", markdown_text(SPEEDUP_NOTE), ""]
    if measurements.profile:
        lines += ["## Profile", "", _md_table(PROFILE_HEADER, _profile_cells(measurements.profile)), ""]
    return lines


def _md_table(header: list[str], rows: list[list[str]], limit: int = 200) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]  # NNCG's own words
    lines += ["| " + " | ".join(markdown_text(cell, limit) for cell in row) + " |" for row in rows]
    return "\n".join(lines)

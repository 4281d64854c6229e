"""`nncg-onnx`: the command line. Bad input is one line on stderr and exit status 2."""

from __future__ import annotations

import argparse
import re
import shlex
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import NoReturn

from . import __version__
from .arguments import DIM_MAX, REQUANTIZE_FORMS
from .backends import BACKENDS
from .errors import NncgError, NncgWarning
from .host_cpu import check_host_runs
from .lowering.band_plan import MEMORY_MODES
from .options import CompileOptions
from .output_files import check_output_folder, write_files
from .passes.unroll import CODE_BUDGET
from .safe_text import shown, terminal_line


class Parser(argparse.ArgumentParser):
    """argparse with every usage error as one line on stderr and exit status 2 (the usage text stays
    behind --help): a typo should not bury the error under forty lines."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {terminal_line(message)} (see {self.prog} --help)\n")


def parse_input_shape(text: str) -> tuple[str, tuple[int, ...]]:
    name, sep, dims = text.rpartition("=")
    if not sep or not name or not dims:
        raise argparse.ArgumentTypeError(f"{shown(text)} is not NAME=DIMxDIMx... (e.g. image=1x3x60x80)")
    sizes = dims.split("x")
    if not all(re.fullmatch(r"[0-9]+", size) and 0 < int(size) <= DIM_MAX for size in sizes):
        raise argparse.ArgumentTypeError(
            f"{shown(text)}: every dimension must be a whole number from 1 to 2**63-1 (e.g. image=1x3x60x80)"
        )
    return name, tuple(int(size) for size in sizes)


def whole_number(text: str) -> int:
    """An int >= 0 (a code budget, a core number)."""
    if not re.fullmatch(r"[0-9]+", text):
        raise argparse.ArgumentTypeError(f"{shown(text)} is not a whole number >= 0")
    return int(text)


def positive_number(text: str) -> int:
    """An int >= 1 (a byte count)."""
    if not re.fullmatch(r"[0-9]+", text) or int(text) < 1:
        raise argparse.ArgumentTypeError(f"{shown(text)} is not a whole number >= 1")
    return int(text)


def non_empty(text: str) -> str:
    if not text:
        raise argparse.ArgumentTypeError("must not be empty")
    return text


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="nncg-onnx",
        description="Compile an ONNX CNN into one plain C file and header (NAME.c, NAME.h).",
    )
    p.add_argument(
        "model", nargs="?", help="the .onnx file, or a Keras .keras/.h5 file or SavedModel folder (needs nncg[keras])"
    )
    p.add_argument("--target", default="ansi-c", choices=sorted(BACKENDS), help="code to print (default: ansi-c)")
    p.add_argument("-o", "--output-dir", default=".", type=non_empty, help="where NAME.c and NAME.h go (default: .)")
    p.add_argument("--name", type=non_empty, help="C function and file name (default: the model file's stem)")
    p.add_argument(
        "--cmake",
        action="store_true",
        help="also write a CMakeLists.txt defining the static library NAME (add_subdirectory() the folder, "
        "then target_link_libraries(app PRIVATE NAME))",
    )
    p.add_argument(
        "--unroll",
        default="auto",
        metavar="auto|LEVEL|none",
        help="auto: unroll each loop that expands to at most 64 statements (register-blocked layers keep "
        "their reduction loops); LEVEL: keep the LEVEL outermost loops of each layer, unroll the rest "
        "(the paper's levels; 0 unrolls everything); none: nothing (default: auto)",
    )
    add_input_shape_option(p)
    p.add_argument(
        "--code-budget",
        type=whole_number,
        default=CODE_BUDGET,
        metavar="N",
        help=f"statements of unrolled code in the whole model: loops whose unrolling would exceed it stay loops "
        f"(default {CODE_BUDGET}; 0: no cap, the paper's levels exactly)",
    )
    p.add_argument(
        "--memory",
        choices=MEMORY_MODES,
        default="speed",
        help="speed (default): every layer computed whole; min: the smallest activation arena, chains of "
        "layers run in bands of rows with line buffers; balanced: half of speed's arena or less where the "
        "estimated latency stays within 1.3x of speed's, else the smallest arena within 1.3x",
    )
    p.add_argument(
        "--ram-budget",
        type=positive_number,
        metavar="BYTES",
        help="the fastest plan whose activation arena fits BYTES; refused (exit 2) with the smallest arena "
        "when none does",
    )
    p.add_argument(
        "--weights",
        choices=("auto", "embed", "bin"),
        default="auto",
        help="embed: weights as static const arrays in the C file; bin: in NAME.weights, which the caller "
        "passes by pointer; auto (default): bin above 4 MiB of weights",
    )
    p.add_argument(
        "--requantize",
        choices=REQUANTIZE_FORMS,
        default="float",
        help="int8 models: how integer layers scale their int32 results; float (default): onnxruntime's "
        "arithmetic, bit-exact; fixed: int32 multiplier and rounding shift, no float (cores without an FPU)",
    )
    p.add_argument(
        "--input-layout",
        choices=("nchw", "nhwc"),
        help="layout of the C function's 4-D inputs (default: the model's own; Keras models are nhwc): the other "
        "one inserts a Transpose at the input, which the passes cancel against the model's own",
    )
    p.add_argument(
        "--calibration",
        metavar="PATH",
        help="quantise the model to int8 first (onnxruntime.quantization: QDQ, uint8 activations, int8 weights per "
        "output channel) on these inputs: an .npz keyed by input name with the samples along the first axis, or a "
        "folder of .npy files, one sample each; writes NAME.qdq.onnx beside the C (nncg-quantize has more settings)",
    )
    p.add_argument("--pipeline", help="run this pass pipeline instead of the default (see --list-passes)")
    p.add_argument(
        "--tune",
        action="store_true",
        help="time variants of every register-blocked layer (block shape, unroll budget) with --cc on this "
        "machine and keep each layer's fastest; choices are cached by layer and target (~/.cache/nncg/tune.json)",
    )
    p.add_argument(
        "--tune-runner",
        metavar="CMD",
        help="with --tune: run the timing programs through CMD, e.g. 'qemu-aarch64 -L /usr/aarch64-linux-gnu' "
        "or a script that runs them on a board (with --cc a cross compiler)",
    )
    p.add_argument("--print-ir-after-all", action="store_true", help="print the IR after every pass to stderr")
    p.add_argument(
        "--verify",
        action="store_true",
        help="compile the C with the host compiler, run it and onnxruntime on the same random "
        "inputs, print the errors; exit 1 above tolerance. A quantised output (a DequantizeLinear's or "
        "QuantizeLinear's) is judged in quantisation steps: max steps and share identical, pass within one step",
    )
    p.add_argument(
        "--per-layer",
        action="store_true",
        help="with --verify: also build a debug build that writes every layer's output, compare each with "
        "onnxruntime's and name the first layer above tolerance",
    )
    p.add_argument(
        "--tolerance", type=float, default=1e-4, help="max relative error for --verify of a float output (default 1e-4)"
    )
    p.add_argument(
        "--benchmark",
        action="store_true",
        help="time the generated C (-O3) against onnxruntime (1 thread, IOBinding and plain run), "
        "interleaved; print speed-up, GFLOP/s, %% of the ISA's peak, error and object sizes",
    )
    p.add_argument("--profile", action="store_true", help="time every layer of the generated C; print µs, %% and MACs")
    p.add_argument(
        "--report",
        action="store_true",
        help="also write NAME.report.html (one self-contained page with plots) and NAME.report.md: layers, "
        "the passes' choices, the memory plan, object sizes and the --verify/--benchmark/--profile results "
        "(needs matplotlib)",
    )
    p.add_argument("--cpu", type=whole_number, help="pin --benchmark/--profile to this core")
    p.add_argument("--cc", help="C compiler for --verify, --benchmark, --profile (default: cc, gcc or clang on PATH)")
    p.add_argument("--list-passes", action="store_true", help="list the passes and the default pipeline, then exit")
    p.add_argument("--debug", action="store_true", help="show the traceback of an internal error")
    p.add_argument("--version", action="version", version=f"nncg {__version__}")
    return p


def add_input_shape_option(p: argparse.ArgumentParser) -> None:
    """--input-shape NAME=DIMS, repeatable, as input_shapes() reads it."""
    p.add_argument(
        "--input-shape",
        action="append",
        type=parse_input_shape,
        default=[],
        metavar="NAME=DIMS",
        help="fix a dynamic input shape, e.g. image=1x3x60x80 (repeatable)",
    )


def main(argv: list[str] | None = None) -> int:
    return run_command(build_parser(), run, argv)


def run_command(
    parser: argparse.ArgumentParser, run: Callable[[argparse.Namespace], int], argv: list[str] | None
) -> int:
    """Runs `run` on the parsed `argv`: bad input (NncgError, a file-system error) is one line on stderr
    and exit status 2, any other exception a bug, status 3; NNCG's notes follow a successful run."""
    args = parser.parse_args(argv)
    prog = parser.prog
    notes: list[str] = []
    try:
        with collected_notes(notes):
            status = run(args)
    except NncgError as exc:
        return fail(str(exc), prog)
    except OSError as exc:  # the file system's answer (a full disk, a vanished file): the user's to fix
        if args.debug:
            raise
        return fail(f"{exc} (check the paths given, free space and permissions)", prog)
    except Exception as exc:
        if args.debug:
            raise
        print(
            terminal_line(
                f"{prog}: internal error: {type(exc).__name__}: {exc} (a bug in NNCG: please report it "
                "with the model; --debug shows the traceback)"
            ),
            file=sys.stderr,
        )
        return 3
    for note in notes:  # after the run, so that bad input stays one error line
        print(terminal_line(f"{prog}: note: {note}"), file=sys.stderr)
    return status


@contextmanager
def collected_notes(notes: list[str]) -> Iterator[None]:
    """NNCG's warnings (defaults it chose, such as batch 1) into `notes`, each text once; other
    warnings are shown as usual."""
    with warnings.catch_warnings():
        warnings.simplefilter("always", NncgWarning)
        show = warnings.showwarning

        def collect(message, category, *args, **kwargs):
            if not issubclass(category, NncgWarning):
                return show(message, category, *args, **kwargs)
            if str(message) not in notes:
                notes.append(str(message))

        warnings.showwarning = collect
        yield


def fail(message: str, prog: str) -> int:
    """Prints `message` as the one error line; returns exit status 2."""
    print(terminal_line(f"{prog}: error: {message}"), file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    from .backends import get_target
    from .compiler import compile, onnx_model
    from .frontend.keras_export import is_keras_path
    from .passes import REGISTRY, default_pipeline
    from .quantization import quantize

    if args.list_passes:
        for info in REGISTRY.values():
            params = f"{{{','.join(f'{k}=...' for k in info.params)}}}" if info.params else ""
            print(f"{info.name + params:28} {info.stage:6} {info.doc}")
        print(f"\ndefault pipeline (ssse3): {default_pipeline(get_target('ssse3'))}")
        return 0
    if not args.model:
        raise NncgError("no model given: nncg-onnx MODEL.onnx --target ssse3 -o build/")
    if args.per_layer and not args.verify:
        raise NncgError("--per-layer is a kind of --verify: give both")
    check_output_folder(Path(args.output_dir))  # before compiling (or tuning for a minute)
    if args.verify or args.benchmark or args.profile or (args.tune and not args.tune_runner):
        check_host_runs(args.target)  # they run the code here: say so now, not as a crash after writing
    if args.report:
        from .report import require_plots

        require_plots()
    options = CompileOptions.of(
        args.unroll, args.weights, args.code_budget, args.pipeline, args.memory, args.ram_budget, args.requantize
    )
    if is_keras_path(args.model) or args.input_layout:  # converted once: --verify, --tune, ... use it too
        args.name = args.name or Path(args.model).stem
        args.model = onnx_model(args.model, args.input_layout)[0]
    if args.calibration:  # quantised once, like a Keras model converted: --verify, --tune, ... take the QDQ model
        args.name = args.name or Path(args.model).stem
        args.model = quantize(args.model, args.calibration, input_shapes=input_shapes(args))
    if args.tune or args.tune_runner:
        options = options.with_pipeline(tune_command(args))
    compiled = compile(
        args.model,
        input_layout=args.input_layout,
        target=args.target,
        name=args.name,
        input_shapes=input_shapes(args),
        print_ir_after_all=sys.stderr if args.print_ir_after_all else None,
        **options.kwargs(),
    )
    files = compiled.files(args.output_dir, cmake=args.cmake)
    if args.calibration:
        files[f"{compiled.name}.qdq.onnx"] = args.model.SerializeToString(deterministic=True)
    print_written(write_files(args.output_dir, files))
    results: dict[str, object] = {}  # what --report shows of --verify, --benchmark and --profile
    status = verify_command(args, compiled, options, results) if args.verify else 0
    if args.benchmark or args.profile:
        measure_command(args, options, results)
    if args.report:
        report_command(args, compiled, results)
    return status


def print_written(paths) -> None:
    print(terminal_line(f"wrote {', '.join(f'{p} ({p.stat().st_size} bytes)' for p in paths)}"))


def input_shapes(args: argparse.Namespace) -> dict[str, tuple[int, ...]] | None:
    """The --input-shape options as compile() takes them; an input given twice is an error."""
    shapes: dict[str, tuple[int, ...]] = {}
    for name, shape in args.input_shape:
        if name in shapes:
            raise NncgError(f"--input-shape gives input {shown(name)} twice; give each input once")
        shapes[name] = shape
    return shapes or None


def tune_command(args: argparse.Namespace) -> str:
    from .tune import tune

    if args.pipeline:
        raise NncgError("--tune builds its own pipeline: give --tune or --pipeline, not both")
    if args.unroll != "auto":
        raise NncgError("--tune chooses unroll budgets per layer: leave --unroll at auto")
    if args.memory != "speed" or args.ram_budget:
        raise NncgError("--tune times the layers computed whole: give --tune or --memory/--ram-budget, not both")
    if args.requantize != "float":
        raise NncgError("--tune times the default pipeline: give --tune or --requantize fixed, not both")
    return tune(
        args.model, args.target, cc=args.cc, runner=shlex.split(args.tune_runner or ""),
        input_shapes=input_shapes(args), weights=args.weights, code_budget=args.code_budget or None,
        cpu=args.cpu,
    )  # fmt: skip


def verify_command(
    args: argparse.Namespace, compiled, compile_options: CompileOptions, results: dict[str, object]
) -> int:
    """The outputs' table (and with --per-layer every layer's); 1 when any is above tolerance."""
    from .frontend import load_model
    from .verify import verify
    from .verify_layers import verify_per_layer

    model = load_model(args.model, input_shapes(args))
    reports = [verify(model, compiled, tolerance=args.tolerance, cc=args.cc)]
    results["verify"] = reports[0]
    if args.per_layer:
        options = dict(name=args.name, input_shapes=input_shapes(args), **compile_options.kwargs())
        reports.append(verify_per_layer(args.model, args.target, tolerance=args.tolerance, cc=args.cc, **options))
    print("\n".join(report.format() for report in reports))
    return 0 if all(report.ok for report in reports) else 1


def measure_command(args: argparse.Namespace, compile_options: CompileOptions, results: dict[str, object]) -> None:
    from .bench.benchmark import benchmark, format_profile, format_results, profile

    options = dict(
        target=args.target, cc=args.cc, cpu=args.cpu, input_shapes=input_shapes(args), name=args.name,
        **compile_options.kwargs(),
    )  # fmt: skip
    if args.benchmark:
        results["benchmark"] = benchmark(args.model, **options)
        print(format_results([results["benchmark"]]))
    if args.profile:
        results["profile"] = profile(args.model, **options)
        print(format_profile(results["profile"]))


def report_command(args: argparse.Namespace, compiled, results: dict[str, object]) -> None:
    from .report import Measurements, write_report

    paths = write_report(compiled, args.output_dir, Measurements(**results), cc=args.cc)
    print_written(paths)


if __name__ == "__main__":
    sys.exit(main())

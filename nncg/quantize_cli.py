"""`nncg-quantize`: a float ONNX model and calibration inputs to its QDQ model (nncg.quantize), written
all or nothing. Bad input is one line on stderr and exit status 2, as for nncg-onnx."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import __version__
from .cli import Parser, add_input_shape_option, input_shapes, non_empty, print_written, run_command
from .errors import NncgError
from .output_files import check_output_folder, write_files
from .quantization import ACTIVATIONS, CALIBRATE_METHODS, quantize
from .safe_text import shown


def build_parser() -> argparse.ArgumentParser:
    p = Parser(
        prog="nncg-quantize",
        description="Quantise a float ONNX model to int8 in the QDQ format with onnxruntime.quantization (static "
        "activation ranges from the calibration inputs, int8 weights per output channel); nncg-onnx compiles the "
        "result.",
    )
    p.add_argument("model", help="the float .onnx file")
    p.add_argument(
        "--calibration",
        required=True,
        metavar="PATH",
        help="an .npz keyed by input name, each array the samples along the first axis (N, *input shape), or a "
        "folder of .npy files, one sample each, for a one-input model",
    )
    p.add_argument("-o", "--output", required=True, type=non_empty, metavar="FILE", help="the QDQ model to write")
    p.add_argument(
        "--activations",
        choices=ACTIVATIONS,
        default="uint8",
        help="type of the quantised activations (default uint8; TFLite uses int8)",
    )
    p.add_argument(
        "--method", choices=CALIBRATE_METHODS, default="minmax", help="how ranges are calibrated (default minmax)"
    )
    p.add_argument(
        "--per-tensor", action="store_true", help="one scale per weight tensor instead of one per output channel"
    )
    p.add_argument(
        "--reduce-range",
        action="store_true",
        help="7-bit weights (-64..64), as onnxruntime advises on x86 without VNNI: ssse3 and avx2 then multiply four "
        "input channels per pmaddubsw in every layer, at half the weight resolution",
    )
    add_input_shape_option(p)
    p.add_argument("--debug", action="store_true", help="show the traceback of an internal error")
    p.add_argument("--version", action="version", version=f"nncg {__version__}")
    return p


def main(argv: list[str] | None = None) -> int:
    return run_command(build_parser(), run, argv)


def run(args: argparse.Namespace) -> int:
    output = Path(args.output)
    if output.name in ("", ".", "..") or output.is_dir():
        raise NncgError(f"-o {shown(args.output, 200)} is a folder; give the file to write, e.g. model.int8.onnx")
    check_output_folder(output.parent)  # before calibrating
    quantized = quantize(
        args.model,
        args.calibration,
        activations=args.activations,
        per_channel=not args.per_tensor,
        calibrate_method=args.method,
        input_shapes=input_shapes(args),
        reduce_range=args.reduce_range,
    )
    print_written(write_files(output.parent, {output.name: quantized.SerializeToString(deterministic=True)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())

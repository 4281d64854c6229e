"""Whether an exact integer Winograd F(2x2, 3x3) would pay for the int8 3x3 convolutions (issue 16):
per model and target, the instructions (callgrind Ir, one inference) of each layer Winograd applies to
(a 3x3, stride-1, ungrouped QLinearConv of at least passes/winograd.MIN_INPUT_CHANNELS input channels)
in NNCG's int8 C as compiled, against the prototype benchmarks/int8_winograd.c built for the layer's
geometry and zero points (pmaddwd on int16 input-channel pairs; exact: it checks its outputs against a
scalar direct convolution and exits 1 on any difference, which stops this script).

    python3 -m benchmarks.int8_winograd [--models resnet8 ...] [--targets ssse3 avx2]

ssse3 and avx2 only: valgrind does not run AVX-512. Instruction counts do not depend on the machine's
load; both sides are built by the same compiler with -O2 and the target's flags (NNCG's C with
-fno-inline-functions-called-once, so each layer stays its own function)."""

from __future__ import annotations

import argparse
import math
import re
import subprocess
import tempfile
from pathlib import Path

import nncg
from nncg.frontend import import_onnx
from nncg.ir.c_names import c_identifier
from nncg.passes.winograd import MIN_INPUT_CHANNELS
from nncg.verify import find_c_compiler

from .int8_suite import quantized_model

PROTOTYPE = Path(__file__).with_name("int8_winograd.c")
MAIN = """#include "{name}.h"
static float input[{size}], output[{outputs}];
int main(void) {{ {name}(input, output); return 0; }}
"""


def winograd_layers(model) -> dict[str, dict[str, int]]:
    """C layer name -> the prototype's geometry, for the layers Winograd would take."""
    graph = import_onnx(model, None)
    layers = {}
    for node in graph.nodes:
        a = node.attrs
        if node.op != "QLinearConv" or (a.kernel, a.strides, a.dilations, a.group) != ((3, 3), (1, 1), (1, 1), 1):
            continue
        c_out, c_in = graph.shape(node.inputs[1])[:2]
        rows, columns = graph.shape(node.outputs[0])[2:]
        if c_in < MIN_INPUT_CHANNELS or rows != columns or a.pads_begin != (1, 1):
            continue
        geometry = {"SIZE": rows, "CI": c_in, "CO": c_out, "ZX": a.x_zero_point, "ZY": a.out.zero_point}
        layers[c_identifier(node.name)] = geometry
    return layers


def callgrind(command: list[str], workdir: Path) -> dict[str, int]:
    """Ir per function (inclusive: with the functions it calls) of one run of `command`."""
    out = workdir / "callgrind.out"
    subprocess.run(
        ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", *command], check=True, capture_output=True
    )
    annotate = ["callgrind_annotate", "--inclusive=yes", "--threshold=100", str(out)]
    report = subprocess.run(annotate, check=True, capture_output=True, text=True).stdout
    counts = {}
    for line in report.splitlines():
        match = re.match(r"\s*([\d,]+) \([^)]*\)\s+\S*:(\w+) ", line)
        if match:
            counts[match.group(2)] = int(match.group(1).replace(",", ""))
    return counts


def measure(name: str, target: str, cc: str, workdir: Path) -> list[tuple[str, dict, int, int, int]]:
    """[(layer, geometry, direct Ir, Winograd Ir, the model's Ir)]."""
    model = quantized_model(name)
    compiled = nncg.compile(model, target=target)
    compiled.write(workdir)
    size, outputs = (math.prod(p.shape) for p in (compiled.inputs[0], compiled.outputs[0]))
    (workdir / "main.c").write_text(MAIN.format(name=compiled.name, size=size, outputs=outputs))
    flags = ["-O2", *compiled.cflags]
    binary = workdir / "model"
    sources = [str(workdir / "main.c"), str(workdir / f"{compiled.name}.c")]
    subprocess.run(
        [cc, *flags, "-fno-inline-functions-called-once", f"-I{workdir}", *sources, "-o", str(binary), "-lm"],
        check=True,
    )
    direct = callgrind([str(binary)], workdir)
    rows = []
    for layer, geometry in winograd_layers(model).items():
        prototype = workdir / f"winograd_{layer}"
        defines = [f"-D{k}={v}" for k, v in geometry.items()]
        subprocess.run([cc, *flags, *defines, str(PROTOTYPE), "-o", str(prototype), "-lm"], check=True)
        winograd = callgrind([str(prototype)], workdir)["winograd_layer"]
        rows.append((layer, geometry, direct[f"{compiled.name}_{layer}"], winograd, direct[compiled.name]))
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["resnet8"])
    parser.add_argument("--targets", nargs="+", default=["ssse3", "avx2"], choices=["ssse3", "avx2"])
    args = parser.parse_args(argv)
    cc = find_c_compiler(None)
    print("| model | target | layer | out side x C_in -> C_out | direct Ir | Winograd Ir | Winograd / direct |")
    print("|---|---|---|---|---|---|---|")
    for name in args.models:
        for target in args.targets:
            with tempfile.TemporaryDirectory(prefix="nncg-int8-winograd-") as tmp:
                rows = measure(name, target, cc, Path(tmp))
            for layer, g, direct, winograd, _ in rows:
                shape = f"{g['SIZE']} x {g['CI']} -> {g['CO']}"
                print(
                    f"| {name} | {target} | {layer} | {shape} | {direct:,} | {winograd:,} | {winograd / direct:.2f} |"
                )
            direct, winograd = sum(r[2] for r in rows), sum(r[3] for r in rows)
            total = rows[0][4] if rows else 0
            saved = f"{(direct - winograd) / total:.0%} of the model's {total:,}" if total else "-"
            print(f"| {name} | {target} | all | | {direct:,} | {winograd:,} | saves {saved} |", flush=True)


if __name__ == "__main__":
    main()

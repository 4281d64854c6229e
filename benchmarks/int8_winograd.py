"""What the exact integer Winograd F(2x2, 3x3) (lowering/winograd_integer.py) saves on the int8 3x3
convolutions (issue 16): per model and target, the instructions (callgrind Ir, one inference) of each
layer integer Winograd applies to, compiled with it forced off (direct) and forced on, and of the whole
model both ways.

    python3 -m benchmarks.int8_winograd [--models resnet8 ...] [--targets ansi-c ssse3 avx2]

ansi-c, ssse3 and avx2 only: valgrind does not run AVX-512. Instruction counts do not depend on the
machine's load; both builds by the same compiler with -O2 and the target's flags, and
-fno-inline-functions-called-once, so each layer stays its own function."""

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
from nncg.passes import default_pipeline
from nncg.passes.winograd import winograd_candidates
from nncg.verify import find_c_compiler

from .int8_suite import quantized_model

MAIN = """#include "{name}.h"
static float input[{size}], output[{outputs}];
int main(void) {{ {name}(input, output); return 0; }}
"""


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


def instructions(model, target: str, layers: list[str], winograd: bool, cc: str, workdir: Path) -> dict[str, int]:
    """Ir of the model (key "") and of each of `layers`, Winograd forced on or off on them."""
    flag = "true" if winograd else "false"
    choice = ";".join(f"{name}:{flag}" for name in layers)
    pipeline = default_pipeline(nncg.get_target(target)).replace(",winograd", f",winograd{{layers={choice}}}")
    compiled = nncg.compile(model, target=target, pipeline=pipeline)
    compiled.write(workdir)
    size, outputs = (math.prod(p.shape) for p in (compiled.inputs[0], compiled.outputs[0]))
    (workdir / "main.c").write_text(MAIN.format(name=compiled.name, size=size, outputs=outputs))
    binary = workdir / "model"
    sources = [str(workdir / "main.c"), str(workdir / f"{compiled.name}.c")]
    flags = ["-O2", *compiled.cflags, "-fno-inline-functions-called-once", f"-I{workdir}"]
    subprocess.run([cc, *flags, *sources, "-o", str(binary), "-lm"], check=True)
    counts = callgrind([str(binary)], workdir)
    return {"": counts[compiled.name]} | {layer: counts[f"{compiled.name}_{c_identifier(layer)}"] for layer in layers}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=["resnet8"])
    parser.add_argument(
        "--targets", nargs="+", default=["ansi-c", "ssse3", "avx2"], choices=["ansi-c", "ssse3", "avx2"]
    )
    args = parser.parse_args(argv)
    cc = find_c_compiler(None)
    print("| model | target | layer | direct Ir | Winograd Ir | Winograd / direct |")
    print("|---|---|---|---|---|---|")
    for name in args.models:
        model = quantized_model(name)
        layers = winograd_candidates(import_onnx(model, None))
        for target in args.targets:
            with tempfile.TemporaryDirectory(prefix="nncg-int8-winograd-") as tmp:
                direct, winograd = (instructions(model, target, layers, w, cc, Path(tmp)) for w in (False, True))
            for layer in [*layers, ""]:
                label = layer or "whole model"
                ratio = winograd[layer] / direct[layer]
                print(
                    f"| {name} | {target} | {label} | {direct[layer]:,} | {winograd[layer]:,} | {ratio:.2f} |",
                    flush=True,
                )


if __name__ == "__main__":
    main()

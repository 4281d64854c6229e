"""C test programs around a compiled model — for verification, benchmark timing and bare-metal runs:
one generator, parameterised by how inputs arrive (files named on the command line, or compiled in),
how outputs leave (files, or printed as hex words) and whether commands on stdin drive the calls."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .backends.c_file import PROFILE_CLOCK_DEFAULT
from .errors import NncgError

INDENT = "    "


@dataclass(frozen=True)
class PrintedOutputs:
    """Outputs printed as the 8 hex digits of each element's 32 bits (a float's, or an int32 index's
    two's complement), one per line, through the C function
    `put` (takes a string; semihosting on bare metal) declared in `include`; then the C statements
    `after` run (a stack report, say)."""

    put: str
    include: str
    after: tuple[str, ...] = ()


def harness_source(
    compiled: Any,
    *,
    inputs: Sequence[np.ndarray] | None = None,
    outputs: PrintedOutputs | None = None,
    commands: bool = False,
    profile: bool = False,
) -> str:
    """A C89 program calling `compiled` (a CompiledModel, or anything with its name, inputs, outputs).

    Inputs are read from the files named first on the command line (raw little-endian elements of
    each input's dtype: float32, int8 or uint8), or, given as arrays, compiled in. Outputs are
    written to the files named next (the same format, int32 too), or printed as `outputs` says. Outputs
    start as all-ones bytes (a NaN; index -1), so an element the model never writes shows up. The
    model runs once, or with `commands` (POSIX) as lines on stdin say: "run N" times N calls and
    answers nanoseconds, "profile" answers seconds per layer (a profile build, with `profile`),
    "outputs" writes the outputs and answers "ok", anything else quits."""
    if commands and outputs is not None:
        raise NncgError("a harness driven by commands writes its outputs to files")
    parts = _Parts(compiled, inputs, outputs, commands, profile)
    sections = [
        "\n".join([parts.title(), *parts.includes(), f'#include "{compiled.name}.h"']),
        "\n".join(parts.declarations()),
        *(helper.rstrip("\n") for helper in parts.helpers()),
        "\n".join(parts.main()),
    ]
    return "\n\n".join(sections) + "\n"


class _Parts:
    """The pieces of one harness; each helper function is emitted only when used (-Werror)."""

    def __init__(self, compiled: Any, inputs: Sequence[np.ndarray] | None, outputs: PrintedOutputs | None,
                 commands: bool, profile: bool) -> None:  # fmt: skip
        self.name = compiled.name
        self.in_sizes = [_element_count(spec.shape) for spec in compiled.inputs]
        self.out_sizes = [_element_count(spec.shape) for spec in compiled.outputs]
        self.in_types = [C_TYPES[getattr(spec, "dtype", "float32")] for spec in compiled.inputs]
        self.out_types = [C_TYPES[getattr(spec, "dtype", "float32")] for spec in compiled.outputs]
        self.baked = None if inputs is None else list(inputs)
        self.printed = outputs
        self.commands = commands
        self.profile = profile
        self.weights_file = getattr(compiled, "weights", None) is not None
        # The command line's file names, as the usage message shows them.
        self.files = [f"IN{i}" for i in range(len(self.in_sizes)) if self.baked is None]
        self.files += [f"OUT{i}" for i in range(len(self.out_sizes)) if outputs is None]
        if self.baked is not None and [a.size for a in self.baked] != self.in_sizes:
            raise NncgError(f"{self.name} takes inputs of {self.in_sizes} floats, got {[a.size for a in self.baked]}")

    # --- top of the file

    def title(self) -> str:
        how_in = "reads its inputs from files" if self.baked is None else "has its inputs compiled in"
        how_often = "as commands on stdin say" if self.commands else "once"
        how_out = "writes its outputs to files" if self.printed is None else "prints its outputs as hex words"
        return f"/* Test program by nncg.c_harness: {how_in}, calls {self.name} {how_often}, {how_out}. */"

    def includes(self) -> list[str]:
        lines = ["#define _POSIX_C_SOURCE 199309L"] if self.commands else []  # clock_gettime
        if self.files or self.commands or self.weights_file:
            lines.append("#include <stdio.h>")
        if self.weights_file:
            lines.append("#include <stdlib.h>")
        lines.append("#include <string.h>")
        if self.commands:
            lines += ["#include <time.h>", *PROFILE_CLOCK_DEFAULT]  # the `run` timer's clock too
        if self.printed is not None:
            lines += ["#include <stdint.h>", f'#include "{self.printed.include}"']
        return lines

    def declarations(self) -> list[str]:
        if self.baked is None:
            sized = zip(self.in_types, self.in_sizes)
            lines = [f"static {t} nncg_in{i}[{max(n, 1)}];" for i, (t, n) in enumerate(sized)]
        else:
            lines = [f"static const {t} nncg_in{i}[{max(a.size, 1)}] = {{\n{_c_values(a, t)}\n}};"
                     for i, (t, a) in enumerate(zip(self.in_types, self.baked))]  # fmt: skip
        lines += [
            f"static {t} nncg_out{i}[{max(n, 1)}];" for i, (t, n) in enumerate(zip(self.out_types, self.out_sizes))
        ]
        if self.weights_file:
            lines.append("static const void *nncg_weights;")
        if self.profile:
            lines += [
                f"extern const int {self.name}_profile_count;",
                f"extern const char *const {self.name}_profile_layers[];",
                f"extern double {self.name}_profile_seconds[];",
            ]
        return lines

    def helpers(self) -> list[str]:
        pieces = [WEIGHTS_LOADER.format(name=self.name, macro=self.name.upper())] if self.weights_file else []
        if self.files:
            pieces.append(SWAP_IF_BIG_ENDIAN)
        if self.baked is None and self.in_sizes:
            pieces.append(READ_VALUES)
        if self.printed is None and self.out_sizes:
            pieces.append(WRITE_VALUES)
        if self.printed is not None:
            pieces.append(PRINT_HEX.format(put=self.printed.put))
            pieces += [PRINT_WORDS[t] for t in C_TYPES.values() if t in self.out_types]
        return pieces

    # --- main

    def main(self) -> list[str]:
        signature = "int main(int argc, char *argv[])" if self.files else "int main(void)"
        body = ["char line[64];"] if self.commands else []
        body += self.check_arguments()
        body += ["nncg_weights = nncg_load_weights();"] if self.weights_file else []
        body += self.read_inputs()
        body += [f"memset(nncg_out{i}, 0xff, sizeof nncg_out{i});" for i in range(len(self.out_sizes))]
        body += self.command_loop() if self.commands else [self.call(), *self.deliver_outputs(), *self.after()]
        return [signature, "{", *_indented(body + ["return 0;"]), "}"]

    def check_arguments(self) -> list[str]:
        if not self.files:
            return []
        return [
            f"if (argc != {1 + len(self.files)}) {{",
            f'    fprintf(stderr, "usage: %s {" ".join(self.files)}\\n", argv[0]);',
            "    return 2;",
            "}",
        ]

    def read_inputs(self) -> list[str]:
        if self.baked is not None:
            return []
        return [
            f"if (!nncg_read(argv[{1 + i}], nncg_in{i}, sizeof nncg_in{i}[0], {n}UL)) return 1;"
            for i, n in enumerate(self.in_sizes)
        ]

    def deliver_outputs(self) -> list[str]:
        if self.printed is not None:
            return [
                f"nncg_print_{PRINTED[t]}(nncg_out{i}, {n}UL);"
                for i, (t, n) in enumerate(zip(self.out_types, self.out_sizes))
            ]
        first = 1 + len(self.files) - len(self.out_sizes)
        return [
            f"if (!nncg_write(argv[{first + i}], nncg_out{i}, sizeof nncg_out{i}[0], {n}UL)) return 1;"
            for i, n in enumerate(self.out_sizes)
        ]

    def after(self) -> list[str]:
        return list(self.printed.after) if self.printed is not None else []

    def call(self) -> str:
        args = [f"nncg_in{i}" for i in range(len(self.in_sizes))] + [f"nncg_out{i}" for i in range(len(self.out_sizes))]
        return f"{self.name}({', '.join(args + (['nncg_weights'] if self.weights_file else []))});"

    def command_loop(self) -> list[str]:
        run = [
            "struct timespec a, b;",
            "clock_gettime(NNCG_PROFILE_CLOCK, &a);",
            "for (i = 0; i < n; ++i) {",
            f"    {self.call()}",
            "}",
            "clock_gettime(NNCG_PROFILE_CLOCK, &b);",
            'printf("%.0f\\n", (b.tv_sec - a.tv_sec) * 1e9 + (b.tv_nsec - a.tv_nsec));',
        ]
        branches = [
            'if (sscanf(line, "run %ld", &n) == 1) {', *_indented(run),
            '} else if (strncmp(line, "profile", 7) == 0) {', *_indented(self.profile_report()),
            '} else if (strncmp(line, "outputs", 7) == 0) {', *_indented([*self.deliver_outputs(), 'printf("ok\\n");']),
            "} else {", "    break;", "}",
        ]  # fmt: skip
        loop = ["long n, i;", *branches, "fflush(stdout);"]
        return ["while (fgets(line, sizeof line, stdin) != NULL) {", *_indented(loop), "}"]

    def profile_report(self) -> list[str]:
        if not self.profile:
            return ['printf("none\\n");']
        name = self.name
        return [
            f"for (i = 0; i < {name}_profile_count; ++i) {{",
            f'    printf("%s %.9f\\n", {name}_profile_layers[i], {name}_profile_seconds[i]);',
            f"    {name}_profile_seconds[i] = 0;",
            "}",
            'printf("end\\n");',
        ]


def _indented(lines: list[str]) -> list[str]:
    return [INDENT + line for line in lines]


def _element_count(shape: Sequence[int]) -> int:
    return math.prod(int(d) for d in shape)


def _c_values(values: np.ndarray, c_type: str) -> str:
    """Constants of the input's C type, 8 a line: floats with 9 significant digits (which give back
    the same float32 exactly), integers as they are."""
    if c_type != "float":
        items = [str(int(v)) for v in np.asarray(values).ravel()]
    else:
        floats = np.asarray(values, dtype=np.float32).ravel()
        if not np.isfinite(floats).all():
            raise NncgError("compiled-in inputs must be finite")
        items = [f"{float(v):.8e}f" for v in floats]
    return ",\n".join(", ".join(items[i : i + 8]) for i in range(0, len(items), 8))


# Loads NAME.weights (a model compiled with weights in a file) at a NAME_WEIGHTS_ALIGN-byte aligned
# address (malloc's is not enough; C89 has no aligned_alloc, so it over-allocates and rounds up) and
# checks it with NAME_weights_ok.
WEIGHTS_LOADER = """\
static const void *nncg_load_weights(void)
{{
    FILE *f = fopen("{name}.weights", "rb");
    unsigned char *raw = (unsigned char *)malloc({macro}_WEIGHTS_BYTES + {macro}_WEIGHTS_ALIGN);
    unsigned char *data = raw == NULL ? NULL : raw + ({macro}_WEIGHTS_ALIGN - (size_t)raw % {macro}_WEIGHTS_ALIGN);
    if (f == NULL || data == NULL || fread(data, 1, {macro}_WEIGHTS_BYTES, f) != {macro}_WEIGHTS_BYTES) {{
        fprintf(stderr, "harness: cannot read {name}.weights\\n");
        exit(1);
    }}
    fclose(f);
    if (!{name}_weights_ok(data)) {{
        fprintf(stderr, "harness: {name}.weights is misaligned or fails its CRC-32 check\\n");
        exit(1);
    }}
    return data;
}}
"""

# The C type of an input or output array, by its dtype; the integer types come from the model's header.
C_TYPES = {"float32": "float", "int8": "nncg_int8", "uint8": "nncg_uint8", "int32": "nncg_int32"}

SWAP_IF_BIG_ENDIAN = """\
/* Converts between little-endian file data and native `size`-byte elements (a no-op on
   little-endian hosts). */
static void nncg_swap_if_big_endian(void *data, size_t size, unsigned long count)
{
    unsigned int one = 1;
    unsigned char *p = (unsigned char *)data;
    unsigned char t;
    unsigned long i;
    size_t j;
    if (*(unsigned char *)&one == 1) return;
    for (i = 0; i < count; ++i, p += size) {
        for (j = 0; j < size / 2; ++j) {
            t = p[j]; p[j] = p[size - 1 - j]; p[size - 1 - j] = t;
        }
    }
}
"""

READ_VALUES = """\
static int nncg_read(const char *path, void *data, size_t size, unsigned long count)
{
    FILE *f = fopen(path, "rb");
    int ok;
    if (f == NULL) {
        fprintf(stderr, "harness: cannot open %s\\n", path);
        return 0;
    }
    ok = fread(data, size, count, f) == count && fgetc(f) == EOF;
    fclose(f);
    if (!ok) fprintf(stderr, "harness: %s does not hold exactly %lu values\\n", path, count);
    nncg_swap_if_big_endian(data, size, count);
    return ok;
}
"""

# Swaps the outputs in place on a big-endian machine, so it swaps them back after writing.
WRITE_VALUES = """\
static int nncg_write(const char *path, void *data, size_t size, unsigned long count)
{
    FILE *f = fopen(path, "wb");
    int ok;
    if (f == NULL) {
        fprintf(stderr, "harness: cannot create %s\\n", path);
        return 0;
    }
    nncg_swap_if_big_endian(data, size, count);
    ok = fwrite(data, size, count, f) == count;
    nncg_swap_if_big_endian(data, size, count);
    ok = fclose(f) == 0 && ok;
    if (!ok) fprintf(stderr, "harness: cannot write %s\\n", path);
    return ok;
}
"""

PRINT_HEX = """\
static void nncg_print_hex(uint32_t value)
{{
    static const char digits[] = "0123456789abcdef";
    char line[10];
    int i;
    for (i = 0; i < 8; ++i) line[i] = digits[(value >> (28 - 4 * i)) & 0xf];
    line[8] = '\\n';
    line[9] = 0;
    {put}(line);
}}
"""

# The print function of each output C type (its name's suffix, then its definition); an integer
# prints as its int32 two's complement.
PRINTED = {"float": "floats", "nncg_int8": "int8s", "nncg_uint8": "uint8s", "nncg_int32": "int32s"}
PRINT_INTEGERS = """\
static void nncg_print_{suffix}(const {c_type} *data, unsigned long count)
{{
    unsigned long i;
    for (i = 0; i < count; ++i) nncg_print_hex((uint32_t)(nncg_int32)data[i]);
}}
"""
PRINT_WORDS = {
    "float": """\
static void nncg_print_floats(const float *data, unsigned long count)
{
    unsigned long i;
    uint32_t bits;
    for (i = 0; i < count; ++i) {
        memcpy(&bits, &data[i], sizeof bits);
        nncg_print_hex(bits);
    }
}
""",
    **{t: PRINT_INTEGERS.format(suffix=PRINTED[t], c_type=t) for t in ("nncg_int8", "nncg_uint8", "nncg_int32")},
}

"""The timing harness: the generated C built at -O3 into a program that Python drives over stdin, so
its batches can be interleaved with onnxruntime's. Also the object's section sizes (flash and RAM)."""

from __future__ import annotations

import re
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import NncgError
from ..verify import weights_loader

# Commands on stdin, one per line: "run N" times N calls and answers the nanoseconds; "profile"
# answers the seconds accumulated per layer (profile builds); "outputs" writes the outputs; "quit".
HARNESS = r"""#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "{name}.h"
{profile_decls}
{buffers}

static void read_floats(const char *path, float *data, size_t count)
{{
    FILE *f = fopen(path, "rb");
    if (f == NULL || fread(data, sizeof(float), count, f) != count) {{
        fprintf(stderr, "bench: cannot read %lu floats from %s\n", (unsigned long)count, path);
        exit(1);
    }}
    fclose(f);
}}

static void write_floats(const char *path, const float *data, size_t count)
{{
    FILE *f = fopen(path, "wb");
    if (f == NULL || fwrite(data, sizeof(float), count, f) != count) {{
        fprintf(stderr, "bench: cannot write %s\n", path);
        exit(1);
    }}
    fclose(f);
}}

int main(int argc, char **argv)
{{
    char line[64];
    if (argc != {argc}) {{
        fprintf(stderr, "bench: expected {argc_minus_one} file names\n");
        return 2;
    }}
{read_inputs}
    while (fgets(line, sizeof line, stdin) != NULL) {{
        long n, i;
        if (sscanf(line, "run %ld", &n) == 1) {{
            struct timespec a, b;
            clock_gettime(CLOCK_MONOTONIC, &a);
            for (i = 0; i < n; ++i) {{
                {call}
            }}
            clock_gettime(CLOCK_MONOTONIC, &b);
            printf("%.0f\n", (b.tv_sec - a.tv_sec) * 1e9 + (b.tv_nsec - a.tv_nsec));
        }} else if (strncmp(line, "profile", 7) == 0) {{
{print_profile}
        }} else if (strncmp(line, "outputs", 7) == 0) {{
{write_outputs}
            printf("ok\n");
        }} else {{
            break;
        }}
        fflush(stdout);
    }}
    return 0;
}}
"""


@dataclass(frozen=True)
class ObjectSizes:
    """Bytes per section of the compiled model: text and rodata go to flash, data and bss to RAM."""

    text: int
    rodata: int
    data: int
    bss: int


def harness_source(compiled, profile: bool) -> str:
    params = [*compiled.inputs, *compiled.outputs]
    name = compiled.name
    buffers = "\n".join(f"static float {p.c_name}[{int(np.prod(p.shape))}];" for p in params)
    n_in = len(compiled.inputs)
    read_inputs = "\n".join(
        f"    read_floats(argv[{i + 1}], {p.c_name}, sizeof {p.c_name} / sizeof(float));"
        for i, p in enumerate(compiled.inputs)
    )
    write_outputs = "\n".join(
        f"            write_floats(argv[{n_in + i + 1}], {p.c_name}, sizeof {p.c_name} / sizeof(float));"
        for i, p in enumerate(compiled.outputs)
    )
    profile_decls, print_profile = "", '            printf("none\\n");'
    if profile:
        profile_decls = (
            f"extern const int {name}_profile_count;\n"
            f"extern const char *const {name}_profile_layers[];\n"
            f"extern double {name}_profile_seconds[];"
        )
        print_profile = (
            f"            for (i = 0; i < {name}_profile_count; ++i) {{\n"
            f'                printf("%s %.9f\\n", {name}_profile_layers[i], {name}_profile_seconds[i]);\n'
            f"                {name}_profile_seconds[i] = 0;\n"
            "            }\n"
            '            printf("end\\n");'
        )
    loader, weights_arg = weights_loader(compiled)
    if loader:
        buffers += "\nstatic const void *nncg_weights;\n" + loader
        read_inputs = "    nncg_weights = nncg_load_weights();\n" + read_inputs
    return HARNESS.format(
        name=name,
        profile_decls=profile_decls,
        buffers=buffers,
        argc=len(params) + 1,
        argc_minus_one=len(params),
        read_inputs=read_inputs,
        call=f"{name}({', '.join([*(p.c_name for p in params), *weights_arg])});",
        print_profile=print_profile,
        write_outputs=write_outputs,
    )


class CompiledHarness:
    """The built harness for one compiled model, running as a child process."""

    def __init__(
        self,
        compiled,
        workdir: Path,
        cc: str,
        inputs: list[np.ndarray],
        profile: bool = False,
        runner: tuple[str, ...] = (),
    ):
        """`runner` prefixes the harness's command line (an emulator such as qemu-aarch64, or a
        script that runs it on a board), for a harness built with a cross compiler."""
        self.compiled = compiled
        self.workdir = workdir
        compiled.write(workdir)
        (workdir / "bench_main.c").write_text(harness_source(compiled, profile))
        flags = ["-O3", *compiled.cflags]
        start = time.perf_counter()
        _run([cc, *flags, "-c", f"{compiled.name}.c", "-o", f"{compiled.name}.o"], workdir)
        self.compile_seconds = time.perf_counter() - start
        _run([cc, "-O2", "-c", "bench_main.c", "-o", "bench_main.o"], workdir)
        _run([cc, "bench_main.o", f"{compiled.name}.o", "-o", "bench", "-lm"], workdir)
        self.sizes = object_sizes(workdir / f"{compiled.name}.o")
        in_files = [f"in{i}.bin" for i in range(len(inputs))]
        for path, array in zip(in_files, inputs):
            np.ascontiguousarray(array, dtype="<f4").tofile(workdir / path)
        self.out_files = [f"out{i}.bin" for i in range(len(compiled.outputs))]
        try:
            self.process = subprocess.Popen(
                [*runner, "./bench", *in_files, *self.out_files],
                cwd=workdir,
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
            )
        except OSError as exc:
            raise NncgError(f"cannot start the benchmark harness with '{' '.join(runner)}': {exc}") from None

    def run(self, calls: int) -> float:
        """Seconds for `calls` back-to-back inferences."""
        return float(self._ask(f"run {calls}")) * 1e-9

    def layer_seconds(self) -> list[tuple[str, float]]:
        """Seconds per layer accumulated since the last call (profile builds only)."""
        self._send("profile")
        rows = []
        while (line := self._line()) != "end":
            layer, seconds = line.split()
            rows.append((layer, float(seconds)))
        return rows

    def outputs(self) -> list[np.ndarray]:
        self._ask("outputs")
        return [
            np.fromfile(self.workdir / path, dtype="<f4").reshape(p.shape)
            for path, p in zip(self.out_files, self.compiled.outputs)
        ]

    def close(self) -> None:
        if self.process.poll() is None:
            self.process.stdin.write("quit\n")
            self.process.stdin.close()
            self.process.wait(timeout=30)

    def _send(self, command: str) -> None:
        self.process.stdin.write(command + "\n")
        self.process.stdin.flush()

    def _line(self) -> str:
        line = self.process.stdout.readline()
        if not line:
            raise NncgError(f"the benchmark harness of {self.compiled.name} stopped (exit {self.process.poll()})")
        return line.strip()

    def _ask(self, command: str) -> str:
        self._send(command)
        return self._line()


def object_sizes(path: Path) -> ObjectSizes:
    """Section sizes from binutils' `size -A`; .text.* and .rodata.* sections count with their kind."""
    listing = _run(["size", "-A", str(path)], path.parent)
    totals = {"text": 0, "rodata": 0, "data": 0, "bss": 0}
    for line in listing.splitlines():
        match = re.match(r"\.(text|rodata|data|bss)(\.\S*)?\s+(\d+)", line)
        if match:
            totals[match.group(1)] += int(match.group(3))
    return ObjectSizes(**totals)


def _run(command: list[str], cwd: Path) -> str:
    try:
        result = subprocess.run(command, cwd=cwd, capture_output=True, text=True)
    except FileNotFoundError:
        raise NncgError(f"'{command[0]}' is not installed; the benchmark needs it") from None
    if result.returncode != 0:
        raise NncgError(f"{' '.join(command)} failed:\n{result.stderr[-3000:]}")
    return result.stdout

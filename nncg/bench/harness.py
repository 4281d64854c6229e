"""The timing harness: the generated C built at -O3 into a program that Python drives over stdin, so
its batches can be interleaved with onnxruntime's. Also the object's section sizes (flash and RAM)."""

from __future__ import annotations

import re
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..backends.c_file import PROFILE_CPU_TIME_FLAG
from ..c_harness import harness_source
from ..errors import NncgError
from ..host_cpu import check_host_runs
from ..safe_text import shown
from ..tools import run_tool
from ..verify import write_input


@dataclass(frozen=True)
class ObjectSizes:
    """Bytes per section of the compiled model: text and rodata go to flash, data and bss to RAM."""

    text: int
    rodata: int
    data: int
    bss: int


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
        cpu_time: bool = False,
    ):
        """`runner` prefixes the harness's command line (an emulator such as qemu-aarch64, or a
        script that runs it on a board), for a harness built with a cross compiler. `cpu_time`: `run`
        and the profile timers read the thread's CPU time instead of the wall clock (on a shared core
        it leaves out the time other processes run; each timer read is then a system call)."""
        if not runner:
            check_host_runs(compiled.target)
        self.compiled = compiled
        self.workdir = workdir
        compiled.write(workdir)
        # Commands on stdin, one per line: "run N", "profile", "outputs", "quit" (see c_harness).
        (workdir / "bench_main.c").write_text(harness_source(compiled, commands=True, profile=profile))
        clock = [PROFILE_CPU_TIME_FLAG] if cpu_time else []
        flags = ["-O3", *compiled.cflags, *clock]
        start = time.perf_counter()
        model_c = f"{compiled.name}.c"
        run_tool([cc, *flags, "-c", model_c, "-o", f"{compiled.name}.o"], f"compiling {model_c}", cwd=workdir)
        self.compile_seconds = time.perf_counter() - start
        run_tool([cc, "-O2", *clock, "-c", "bench_main.c", "-o", "bench_main.o"], "compiling bench_main.c", cwd=workdir)
        link = [cc, "bench_main.o", f"{compiled.name}.o", "-o", "bench", "-lm"]
        run_tool(link, "linking the benchmark harness", cwd=workdir)
        self.sizes = object_sizes(workdir / f"{compiled.name}.o")
        in_files = [f"in{i}.bin" for i in range(len(inputs))]
        for path, spec, array in zip(in_files, compiled.inputs, inputs):
            write_input(workdir / path, spec, array)
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
            np.fromfile(self.workdir / path, dtype=np.dtype(p.dtype).newbyteorder("<")).reshape(p.shape)
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
            try:
                code = self.process.wait(timeout=10)  # its output closed: it is ending, so reap it for the status
            except subprocess.TimeoutExpired:
                code = None
            how = "" if code is None else f" (signal {-code})" if code < 0 else f" (exit status {code})"
            raise NncgError(f"the benchmark harness of {shown(self.compiled.name)} stopped{how}")
        return line.strip()

    def _ask(self, command: str) -> str:
        self._send(command)
        return self._line()


def object_sizes(path: Path) -> ObjectSizes:
    """Section sizes from binutils' `size -A`; .text.* and .rodata.* sections count with their kind."""
    listing = run_tool(["size", "-A", path], "reading section sizes", cwd=path.parent).stdout
    totals = {"text": 0, "rodata": 0, "data": 0, "bss": 0}
    for line in listing.splitlines():
        match = re.match(r"\.(text|rodata|data|bss)(\.\S*)?\s+(\d+)", line)
        if match:
            totals[match.group(1)] += int(match.group(3))
    return ObjectSizes(**totals)

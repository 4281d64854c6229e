"""Building the generated C for other machines and running it there (tests/test_cross_targets.py,
scripts/cross_matrix.py).

Linux targets reuse nncg.verify's harness with a cross compiler and a qemu-user prefix. The
Cortex-M4 is bare metal: the inputs are compiled into the program, which runs in qemu-system-arm
and prints its outputs through semihosting (start-up code and linker script in tests/cortex_m4/).
"""

from __future__ import annotations

import functools
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnx

import nncg
from nncg.c_harness import PrintedOutputs, harness_source
from nncg.compiler import CompiledModel
from nncg.quant_steps import Comparison, compare_steps
from nncg.tools import run_tool
from nncg.verify import VerificationError, VerifyReport, compare, random_inputs, reference_outputs, verify

ROOT = Path(__file__).resolve().parent.parent
CORTEX_M4_DIR = Path(__file__).resolve().parent / "cortex_m4"
PAPER_NETWORKS = {n: ROOT / "examples" / f"{n}.onnx" for n in ("ball", "pedestrian", "robot")}
MLPERF_TINY = {
    n: ROOT / "benchmarks" / "models" / f"{n}.onnx" for n in ("resnet8", "dscnn", "mobilenet_v1_025", "autoencoder")
}
MODELS = {**PAPER_NETWORKS, **MLPERF_TINY}
OPT = "-O2"
TOLERANCE = 1e-4  # as tests/helpers.py: max abs error relative to the output's largest magnitude
SEED = 0
TOOL_TIMEOUT_S = 600
QEMU_TIMEOUT_S = 300


@dataclass(frozen=True)
class Toolchain:
    """How one target builds and runs the generated C: the NNCG target, compiler, flags and emulator."""

    name: str
    target: str
    cc: str
    flags: tuple[str, ...] = ()
    emulator: tuple[str, ...] = ()  # prefix that runs the program; empty: the host runs it
    native_if_possible: bool = False  # i686: an x86-64 kernel with 32-bit support runs it itself


def _linux(
    name: str, cc: str, emulator: str | tuple[str, ...], target: str = "ansi-c", flags: tuple[str, ...] = ()
) -> Toolchain:
    # Static: qemu-user then needs no target libraries (no -L sysroot).
    prefix = (emulator,) if isinstance(emulator, str) else emulator
    return Toolchain(name, target, cc, ("-static", *flags), prefix, native_if_possible=emulator == "qemu-i386")


ARMHF_NEON_FLAGS = ("-mfpu=neon-vfpv4", "-mfloat-abi=hard")  # the neon target on ARMv7 with VFPv4 (FMA)

TOOLCHAINS = {
    t.name: t
    for t in (
        _linux("i686-ansi-c", "i686-linux-gnu-gcc", "qemu-i386"),
        # The paper's Nao robot: a 32-bit Atom (Bonnell) with SSSE3.
        _linux("i686-ssse3", "i686-linux-gnu-gcc", "qemu-i386", "ssse3", ("-march=bonnell", "-mssse3")),
        _linux("armhf", "arm-linux-gnueabihf-gcc", "qemu-arm"),
        _linux("aarch64", "aarch64-linux-gnu-gcc", "qemu-aarch64"),
        # NEON: baseline on aarch64; ARMv7 needs it switched on, with VFPv4 for fused multiply-adds,
        # or plain NEON (VFPv3), where the generated file falls back to vmlaq_f32.
        _linux("armhf-neon", "arm-linux-gnueabihf-gcc", "qemu-arm", "neon", ARMHF_NEON_FLAGS),
        _linux("armhf-neon-vfpv3", "arm-linux-gnueabihf-gcc", "qemu-arm", "neon", ("-mfpu=neon", "-mfloat-abi=hard")),
        # plain neon on a CPU without the dot-product extension; neon-dotprod on qemu's CPU with every extension
        _linux("aarch64-neon", "aarch64-linux-gnu-gcc", ("qemu-aarch64", "-cpu", "cortex-a53"), "neon"),
        _linux("aarch64-neon-dotprod", "aarch64-linux-gnu-gcc", ("qemu-aarch64", "-cpu", "max"), "neon-dotprod"),
        _linux("riscv64", "riscv64-linux-gnu-gcc", "qemu-riscv64"),
        Toolchain("clang", "ansi-c", "clang"),
        Toolchain("tcc", "ansi-c", "tcc"),
    )
}
# Every model on every toolchain; the MLPerf-Tiny-shaped models (the slowest to build and run) first,
# so that they do not finish last on one xdist worker.
CASES = [(tc, model) for model in (*MLPERF_TINY, *PAPER_NETWORKS) for tc in TOOLCHAINS]
NEON_TOOLCHAINS = tuple(name for name, tc in TOOLCHAINS.items() if tc.target == "neon")
# clang cross-compiles the neon file (-c: no target libraries needed) with its own arm_neon.h and
# the cross sysroot's headers that the gcc cross toolchains install.
CLANG_NEON_FLAGS = {
    "aarch64": ("--target=aarch64-linux-gnu",),
    "armhf": ("--target=arm-linux-gnueabihf", *ARMHF_NEON_FLAGS),
    "armhf-vfpv3": ("--target=arm-linux-gnueabihf", "-mfpu=neon", "-mfloat-abi=hard"),
}
CORTEX_M4_MODELS = ("ball", "pedestrian", "robot")
# issue 18's models at --memory min, float: the two MLPerf-Tiny-shaped ones with its arena targets too
CORTEX_M4_MIN_MODELS = (*CORTEX_M4_MODELS, "resnet8", "mobilenet_v1_025")
CORTEX_M4_INT8_MODELS = tuple(MLPERF_TINY)  # quantised as tests/test_int8.py quantises the repository's models
CORTEX_M4_MIN_INT8_MODELS = ("ball", "pedestrian", "robot", "resnet8", "mobilenet_v1_025", "dscnn")


@functools.cache
def runs_natively(cc: str) -> bool:
    """Whether this machine runs a static program built by `cc` itself (a 32-bit x86 program on an
    x86-64 kernel built with IA-32 emulation)."""
    with tempfile.TemporaryDirectory(prefix="nncg-probe-") as tmp:
        source, program = Path(tmp) / "probe.c", Path(tmp) / "probe"
        source.write_text("int main(void) { return 0; }\n")
        try:
            run_tool([cc, "-static", source, "-o", program], "building a probe", error=VerificationError)
            run_tool([program], "running the probe", timeout=60, error=VerificationError)
        except VerificationError:  # no static libc for it, or an exec format error: the kernel cannot run it
            return False
        return True


def runner(toolchain: Toolchain) -> tuple[str, ...]:
    """The command prefix that runs the toolchain's programs on this machine."""
    if toolchain.native_if_possible and runs_natively(toolchain.cc):
        return ()
    return toolchain.emulator


def missing_tools(toolchain: Toolchain) -> list[str]:
    """The compiler or emulator this toolchain needs that is not on PATH."""
    if shutil.which(toolchain.cc) is None:
        return [toolchain.cc]
    return [tool for tool in runner(toolchain)[:1] if shutil.which(tool) is None]


def verify_on(toolchain: Toolchain, model: str | onnx.ModelProto, compiled: CompiledModel) -> VerifyReport:
    """Builds `compiled` (the C of MODELS[model], or of the model given) with the toolchain, runs it,
    compares with onnxruntime."""
    return verify(
        nncg.load_model(MODELS[model]) if isinstance(model, str) else model,
        compiled,
        seed=SEED,
        tolerance=TOLERANCE,
        cc=toolchain.cc,
        opt=OPT,
        extra_cflags=toolchain.flags,
        runner=runner(toolchain),
    )


def clang_cross_problem(flags: Sequence[str]) -> str | None:
    """Why clang cannot compile NEON code with these flags here (no clang, no sysroot headers), or None."""
    if shutil.which("clang") is None:
        return "clang not installed (scripts/install-test-deps.sh installs it)"
    with tempfile.TemporaryDirectory(prefix="nncg-probe-") as tmp:
        source = Path(tmp) / "probe.c"
        source.write_text("#include <math.h>\n#include <arm_neon.h>\nint probe(void) { return 0; }\n")
        try:
            probe = ["clang", *flags, "-c", source, "-o", source.with_suffix(".o")]
            run_tool(probe, "compiling a NEON probe", error=VerificationError)
            return None
        except VerificationError as exc:
            lines = str(exc).splitlines()
    first = next((line for line in lines[1:] if "error" in line), lines[-1])
    return f"clang {' '.join(flags)} cannot build NEON code here (cross sysroot headers missing?): {first}"


def compile_with_clang(flags: Sequence[str], compiled: CompiledModel, workdir: Path) -> None:
    """Compiles the model's C file with clang and the target's strict flags (-c); raises on an error or warning."""
    compiled.write(workdir)
    _run(["clang", *flags, OPT, *compiled.strict_cflags, "-c", f"{compiled.name}.c", "-o", "model.o"], workdir)


# --- Cortex-M4, bare metal ---

CORTEX_M4_CC = "arm-none-eabi-gcc"
CORTEX_M4_TOOLS = (CORTEX_M4_CC, "arm-none-eabi-size", "qemu-system-arm")
CORTEX_M4_FLAGS = (
    "-mcpu=cortex-m4", "-mthumb", "-mfpu=fpv4-sp-d16", "-mfloat-abi=hard", "-Os",
    "-ffunction-sections", "-fdata-sections",
)  # fmt: skip
# newlib (nano) only for libm's exp (and memset); nosys.specs stubs the system calls nothing here makes.
CORTEX_M4_SCRIPT = CORTEX_M4_DIR / "mps2_an386.ld"
CORTEX_M4_LINK = ("-nostartfiles", "--specs=nano.specs", "--specs=nosys.specs", "-Wl,--gc-sections")
# Semihosting output goes to a file: QEMU would otherwise mix it into its own messages on stderr.
QEMU_MPS2_AN386 = (
    "qemu-system-arm", "-M", "mps2-an386", "-display", "none", "-monitor", "none", "-serial", "null",
    "-chardev", "file,id=semihosting,path=semihosting.txt",
    "-semihosting-config", "enable=on,target=native,chardev=semihosting", "-kernel",
)  # fmt: skip
PROGRAM_FLAGS = ("-std=c11", "-Wall", "-Wextra", "-Werror")


@dataclass(frozen=True)
class CortexM4Result:
    """One run on the emulated Cortex-M4: the outputs, the stack's deepest use, and section sizes
    (text, rodata, data, bss, stack reserved) in bytes of the model's object file and of the image."""

    outputs: list[np.ndarray]
    stack_bytes: int
    model_sizes: dict[str, int]
    image_sizes: dict[str, int]


# The program prints each output float's bits in hex through semihosting, then the stack's
# high-water mark (startup.h gives both).
CORTEX_M4_OUTPUTS = PrintedOutputs(
    "semihost_write0", "startup.h", ('semihost_write0("stack\\n");', "nncg_print_hex(stack_bytes_used());")
)


def cortex_m4_program(compiled: CompiledModel, inputs: Sequence[np.ndarray]) -> str:
    """C test program: the host's inputs compiled in, one call of the model, the outputs and the
    stack's high-water mark printed."""
    return harness_source(compiled, inputs=inputs, outputs=CORTEX_M4_OUTPUTS)


def _run(cmd: Sequence[str | Path], cwd: Path, timeout: float = TOOL_TIMEOUT_S) -> str:
    """Runs a tool; a nonzero status, a warning or the timeout raises VerificationError with its
    output. Returns stdout."""
    what = Path(str(cmd[0])).name
    return run_tool(cmd, what, cwd=cwd, timeout=timeout, reject_warnings=True, error=VerificationError).stdout


def section_sizes(path: Path) -> dict[str, int]:
    """Bytes of text, rodata, data, bss and stack sections of an object or image (`arm-none-eabi-size -A`)."""
    kinds = {".text": "text", ".rodata": "rodata", ".ARM.exidx": "rodata", ".data": "data", ".bss": "bss"}
    kinds |= {".stack": "stack"}  # only in the image: the linker script's reservation
    sizes = dict.fromkeys(kinds.values(), 0)
    for line in _run(["arm-none-eabi-size", "-A", str(path)], path.parent).splitlines():
        fields = line.split()
        if len(fields) == 3 and fields[1].isdigit():
            kind = next((k for prefix, k in kinds.items() if fields[0].startswith(prefix)), None)
            if kind:
                sizes[kind] += int(fields[1])
    return sizes


def linker_script(ram: int | None, stack: int | None) -> str:
    """The board's linker script, with only `ram` bytes of RAM and a stack of `stack` bytes (None:
    the board's 4 MB and 16 KB)."""
    script = CORTEX_M4_SCRIPT.read_text()
    if ram is not None:
        script = script.replace("ORIGIN = 0x20000000, LENGTH = 4M", f"ORIGIN = 0x20000000, LENGTH = {ram}")
    if stack is not None:
        script = script.replace("STACK_SIZE = 16K;", f"STACK_SIZE = {stack};")
    return script


def build_cortex_m4(
    compiled: CompiledModel,
    inputs: Sequence[np.ndarray],
    workdir: Path,
    ram: int | None = None,
    stack: int | None = None,
) -> tuple[Path, Path]:
    """Compiles the model (with its strict flags), the test program and the start-up code for the
    Cortex-M4 and links them with `ram` bytes of RAM and a `stack`-byte stack (see linker_script);
    returns the model's object file and the image."""
    compiled.write(workdir)
    (workdir / "board.ld").write_text(linker_script(ram, stack))
    (workdir / "main.c").write_text(cortex_m4_program(compiled, inputs))
    cc, include = [CORTEX_M4_CC, *CORTEX_M4_FLAGS], f"-I{CORTEX_M4_DIR}"
    model_obj, image = workdir / f"{compiled.name}.o", workdir / f"{compiled.name}.elf"
    _run([*cc, *compiled.strict_cflags, "-c", f"{compiled.name}.c", "-o", model_obj.name], workdir)
    _run([*cc, *PROGRAM_FLAGS, include, "-I.", "-c", "main.c", "-o", "main.o"], workdir)
    _run([*cc, *PROGRAM_FLAGS, include, "-c", str(CORTEX_M4_DIR / "startup.c"), "-o", "startup.o"], workdir)
    link = [*cc, *CORTEX_M4_LINK, "-Tboard.ld", model_obj.name, "main.o", "startup.o", "-o", image.name, "-lm"]
    _run(link, workdir)
    return model_obj, image


def _parse_output(text: str, compiled: CompiledModel) -> tuple[list[np.ndarray], int]:
    """The outputs and the stack bytes from what the program printed."""
    words = text.split()
    if "stack" not in words:
        raise VerificationError(f"the Cortex-M4 program stopped early; it printed: {' '.join(words[-5:])}")
    marker = words.index("stack")
    bits = np.array([int(word, 16) for word in words[:marker]], dtype=np.uint32)
    sizes = [int(np.prod(spec.shape)) for spec in compiled.outputs]
    if bits.size != sum(sizes):
        raise VerificationError(f"the Cortex-M4 program printed {bits.size} floats, expected {sum(sizes)}")
    chunks = np.split(bits, np.cumsum(sizes)[:-1])  # each output's 32-bit words: float32, or integers as int32
    outputs = [
        (c.view(np.float32) if spec.dtype == "float32" else c.view(np.int32).astype(spec.dtype)).reshape(spec.shape)
        for c, spec in zip(chunks, compiled.outputs)
    ]
    return outputs, int(words[marker + 1], 16)


def run_cortex_m4(compiled: CompiledModel, inputs: Sequence[np.ndarray], workdir: Path, **memory) -> CortexM4Result:
    """Builds the model for the Cortex-M4 (`memory`: build_cortex_m4's ram and stack), runs it on
    QEMU's MPS2 AN386 and reads its outputs."""
    model_obj, image = build_cortex_m4(compiled, inputs, workdir, **memory)
    _run([*QEMU_MPS2_AN386, image.name], workdir, timeout=QEMU_TIMEOUT_S)
    outputs, stack_bytes = _parse_output((workdir / "semihosting.txt").read_text(), compiled)
    return CortexM4Result(outputs, stack_bytes, section_sizes(model_obj), section_sizes(image))


def verify_on_cortex_m4(
    model: str, compiled: CompiledModel, workdir: Path, **memory
) -> tuple[VerifyReport, CortexM4Result]:
    """Runs `compiled` (the C of MODELS[model]) on the Cortex-M4 (`memory`: build_cortex_m4's ram
    and stack) and compares with onnxruntime."""
    inputs = random_inputs(compiled.inputs, SEED)
    result = run_cortex_m4(compiled, inputs, workdir, **memory)
    references = reference_outputs(nncg.load_model(MODELS[model]), compiled.inputs, inputs)
    stats = compare(result.outputs, references, [spec.name for spec in compiled.outputs])
    return VerifyReport(compiled.name, "cortex-m4", tuple(stats), TOLERANCE, SEED), result


def quantized_model(model: str) -> onnx.ModelProto:
    """MODELS[model] quantised as tests/test_int8.py quantises the repository's models (tests/int8_models.py)."""
    from int8_models import quantized, repository_model

    return quantized(repository_model(MODELS[model].relative_to(ROOT)))


def verify_int8_on_cortex_m4(
    qdq: onnx.ModelProto, compiled: CompiledModel, workdir: Path, **memory
) -> tuple[Comparison, CortexM4Result]:
    """`compiled` (the ansi-c int8 C of the QDQ model `qdq`) run on the Cortex-M4 (`memory`:
    build_cortex_m4's ram and stack), the outputs against onnxruntime on `qdq` in quantisation steps."""
    from int8_models import onnxruntime_outputs

    inputs = random_inputs(compiled.inputs, SEED)
    result = run_cortex_m4(compiled, inputs, workdir, **memory)
    reference = onnxruntime_outputs(qdq, {spec.name: x for spec, x in zip(compiled.inputs, inputs)})
    return compare_steps(qdq, [(result.outputs, reference)]), result


def size_row(result: CortexM4Result, arena_bytes: int) -> dict[str, int]:
    """Flash (text + rodata + data's initial values) and RAM (data + bss, the arena being part of
    bss, + the stack's deepest use) of the model's object file and of the whole linked image."""
    m, image = result.model_sizes, result.image_sizes
    return {
        "flash": m["text"] + m["rodata"] + m["data"],
        "text": m["text"],
        "rodata": m["rodata"],
        "RAM": m["data"] + m["bss"] + result.stack_bytes,
        "data": m["data"],
        "bss": m["bss"],
        "arena": arena_bytes,
        "stack": result.stack_bytes,
        "image flash": image["text"] + image["rodata"] + image["data"],
        "image RAM": image["data"] + image["bss"] + result.stack_bytes,
    }


def format_table(rows: dict[str, dict[str, object]], corner: str = "model") -> str:
    """A right-aligned text table: one row per key, the columns of the first row."""
    columns = list(next(iter(rows.values())))
    cells = [[corner, *columns]] + [[name, *(str(row.get(c, "-")) for c in columns)] for name, row in rows.items()]
    widths = [max(len(line[i]) for line in cells) for i in range(len(cells[0]))]
    return "\n".join("  ".join(c.rjust(w) for c, w in zip(line, widths)).rstrip() for line in cells)


def check_on_neon(toolchain: str, model: onnx.ModelProto) -> None:
    """Compile `model` for neon and compare it with onnxruntime under `toolchain`'s emulator (skipped
    when the toolchain is missing)."""
    from test_cross_targets import require  # the skip rule of the cross tests

    tc = TOOLCHAINS[toolchain]
    require(missing_tools(tc))
    report = verify_on(tc, model, nncg.compile(model, target="neon", verify_ir=True))
    assert report.ok, report.format()

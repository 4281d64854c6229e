"""What the host CPU can run: its x86 flags, and which targets' generated code needs which."""

from __future__ import annotations

import platform
import re
from pathlib import Path

from .errors import NncgError

# The /proc/cpuinfo flags an x86 target's generated code needs to run (ansi-c needs none).
TARGET_CPU_FLAGS = {
    "ansi-c": (),
    "ssse3": ("sse2", "ssse3"),
    "avx2": ("avx2", "fma"),
    "avx512": ("avx512f",),
    "avx512vnni": ("avx512f", "avx512bw", "avx512vl", "avx512_vnni"),
}


def cpu_flags() -> frozenset[str]:
    """The host x86 CPU's /proc/cpuinfo flags; empty on other machines or where that cannot be read."""
    if platform.machine().lower() not in ("x86_64", "amd64", "i386", "i686"):
        return frozenset()
    try:
        cpuinfo = Path("/proc/cpuinfo").read_text()
    except OSError:
        return frozenset()  # not Linux: nothing we can determine without running code
    match = re.search(r"^flags\s*:(.*)$", cpuinfo, re.MULTILINE)
    return frozenset(match.group(1).split()) if match else frozenset()


def host_targets() -> list[str]:
    """The targets whose code runs on this CPU: ansi-c always, the x86 ones whose flags it has."""
    flags = cpu_flags()
    return [target for target, needs in TARGET_CPU_FLAGS.items() if flags.issuperset(needs)]


def check_host_runs(target: str) -> None:
    """Raises NncgError when this host's CPU is known to lack a flag `target`'s code needs: run here,
    that code would stop on an illegal instruction. Silent where the flags cannot be read."""
    flags = cpu_flags()
    missing = sorted(set(TARGET_CPU_FLAGS.get(target, ())) - flags)
    if flags and missing:
        runs = ", ".join(host_targets())
        raise NncgError(
            f"this CPU lacks {' and '.join(missing)}, which --target {target} code needs, so it cannot run"
            f" that code here (--verify, --benchmark, --profile and --tune run it); use a CPU that has them, or a"
            f" target this one runs: {runs}"
        )

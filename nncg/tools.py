"""Running external tools — C compilers, the programs they build, emulators — with a timeout, and
errors that name the step, the command and the head of the tool's output."""

from __future__ import annotations

import os
import subprocess
from collections.abc import Mapping, Sequence

from .errors import NncgError

TOOL_TIMEOUT_S = 600
OUTPUT_LINES = 40


def run_tool(
    command: Sequence[str | os.PathLike[str]],
    what: str,
    *,
    cwd: str | os.PathLike[str] | None = None,
    timeout: float = TOOL_TIMEOUT_S,
    env: Mapping[str, str] | None = None,
    stdin: bytes | None = None,
    text: bool = True,
    reject_warnings: bool = False,
    error: type[NncgError] = NncgError,
) -> subprocess.CompletedProcess:
    """Run `command` (`what` names the step in errors) and return it finished: stderr as text,
    stdout as text or, with `text=False`, as bytes (a program writing floats).

    Raises `error` when the tool cannot start, runs past `timeout` seconds, is killed by a signal,
    exits nonzero, or — with `reject_warnings`, for compilers — writes "warning:" to stderr.
    `stdin` is fed to the tool as bytes."""
    argv = [str(part) for part in command]
    shown = " ".join(argv)
    try:
        proc = subprocess.run(
            argv, cwd=cwd, env=None if env is None else dict(env), input=stdin, capture_output=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        raise error(f"{what} timed out after {timeout:g}s: {shown}") from None
    except OSError as exc:  # not found, not executable, or built for another machine
        raise error(f"{what}: cannot run {argv[0]!r} ({exc.strerror or exc}); is it installed?") from None
    stdout, stderr = _text(proc.stdout), _text(proc.stderr)
    status = _failure(proc.returncode, stderr, reject_warnings)
    if status is not None:
        output = output_head(stderr + stdout)
        raise error(f"{what} {status}: {shown}" + (f"\n{output}" if output else ""))
    return subprocess.CompletedProcess(argv, proc.returncode, stdout if text else proc.stdout, stderr)


def _text(data: bytes) -> str:
    return data.decode("utf-8", errors="replace")


def _failure(returncode: int, stderr: str, reject_warnings: bool) -> str | None:
    """How the tool failed, or None when it did not."""
    if returncode < 0:
        return f"crashed with signal {-returncode}"
    if returncode > 0:
        return f"exited with status {returncode}"
    if reject_warnings and "warning:" in stderr:
        return "warned"
    return None


def output_head(text: str, lines: int = OUTPUT_LINES) -> str:
    """The first `lines` lines of a tool's output, noting how many were cut."""
    all_lines = text.rstrip().splitlines()
    cut = len(all_lines) - lines
    return "\n".join(all_lines[:lines] + ([f"... ({cut} more lines)"] if cut > 0 else []))

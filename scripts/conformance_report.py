"""Runs onnx's backend node tests through NNCG and writes docs/conformance.md.

    python3 scripts/conformance_report.py [-j 2] [--failures] [--readme]

The cases, and the exclusions with their reasons, are those of tests/test_onnx_conformance.py
(nncg/conformance.py). Per operator: cases passed / failed / excluded, the exclusion reasons and the
failing cases with their first error line; then a total. `--readme` also rewrites the totals line
of README.md's Conformance section.
"""

from __future__ import annotations

import argparse
import multiprocessing
import re
import sys
import time
import unittest
import warnings
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import onnx  # noqa: E402

from nncg import conformance  # noqa: E402
from nncg.onnx_backend import NncgBackend  # noqa: E402

OUTPUT = ROOT / "docs" / "conformance.md"
README = ROOT / "README.md"
_TEST_CASES: dict = {}


def _summary(exc: BaseException) -> str:
    """One line for a failure: numpy's mismatch statistics, or the error's first line."""
    text = str(exc)
    if isinstance(exc, AssertionError):
        found = re.finditer(r"(Mismatched elements|Max absolute difference|Max relative difference)[^\n]*", text)
        stats = [m.group(0).strip() for m in found]
        shape = re.search(r"Output \d+ has incorrect shape.*?\n.*?\n\s*(.*\n\s*.*)", text)
        if stats:
            return "wrong values: " + "; ".join(stats)
        if shape:
            return "wrong shape: " + " ".join(shape.group(1).split())
        if "dtype" in text or "Items are not equal" in text:
            return "mismatch: " + " ".join(text.split())[:200]
    lines = [line.strip() for line in text.strip().splitlines() if line.strip()]
    first = lines[0] if lines else ""
    if first.startswith(("compiling ", "building ", "linking ")) and len(lines) > 1:
        first = first.split(":")[0] + ": " + next((line for line in lines[1:] if "error" in line), lines[1])
    return f"{type(exc).__name__}: {first}"[:300]


def _run(name: str) -> tuple[str, str, str]:
    """(name, status, detail): status passed / failed / excluded."""
    reason = conformance.exclusion_reason(name)
    if reason is not None:
        return name, "excluded", reason
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            conformance.run_node_case(_TEST_CASES, name)
    except unittest.SkipTest as exc:
        return name, "excluded", f"skipped by onnx: {exc}"
    except Exception as exc:  # any failure is reported, not raised
        return name, "failed", _summary(exc)
    return name, "passed", ""


def run_all(jobs: int) -> list[tuple[str, str, str, str]]:
    """(op, name, status, detail) for every selected node case, in name order."""
    cases = conformance.select_node_cases()
    ops = {case.name: case.op for case in cases}
    names = [case.name for case in cases]
    if jobs > 1:
        with multiprocessing.get_context("fork").Pool(jobs) as pool:
            results = pool.map(_run, names, chunksize=1)
    else:
        results = [_run(name) for name in names]
    return [(ops[name], name, status, detail) for name, status, detail in results]


def totals_line(results: list[tuple[str, str, str, str]]) -> str:
    count = defaultdict(int)
    for _, _, status, _ in results:
        count[status] += 1
    ops = len({op for op, *_ in results})
    return (
        f"{len(results)} cases of {ops} operators: {count['passed']} passed, "
        f"{count['failed']} failed, {count['excluded']} excluded"
    )


def float32_line(results: list[tuple[str, str, str, str]]) -> str:
    """The float32 share: of the cases computing on float32 data (conformance.is_float32_case), how
    many pass."""
    statuses = [status for _, name, status, _ in results if conformance.is_float32_case(name)]
    passed = statuses.count("passed")
    return (
        f"{passed} of {len(statuses)} float32 cases pass ({100 * passed / len(statuses):.1f} %); "
        f"{statuses.count('failed')} fail, {statuses.count('excluded')} are excluded"
    )


def markdown(results: list[tuple[str, str, str, str]]) -> str:
    by_op: dict[str, list[tuple[str, str, str]]] = defaultdict(list)
    for op, name, status, detail in results:
        by_op[op].append((name, status, detail))
    lines = [
        "# ONNX conformance",
        "",
        f"onnx {onnx.__version__}'s backend node tests (`onnx.backend.test`) run through `nncg.onnx_backend`",
        f"(target `{NncgBackend.default_target}`, unroll level {NncgBackend.default_unroll}, host C compiler at "
        f"`{NncgBackend.default_opt}`), compared with onnx's stored outputs at onnx's tolerances (rtol 1e-3,",
        "atol 1e-7). Operator parameters a case feeds as graph inputs (Reshape's shape, Slice's starts, ...)",
        "are bound as constants by the adapter at the first run and compiled in, and so are the weights of",
        "QLinearConv, QLinearMatMul, ConvInteger and MatMulInteger (NNCG's integer kernels take constant",
        "weights); int8 and uint8 data inputs and outputs are the C function's own. A case is counted for the",
        "operator its graph computes (nodes that fold to constants aside; `_expanded` cases for the operator",
        "they expand);",
        "every case of an operator in `nncg.frontend.ops.SUPPORTED_OPS` runs unless `EXCLUDED` in",
        "`nncg/conformance.py` names it with a reason. Written by `scripts/conformance_report.py`;",
        "`python3 -m pytest tests/test_onnx_conformance.py` runs the same cases.",
        "",
        f"**Total (node tests): {totals_line(results)}.**",
        "",
        f"**Float32 share: {float32_line(results)}.** A case is a float32 case when every graph output and",
        "every graph input a node reads as data (not in an operator-parameter slot such as Reshape's shape or",
        "ReduceSum's axes) is float32, ArgMax/ArgMin's int64 indices aside (`is_float32_case` in",
        "`nncg/conformance.py`); the other cases (integer, float64, float16, bool data) are excluded for their",
        "types, but the int8/uint8 cases of the quantisation operators, which run. Excluded float32 cases",
        "count as not passing.",
        "",
        "| operator | cases | passed | failed | excluded |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for op in sorted(by_op):
        rows = by_op[op]
        n = {s: sum(1 for _, status, _ in rows if status == s) for s in ("passed", "failed", "excluded")}
        lines.append(f"| {op} | {len(rows)} | {n['passed']} | {n['failed']} | {n['excluded']} |")
    lines += ["", "## Exclusions and failures by operator", ""]
    for op in sorted(by_op):
        rows = by_op[op]
        reasons: dict[str, list[str]] = defaultdict(list)
        for name, status, detail in rows:
            if status == "excluded":
                reasons[detail].append(name)
        failed = [(name, detail) for name, status, detail in rows if status == "failed"]
        if not reasons and not failed:
            continue
        lines.append(f"### {op}")
        lines.append("")
        for reason, names in sorted(reasons.items()):
            lines.append(f"- excluded ({len(names)}): {reason} — {', '.join(f'`{n}`' for n in names)}")
        for name, detail in failed:
            lines.append(f"- **failed** `{name}`: {detail}")
        lines.append("")
    return "\n".join(lines).rstrip() + "\n"


def update_readme(line: str, float32: str) -> bool:
    """Rewrites the totals lines (starting with 'Node tests:' and 'Float32 share:') in README.md's
    Conformance section."""
    text = README.read_text(encoding="utf-8")
    text, count = re.subn(r"(?m)^Node tests: .*$", f"Node tests: {line}.", text)
    text, share = re.subn(r"(?m)^Float32 share: .*$", f"Float32 share: {float32}.", text)
    if count and share:
        README.write_text(text, encoding="utf-8")
    return bool(count and share)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-j", "--jobs", type=int, default=2, help="parallel processes (default 2)")
    parser.add_argument("-o", "--output", type=Path, default=OUTPUT, help=f"markdown file (default {OUTPUT})")
    parser.add_argument("--failures", action="store_true", help="also print every failing case and its error")
    parser.add_argument("--readme", action="store_true", help="update the totals line in README.md")
    args = parser.parse_args(argv)
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # onnx's case generators warn about overflowing casts
        _TEST_CASES.update(conformance.backend_test_cases(NncgBackend, __name__))
    results = run_all(args.jobs)
    seconds = time.perf_counter() - start
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(markdown(results), encoding="utf-8")
    if args.failures:
        for op, name, status, detail in results:
            if status == "failed":
                print(f"{op}\t{name}\t{detail}")
    total = totals_line(results)
    print(f"{total}; {float32_line(results)} ({seconds:.0f} s); wrote {args.output}")
    if args.readme and not update_readme(total, float32_line(results)):
        print("README.md lacks the 'Node tests:' or 'Float32 share:' line to update", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())

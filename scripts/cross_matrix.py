"""Prints what tests/test_cross_targets.py checks as two tables: the max absolute error against
onnxruntime per target and model, and the Cortex-M4 flash and RAM bytes per model.

    python3 scripts/cross_matrix.py [-j 2]

Targets whose toolchain is missing show as "missing"; a failed run shows as FAIL (max rel error
above the tests' tolerance) or ERROR.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(ROOT), str(ROOT / "tests")]

from cross_helpers import (  # noqa: E402
    CASES,
    CORTEX_M4_MODELS,
    CORTEX_M4_TOOLS,
    MODELS,
    TOOLCHAINS,
    format_table,
    missing_tools,
    size_row,
    verify_on,
    verify_on_cortex_m4,
)

import nncg  # noqa: E402


def _cell(report) -> str:
    error = f"{max(s.max_abs for s in report.stats):.2g}"
    return error if report.ok else f"FAIL {error}"


def target_cell(toolchain: str, model: str) -> str:
    tc = TOOLCHAINS[toolchain]
    if missing_tools(tc):
        return "missing"
    try:
        return _cell(verify_on(tc, model, nncg.compile(MODELS[model], target=tc.target)))
    except Exception as exc:  # noqa: BLE001 - the table shows it, the run goes on
        return f"ERROR {type(exc).__name__}"


def cortex_m4_row(model: str) -> dict[str, object]:
    if any(shutil.which(tool) is None for tool in CORTEX_M4_TOOLS):
        return {"max abs err": "missing"}
    compiled = nncg.compile(MODELS[model], target="ansi-c")
    with tempfile.TemporaryDirectory(prefix="nncg-cortex-m4-") as tmp:
        report, result = verify_on_cortex_m4(model, compiled, Path(tmp))
    return {"max abs err": _cell(report), **size_row(result, compiled.arena_bytes)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-j", "--jobs", type=int, default=1, help="runs at a time (default 1)")
    args = parser.parse_args()
    with ProcessPoolExecutor(args.jobs) as pool:
        cells = pool.map(target_cell, *zip(*CASES))
        m4_rows = pool.map(cortex_m4_row, CORTEX_M4_MODELS)
        errors: dict[str, dict[str, object]] = {tc: {} for tc in TOOLCHAINS}
        for (toolchain, model), cell in zip(CASES, cells):
            errors[toolchain][model] = cell
        for toolchain in TOOLCHAINS:
            errors[toolchain] = {model: errors[toolchain].get(model, "-") for model in MODELS}
        print("max abs error vs onnxruntime (seed 0), '-': not run\n")
        print(format_table(errors, corner="target"))
        print("\nCortex-M4 (arm-none-eabi-gcc -Os, MPS2 AN386 in QEMU): bytes of the model's object file;")
        print("image: the whole program with start-up, test harness, embedded input and newlib\n")
        print(format_table(dict(zip(CORTEX_M4_MODELS, m4_rows))))
    return 0


if __name__ == "__main__":
    sys.exit(main())

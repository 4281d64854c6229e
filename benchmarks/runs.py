"""A suite measured several times (--runs N): each row merged with its namesakes of the other runs (same
model, target, setting). Times are the medians over the runs; a paired ratio keeps every run's value, for
its median and its range column. Used by suite.py, memory_suite.py and int8_suite.py alike."""

from __future__ import annotations

import statistics
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import TypeVar

from nncg.bench.benchmark import BenchResult

R = TypeVar("R")
# A BenchResult's figures over runs (the peak's where it was sampled in the batches).
RESULT_MEDIANS = ("nncg_us", "ort_bound_us", "ort_run_us", "speedup", "peak_gflops", "paired_percent")


def merged_runs(
    same: Sequence[R],
    measured: Callable[[R], bool],
    medians: tuple[str, ...] = (),
    results: tuple[str, ...] = (),
    per_run: dict[str, Callable[[R], tuple]] | None = None,
) -> R:
    """The first run's row with its `medians` fields (µs) and its `results` (BenchResults: median_result)
    the medians over the runs, and each `per_run` field every run's values in run order (what the
    callable gives of a run: its ratios). A run that failed (not `measured`) stands for all: a model fails
    the same way each time; a single run is kept as measured."""
    failed = [row for row in same if not measured(row)]
    if failed or len(same) == 1:
        return (failed or same)[0]
    fields: dict[str, object] = _medians(same, medians)
    fields |= {name: median_result([getattr(row, name) for row in same]) for name in results}
    fields |= {name: tuple(x for row in same for x in of_run(row)) for name, of_run in (per_run or {}).items()}
    return replace(same[0], **fields)


def median_result(results: Sequence[BenchResult]) -> BenchResult:
    """The first of a model's results of several runs with the medians over the runs of its µs and speed-up
    (no per-batch times: they are one run's)."""
    return replace(results[0], **_medians(results, RESULT_MEDIANS), batch_us=())


def runs_of(rows: Sequence[object], per_run: str) -> int:
    """How many runs the rows are merged from: the most values of their `per_run` field (a row of a single
    run may have none or one)."""
    return max((len(getattr(row, per_run)) for row in rows), default=0)


def _medians(rows: Sequence[object], fields: tuple[str, ...]) -> dict[str, float]:
    """The medians of the fields every row has a value of (not None)."""
    values = {name: [getattr(row, name) for row in rows] for name in fields}
    return {name: statistics.median(v) for name, v in values.items() if None not in v}

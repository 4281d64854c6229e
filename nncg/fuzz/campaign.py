"""A fuzz run: cases (seed, 0..N-1) evaluated in worker processes, counted per outcome; every
failure saved, the first of each kind of failure shrunk to a minimal model."""

from __future__ import annotations

import json
import os
import re
import time
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .build import build
from .case import Case, evaluate, make_case
from .options import Options
from .recipe import Recipe
from .runner import OUTCOMES, SHRINKABLE, Outcome
from .shrinker import MAX_EVALUATIONS, MAX_SECONDS, Shrunk, shrink

PROGRESS_SECONDS = 30
SHRINKS_PER_SIGNATURE = 3


@dataclass
class Settings:
    seed: int = 0
    count: int | None = 100  # None: until `minutes` are up
    minutes: float | None = None
    targets: list[str] = field(default_factory=lambda: ["ansi-c"])
    jobs: int = 1
    out: Path = Path("fuzz-out")
    sanitize_fraction: float = 0.1
    focus: tuple[str, ...] = ()  # step kinds proposed more often (nncg.fuzz.generator.FOCUS_WEIGHT)
    every_target: bool = False  # each graph on every target (count = graphs x targets)
    shrink: bool = True
    shrink_evaluations: int = MAX_EVALUATIONS
    shrink_seconds: float = MAX_SECONDS


@dataclass
class Summary:
    counts: Counter = field(default_factory=Counter)
    saved: list[tuple[int, str, Path]] = field(default_factory=list)  # (index, kind, directory)
    seconds: float = 0.0

    def format(self) -> str:
        lines = [f"{sum(self.counts.values())} cases in {self.seconds:.0f} s"]
        lines += [f"  {kind:20} {self.counts[kind]}" for kind in OUTCOMES if self.counts[kind]]
        lines += [f"{kind}: {path}" for _, kind, path in sorted(self.saved)]
        return "\n".join(lines)


def run(settings: Settings, log: Callable[[str], None] = print) -> Summary:
    """Evaluate the cases, save and shrink the failures; returns the counts and saved paths."""
    start = time.monotonic()
    results = _evaluate_all(settings, log, start)
    summary = Summary(Counter(outcome.kind for _, outcome in results.values()))
    failures = {i: r for i, r in sorted(results.items()) if r[1].kind != "pass"}
    groups: dict[str, list[int]] = {}
    for index, (case, outcome) in failures.items():
        if outcome.kind in SHRINKABLE and case is not None and settings.shrink:
            groups.setdefault(outcome.signature(), []).append(index)
    cases = {signature: [(i, failures[i][0]) for i in indices] for signature, indices in groups.items()}
    shrunk, same_as = _shrink_groups(settings, cases, log)
    for index, (case, outcome) in failures.items():
        first = same_as.get(index)
        twin = _case_dir(settings, first, failures[first][1]) if first is not None else None
        path = save(settings.out, index, settings.seed, case, outcome, shrunk.get(index), twin)
        summary.saved.append((index, outcome.kind, path))
    summary.seconds = time.monotonic() - start
    return summary


def _evaluate_all(settings: Settings, log, start: float) -> dict[int, tuple[Case | None, Outcome]]:
    results: dict[int, tuple[Case | None, Outcome]] = {}
    last = [start]

    def report(index: int, case: Case | None, outcome: Outcome) -> None:
        results[index] = (case, outcome)
        if outcome.kind != "pass":
            log(f"case {index}: {outcome.kind}: {outcome.message.splitlines()[0][:160] if outcome.message else ''}")
        if time.monotonic() - last[0] > PROGRESS_SECONDS:
            last[0] = time.monotonic()
            log(_progress(results, start))

    indices = _indices(settings, start)
    if settings.jobs <= 1:
        for index in indices:
            report(*evaluate_index(settings, index))
        return results
    with ProcessPoolExecutor(max_workers=settings.jobs) as pool:
        pending: set[Future] = set()
        for index in indices:
            pending.add(pool.submit(evaluate_index, settings, index))
            if len(pending) >= 2 * settings.jobs:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    report(*future.result())
        for future in pending:
            report(*future.result())
    return results


def _indices(settings: Settings, start: float) -> Iterator[int]:
    index = 0
    while settings.count is None or index < settings.count:
        if settings.minutes is not None and time.monotonic() - start > settings.minutes * 60:
            return
        yield index
        index += 1


def _progress(results, start: float) -> str:
    counts = Counter(outcome.kind for _, outcome in results.values())
    shown = ", ".join(f"{kind} {counts[kind]}" for kind in OUTCOMES if counts[kind])
    return f"[{len(results)} cases, {time.monotonic() - start:.0f} s] {shown}"


def evaluate_index(settings: Settings, index: int) -> tuple[int, Case | None, Outcome]:
    """Case `index` of the run: drawn, built, checked, run (in a worker process)."""
    case = make_case(
        settings.seed, index, settings.targets, settings.sanitize_fraction, settings.focus, settings.every_target
    )
    if isinstance(case, Outcome):
        return index, None, case
    return index, case, evaluate(case.recipe, case.options)


def _shrink_groups(settings: Settings, groups: dict[str, list[tuple[int, Case]]], log):
    """Shrink failures group by group (a group: one signature), groups in parallel. Returns the
    shrunk cases by index, and for each case not shrunk the index of the case it repeats."""
    if not groups:
        return {}, {}
    log(f"shrinking failures of {len(groups)} kinds")
    limits = (settings.shrink_evaluations, settings.shrink_seconds)
    if settings.jobs <= 1:
        results = [shrink_group(signature, group, *limits) for signature, group in groups.items()]
    else:
        with ProcessPoolExecutor(max_workers=settings.jobs) as pool:
            jobs = [pool.submit(shrink_group, signature, group, *limits) for signature, group in groups.items()]
            results = [job.result() for job in jobs]
    shrunk, same_as = {}, {}
    for done, repeats in results:
        shrunk |= done
        same_as |= repeats
    return shrunk, same_as


def shrink_group(signature: str, group: list[tuple[int, Case]], evaluations: int, seconds: float):
    """Shrink the first case of a group of same-signature failures, then each later one whose
    features do not include a minimal case's (likely another bug), up to SHRINKS_PER_SIGNATURE."""
    shrunk: dict[int, tuple[Shrunk, Outcome]] = {}
    same_as: dict[int, int] = {}
    for index, case in group:
        kinds = features(case.recipe)
        explained = [i for i, (s, _) in shrunk.items() if features(s.recipe) <= kinds]
        if explained or len(shrunk) >= SHRINKS_PER_SIGNATURE:
            same_as[index] = explained[0] if explained else group[0][0]
            continue
        shrunk[index] = shrink_case(case.recipe, case.options, signature, evaluations, seconds)
    return shrunk, same_as


def features(recipe: Recipe) -> set[str]:
    """Step kinds and their text parameters (modes, ops): a failure whose case has all of a minimal
    case's features is taken for the same bug."""
    out = set()
    for step in recipe.steps:
        out.add(step.op)
        out |= {f"{step.op}.{key}={value}" for key, value in step.params.items() if isinstance(value, str)}
    return out


def shrink_case(
    recipe: Recipe, options: Options, signature: str, evaluations: int, seconds: float
) -> tuple[Shrunk, Outcome]:
    """The smallest case failing with the same signature, and its outcome."""
    outcomes: dict[str, Outcome] = {}

    def fails(r: Recipe, o: Options) -> bool:
        outcome = evaluate(r, o)
        outcomes[r.key() + repr(o)] = outcome
        return outcome.signature() == signature

    shrunk = shrink(recipe, options, fails, evaluations, seconds)
    final = outcomes.get(shrunk.recipe.key() + repr(shrunk.options)) or evaluate(shrunk.recipe, shrunk.options)
    return shrunk, final


# ---------------------------------------------------------------------------- saving


def _slug(kind: str) -> str:
    return re.sub(r"[^a-z0-9-]+", "-", kind.lower())


def _case_dir(settings: Settings, index: int, outcome: Outcome) -> Path:
    return settings.out / _slug(outcome.kind) / f"s{settings.seed}-{index}"


def save(out: Path, index: int, seed: int, case: Case | None, outcome: Outcome, shrunk, same_as: Path | None) -> Path:
    """Write the failing case (and its shrunk version) into OUT/KIND/sSEED-INDEX/; returns the folder."""
    folder = out / _slug(outcome.kind) / f"s{seed}-{index}"
    folder.mkdir(parents=True, exist_ok=True)
    record: dict[str, Any] = {
        "seed": seed,
        "index": index,
        "outcome": outcome_json(outcome),
        "signature": outcome.signature(),
    }
    if case is not None:
        record |= {
            "recipe": case.recipe.to_json(),
            "options": case.options.to_json(),
            "command": case.options.command(),
        }
        _write_model(case.recipe, folder / "model.onnx")
    if same_as is not None:
        record["same_as"] = str(same_as)
    (folder / "case.json").write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    if shrunk is not None:
        result, final = shrunk
        minimal = {
            "recipe": result.recipe.to_json(),
            "options": result.options.to_json(),
            "outcome": outcome_json(final),
            "command": result.options.command("minimal.onnx"),
            "evaluations": result.evaluations,
        }
        _write_model(result.recipe, folder / "minimal.onnx")
        (folder / "minimal.json").write_text(json.dumps(minimal, indent=1, sort_keys=True) + "\n")
    return folder


def _write_model(recipe: Recipe, path: Path) -> None:
    try:
        path.write_bytes(build(recipe).SerializeToString())
    except Exception as exc:  # the recipe is saved either way; a model that does not build is noted
        path.with_suffix(".txt").write_text(f"the recipe does not build: {exc}\n")


def outcome_json(outcome: Outcome) -> dict[str, Any]:
    return {"kind": outcome.kind, "message": outcome.message, "max_rel": outcome.max_rel, "c_bytes": outcome.c_bytes}


def replay(path: Path) -> Outcome:
    """Re-run a saved case: FOLDER (its minimal case if shrunk, else the case) or a .json file."""
    if path.is_dir():
        path = path / "minimal.json" if (path / "minimal.json").exists() else path / "case.json"
    data = json.loads(path.read_text())
    return evaluate(Recipe.from_json(data["recipe"]), Options.from_json(data["options"]))


def default_jobs() -> int:
    return os.cpu_count() or 1


def promote(found: Path, dest: Path, description: str, xfail: str | None = None) -> Path:
    """Turn a saved failure (its minimal case if shrunk) into a regression case for
    tests/test_fuzz.py: DEST/model.onnx and DEST/case.json (options, what it checks, xfail reason)."""
    path = found / "minimal.json" if (found / "minimal.json").exists() else found / "case.json"
    data = json.loads(path.read_text())
    recipe, options = Recipe.from_json(data["recipe"]), Options.from_json(data["options"])
    dest.mkdir(parents=True, exist_ok=True)
    (dest / "model.onnx").write_bytes(build(recipe).SerializeToString())
    record: dict[str, Any] = {"description": description, "options": options.to_json(), "recipe": recipe.to_json()}
    record |= {"found_as": data.get("outcome", {}).get("kind"), "command": options.command()}
    if xfail:
        record["xfail"] = xfail
    (dest / "case.json").write_text(json.dumps(record, indent=1, sort_keys=True) + "\n")
    return dest

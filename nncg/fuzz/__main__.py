"""`python -m nncg.fuzz`: a fuzz run, per-outcome counts at the end, the saved path of every failure."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ..host_cpu import host_targets
from .campaign import Settings, default_jobs, promote, replay, run
from .ops import OPS
from .options import CROSS, cross_available


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="python -m nncg.fuzz", description=__doc__)
    parser.add_argument("--count", type=int, help="number of cases (default 100, or unlimited with --minutes)")
    parser.add_argument("--minutes", type=float, help="stop starting new cases after this many minutes")
    parser.add_argument("--seed", type=int, default=0, help="case i of seed S is always the same case")
    parser.add_argument("--targets", help="comma-separated targets (default: every host target; neon runs under qemu)")
    parser.add_argument("--jobs", type=int, default=default_jobs(), help="worker processes (default: CPU count)")
    parser.add_argument("--out", type=Path, default=Path("fuzz-out"), help="where failures are saved")
    parser.add_argument("--sanitize-fraction", type=float, default=0.1, help="share of cases built with ASan+UBSan")
    parser.add_argument(
        "--focus", default="", help="comma-separated step kinds to propose 10x as often, e.g. Resize,MaxPool"
    )
    parser.add_argument(
        "--every-target",
        action="store_true",
        help="build each graph for every target (--count then counts graphs x targets)",
    )
    parser.add_argument("--no-shrink", action="store_true", help="save failures without shrinking them")
    parser.add_argument("--replay", type=Path, help="re-run a saved case (its folder or .json) and print the outcome")
    parser.add_argument(
        "--promote",
        nargs=2,
        type=Path,
        metavar=("FOUND", "DEST"),
        help="make a saved failure a regression case of tests/test_fuzz.py in DEST (tests/fuzz_regressions/NAME)",
    )
    parser.add_argument("--description", default="", help="with --promote: what the case checks, one line")
    parser.add_argument("--xfail", help="with --promote: the reason it still fails (the test is xfail strict)")
    return parser.parse_args(argv)


def targets(text: str | None) -> list[str]:
    if not text:
        return host_targets()
    chosen = [t.strip() for t in text.split(",") if t.strip()]
    for target in chosen:
        if target in CROSS and not cross_available(target):
            raise SystemExit(f"target {target} needs {CROSS[target][0]} and {CROSS[target][2][0]} on PATH")
        if target not in CROSS and target not in host_targets():
            raise SystemExit(f"target {target} does not run on this machine; host targets: {', '.join(host_targets())}")
    return chosen


def focus(text: str) -> tuple[str, ...]:
    chosen = tuple(op.strip() for op in text.split(",") if op.strip())
    unknown = [op for op in chosen if op not in OPS]
    if unknown:
        raise SystemExit(f"unknown step kinds {', '.join(unknown)}; kinds: {', '.join(OPS)}")
    return chosen


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    if args.replay:
        outcome = replay(args.replay)
        print(f"{outcome.kind}: {outcome.message}")
        return 0 if outcome.kind == "pass" else 1
    if args.promote:
        print(promote(*args.promote, args.description, args.xfail))
        return 0
    count = args.count if args.count is not None else (None if args.minutes else 100)
    settings = Settings(
        seed=args.seed,
        count=count,
        minutes=args.minutes,
        targets=targets(args.targets),
        jobs=max(args.jobs, 1),
        out=args.out,
        sanitize_fraction=args.sanitize_fraction,
        focus=focus(args.focus),
        every_target=args.every_target,
        shrink=not args.no_shrink,
    )
    print(
        f"fuzzing: seed {settings.seed}, {count or 'unlimited'} cases"
        + (f", {args.minutes} minutes" if args.minutes else "")
        + f", targets {','.join(settings.targets)}, {settings.jobs} jobs, failures to {settings.out}",
        flush=True,
    )
    summary = run(settings, lambda line: print(line, flush=True))
    print(summary.format(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

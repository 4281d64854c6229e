"""Progress bars for the waits of --tune and --benchmark: a tqdm bar on stderr when it is a terminal,
nothing at all when it is not (a log file, CI), so logs keep only the result lines."""

from __future__ import annotations

import sys

from tqdm import tqdm


def progress_bar(total: int, description: str) -> tqdm:
    """A bar counting to `total`, labelled `description` (NNCG's own text, not the model's); use it
    as a context manager and call update() per step. Disabled when stderr is not a terminal."""
    return tqdm(total=total, desc=description, file=sys.stderr, leave=False, disable=not sys.stderr.isatty())

"""What a compilation is asked for, as one value: `CompileOptions`, turned into a pass pipeline in one
place. A custom pipeline records its own unroll level, weights placement and code budget, so it may
not be combined with those options: the combination is refused, never silently half-applied."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from .errors import NncgError
from .ir.target import Target
from .passes import default_pipeline
from .passes.unroll import CODE_BUDGET


@dataclass(frozen=True)
class CompileOptions:
    """`unroll`: auto, a depth (the paper's levels) or none; `weights`: auto, embed or bin;
    `code_budget`: statements of unrolled code in the whole model (None: no cap); `requantize`: float
    or fixed, how an int8 model's integer layers scale their results; `pipeline`: a custom pass
    pipeline instead of the one these options give."""

    unroll: str = "auto"
    weights: str = "auto"
    code_budget: int | None = CODE_BUDGET
    pipeline: str | None = None
    requantize: str = "float"

    def __post_init__(self) -> None:
        if self.pipeline is None:
            return
        set_too = [f.name for f in fields(self) if f.name != "pipeline" and getattr(self, f.name) != f.default]
        if set_too:
            raise NncgError(
                f"a pipeline records its own {', '.join(set_too)}: give either the pipeline or "
                f"{', '.join(set_too)} (e.g. unroll{{level=...}} and plan-memory{{weights=...}} in the pipeline)"
            )

    @classmethod
    def of(
        cls,
        unroll: str | int | None,
        weights: str,
        code_budget: int | None,
        pipeline: str | None,
        requantize: str = "float",
    ):
        """From nncg.compile's arguments: unroll None means none, code_budget 0 means no cap."""
        return cls("none" if unroll is None else str(unroll), weights, code_budget or None, pipeline, requantize)

    def with_pipeline(self, pipeline: str) -> CompileOptions:
        """These options replaced by a pipeline that records them (what --tune returns)."""
        return replace(CompileOptions(), pipeline=pipeline)

    def kwargs(self) -> dict[str, object]:
        """The options as nncg.compile's keyword arguments."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def pass_pipeline(self, target: Target) -> str:
        """The one place options become the pass pipeline for `target`."""
        if self.pipeline is not None:
            return self.pipeline
        return default_pipeline(target, self.unroll, self.weights, self.code_budget, self.requantize)

"""Bounds of settings that the command line and the workflow's config schema share.

The command line validates its options with these; tests/test_safety.py fails when
workflow/schemas/config.schema.yaml says otherwise, so the two cannot drift apart.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Range:
    """A closed or open interval of a numeric setting."""

    lo: float
    hi: float
    lo_open: bool = False
    hi_open: bool = False

    def schema(self) -> dict:
        """The JSON-schema keywords that say the same."""
        return {("exclusiveMinimum" if self.lo_open else "minimum"): self.lo,
                ("exclusiveMaximum" if self.hi_open else "maximum"): self.hi}


# registration.level: the print is where the density reaches this fraction of the batch's
# dense-polymer level (0 would make the background a print, 1 leaves nothing).
# registration.min_score: a correlation coefficient's share in [0, 1].
REGISTRATION = {"level": Range(0, 1, lo_open=True, hi_open=True), "min_score": Range(0, 1)}

"""Verdicts of the learning experiments (maze, tracking) as typed records, apart from their English.

A claim is a family of comparisons (`Test`: a difference whose sign the claim predicts, its 95% interval
and two-sided p-value). `decide` corrects the family's p-values by Holm's step-down (`CORRECTION`) and
gives each comparison its verdict: `HOLDS` where the adjusted p is below `ALPHA` on the claimed side,
`FAILS` where it is below on the other side, else `OPEN`; the claim holds when every comparison does and
does not hold when any comparison fails. `settle` is the one rule for replicates: a verdict is stated only
where every replicate gives it, else `NOT_SETTLED`. `phrase` is a verdict's words after "the claim" (the
reports' sentences).
"""
from __future__ import annotations

from dataclasses import dataclass

from skinsafe.core.experiments.stats import holm

HOLDS, FAILS, OPEN, NOT_SETTLED = "holds", "does not hold", "not resolved", "not settled"
ALPHA = 0.05
CORRECTION = ("Holm's step-down correction over each claim's comparisons (family-wise error 5%): a comparison "
              "is decided where its adjusted two-sided p-value is below 0.05")


@dataclass(frozen=True)
class Test:
    """One comparison of a claim: `difference` > 0 is the claimed direction; `ci95` its uncorrected 95%
    interval, `p` the two-sided p-value of that test."""

    name: str
    difference: float
    ci95: tuple[float, float]
    p: float


@dataclass(frozen=True)
class Comparison:
    """A `Test` with its Holm-adjusted p-value and its verdict (HOLDS, FAILS or OPEN)."""

    name: str
    difference: float
    ci95: tuple[float, float]
    p: float
    p_holm: float
    verdict: str


def decide(tests: list[Test], alpha: float = ALPHA) -> tuple[Comparison, ...]:
    """Every test of one family with its Holm-adjusted p-value and verdict (module doc)."""
    adjusted = holm([t.p for t in tests]) if tests else []
    return tuple(Comparison(t.name, float(t.difference), (float(t.ci95[0]), float(t.ci95[1])), float(t.p), float(q),
                            OPEN if q >= alpha or t.difference == 0 else HOLDS if t.difference > 0 else FAILS)
                 for t, q in zip(tests, adjusted))


def overall(comparisons) -> str:
    """A claim's verdict from its comparisons: HOLDS when all hold, FAILS when any fails, else OPEN."""
    verdicts = [c.verdict for c in comparisons]
    return HOLDS if verdicts and all(v == HOLDS for v in verdicts) else FAILS if FAILS in verdicts else OPEN


@dataclass(frozen=True)
class Settled:
    """A verdict across replicates: each replicate's, whether they agree, and the one stated (`verdict`)."""

    verdict: str
    replicate_verdicts: tuple[str, ...]
    agrees: bool


def settle(verdicts) -> Settled:
    """The verdict every replicate gives, or NOT_SETTLED where they differ (never one replicate's alone)."""
    v = tuple(verdicts)
    if not v:
        raise ValueError("settle needs at least one replicate's verdict")
    agrees = len(set(v)) == 1
    return Settled(v[0] if agrees else NOT_SETTLED, v, agrees)


def phrase(verdict: str) -> str:
    """"holds", "does not hold", "is not resolved", "is not settled"."""
    return verdict if verdict in (HOLDS, FAILS) else f"is {verdict}"

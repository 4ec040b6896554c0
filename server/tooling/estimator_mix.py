"""Which simulated vehicles run which estimators: a rule every publisher of the tooling takes.

A simulated vehicle's config leaves ``estimators`` empty (its kind's defaults) unless an
:class:`EstimatorMix` names others for it: ``EstimatorMix(4, ("mdsf", "reference_speed"))``
gives ``sim-0004``, ``sim-0008``, ... both estimators. Kept apart from the publisher so the
command line can parse the rule without loading Zenoh.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

__all__ = ["EstimatorMix", "add_estimator_mix_argument"]


@dataclass(frozen=True, slots=True)
class EstimatorMix:
    """Every ``every``-th vehicle (by number: ``sim-000k``, ``sim-00(2k)``, ...) runs the
    estimators ``names``; the others leave ``estimators`` empty (their kind's defaults)."""

    every: int
    names: tuple[str, ...]

    def __post_init__(self) -> None:
        if self.every < 1 or not self.names:
            raise ValueError("an estimator mix needs every >= 1 and at least one name")

    def __str__(self) -> str:
        """The command-line form :meth:`parse` reads."""
        return f"{self.every}:{','.join(self.names)}"

    def names_for(self, number: int) -> tuple[str, ...]:
        """The ``estimators`` of vehicle number ``number`` (1-based, as in its id)."""
        return self.names if number % self.every == 0 else ()

    @classmethod
    def parse(cls, text: str) -> EstimatorMix:
        """``"K:NAME[,NAME...]"``, e.g. ``"4:mdsf,reference_speed"`` (command-line form)."""
        every, sep, names = text.partition(":")
        parts = tuple(n.strip() for n in names.split(",") if n.strip())
        if not sep or not every.strip().isdigit() or not parts:
            raise ValueError(f"expected EVERY:NAME[,NAME...], got {text!r}")
        from estimator.catalog import SPECS  # the estimators only when a rule is given

        unknown = [n for n in parts if n not in SPECS]
        if unknown:
            raise ValueError(f"unknown estimators {unknown}; known: {sorted(SPECS)}")
        return cls(int(every), parts)


def add_estimator_mix_argument(parser: argparse.ArgumentParser, default: str) -> None:
    """``--estimator-mix EVERY:NAME[,NAME...]`` on ``parser`` (``default`` says what it is
    without the option); the parsed value is an :class:`EstimatorMix` or None."""
    parser.add_argument(
        "--estimator-mix",
        type=_parse_argument,
        default=None,
        metavar="EVERY:NAME[,NAME...]",
        help="every EVERY-th simulated vehicle (by the number in its id) runs these "
        f"estimators, e.g. 4:mdsf,reference_speed; the others their kind's defaults ({default})",
    )


def _parse_argument(text: str) -> EstimatorMix:
    try:
        return EstimatorMix.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None

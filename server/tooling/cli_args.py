"""Command-line pieces shared by ``slipfleet`` and ``python -m server.tooling.loadtest``.

* :class:`OneLineParser`: a user's mistake on the command line is one line on stderr (what was
  wrong and where to look), exit status 2, never a usage block or a traceback.
* ``--scenario``: the simulator's scenario names are listed in ``--help`` and checked when
  parsed, without importing the simulator (numpy) for ``--help`` of other commands.
* ``--token-file``: a REST access token for tools that read a server's API.
* argument types for counts and durations whose mistakes are one line.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

__all__ = [
    "SCENARIOS_IN_HELP",
    "TOKEN_ENV",
    "HelpFormatter",
    "OneLineParser",
    "add_scenario_argument",
    "add_token_argument",
    "count_arg",
    "positive_arg",
    "read_token",
    "scenario_names",
    "seconds_or_zero_arg",
]

#: Placeholder in a help text that ``--help`` replaces by the scenario names.
SCENARIOS_IN_HELP = "{scenarios}"
#: Environment variable holding a REST access token when ``--token-file`` is not given.
TOKEN_ENV = "SLIPFLEET_TOKEN"


def scenario_names() -> list[str]:
    """The simulator's scenario names (imported on demand: the simulator pulls in numpy)."""
    from estimator.sim.scenarios import scenario_names as names

    return list(names())


class HelpFormatter(argparse.HelpFormatter):
    """Writes the scenario names where a help text holds :data:`SCENARIOS_IN_HELP`."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = super()._get_help_string(action)
        if text and SCENARIOS_IN_HELP in text:
            text = text.replace(SCENARIOS_IN_HELP, ", ".join(scenario_names()))
        return text


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line: ``prog: what was wrong (see prog --help)``.

    Sub-parsers made by ``add_subparsers`` are of this class too (argparse uses the parent's)."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _scenario_type(mix: bool) -> Callable[[str], str]:
    def scenario(text: str) -> str:
        if mix and text == "mix":
            return text
        names = scenario_names() + (["mix"] if mix else [])
        if text not in names:
            raise argparse.ArgumentTypeError(
                f"unknown scenario {text!r}; one of: {', '.join(names)}"
            )
        return text

    return scenario


def add_scenario_argument(p: argparse.ArgumentParser, default: str, *, mix: bool = False) -> None:
    """``--scenario NAME``, checked against the simulator's names (and ``mix`` if allowed)."""
    also = "; or 'mix': vehicles spread over several" if mix else ""
    p.add_argument(
        "--scenario",
        default=default,
        type=_scenario_type(mix),
        metavar="NAME",
        help=f"simulated drive: {SCENARIOS_IN_HELP}{also} (default {default})",
    )


def add_token_argument(p: argparse.ArgumentParser) -> None:
    """``--token-file PATH``: the REST access token for a server that requires one."""
    p.add_argument(
        "--token-file",
        type=Path,
        default=None,
        metavar="PATH",
        help="file holding a REST access token (viewer role; `slipfleet token create`) for a "
        f"server that requires tokens; default: the environment variable {TOKEN_ENV}",
    )


def read_token(token_file: Path | None) -> str | None:
    """The token of ``token_file`` (first line), else of :data:`TOKEN_ENV`, else None."""
    if token_file is None:
        return os.environ.get(TOKEN_ENV) or None
    try:
        lines = token_file.read_text().strip().splitlines()
    except OSError as exc:
        raise SystemExit(f"cannot read the token file {token_file}: {exc.strerror}") from exc
    if not lines:
        raise SystemExit(f"the token file {token_file} is empty")
    return lines[0].strip()


def positive_arg(text: str) -> float:
    """A number > 0 (seconds, rates)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError("must be > 0")
    return value


def count_arg(text: str) -> int:
    """A whole number ≥ 1 (vehicles)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError("must be 1 or more")
    return value


def seconds_or_zero_arg(text: str) -> float:
    """Seconds > 0, or 0: until Ctrl-C."""
    try:
        return positive_arg(text)
    except argparse.ArgumentTypeError:
        if _is_zero(text):
            return 0.0
        raise argparse.ArgumentTypeError("0 (until Ctrl-C) or a number of seconds > 0") from None


def _is_zero(text: str) -> bool:
    try:
        return float(text) == 0.0
    except ValueError:
        return False

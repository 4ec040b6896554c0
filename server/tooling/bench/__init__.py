"""Benchmarks behind ``slipfleet bench <name> [--json PATH]``.

Each module has ``run(json_path=None) -> dict`` that prints a plain-text table and, given a path,
writes the same numbers as JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import json
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "SOURCE_START_NS",
    "best_of",
    "extract_revision",
    "field_work_sources",
    "int_list",
    "json_from_child",
    "percentile",
    "push_until",
    "revision",
    "script_of",
    "side_by_side",
    "versions",
    "write_json",
]

_REPO = Path(__file__).resolve().parents[3]

SOURCE_START_NS = 1_700_000_000_000_000_000
"""Sensor time at which the field_work sources start."""


def int_list(text: str) -> list[int]:
    """``"1,2,3"`` → ``[1, 2, 3]`` (an argparse ``type``); ValueError if empty or not integers."""
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise ValueError(f"expected comma-separated integers, got {text!r}") from exc
    if not values:
        raise ValueError("expected at least one integer")
    return values


def revision(text: str) -> str:
    """A git revision of this repository (an argparse ``type`` for ``--baseline``): ``text``
    when it names a commit, else ``ArgumentTypeError``, so the command says so in one line
    instead of failing later inside ``git archive``."""
    found = subprocess.run(
        ["git", "-C", str(_REPO), "rev-parse", "--verify", "--quiet", f"{text}^{{commit}}"],
        capture_output=True,
    )
    if not text or text.startswith("-") or found.returncode != 0:
        raise argparse.ArgumentTypeError(f"{text!r} is not a revision of this repository")
    return text


def extract_revision(
    rev: str, into: Path, packages: Sequence[str] = ("estimator", "server")
) -> None:
    """The ``packages`` of git revision ``rev`` (of this repository) into the directory ``into``,
    for a baseline measured side by side in a child process (:func:`json_from_child`)."""
    tar = subprocess.run(
        ["git", "-C", str(_REPO), "archive", "--format=tar", rev, *packages],
        check=True,
        capture_output=True,
    ).stdout
    subprocess.run(["tar", "-x", "-C", str(into)], input=tar, check=True)


def json_from_child(path: str, args: Sequence[str]) -> dict[str, Any]:
    """Run ``python <args>`` with the packages under ``path`` first on its path (this
    repository after them) and return the JSON it prints.

    The same modules cannot be imported twice in one interpreter, so each version runs in its
    own; the working directory is a temporary one, so it does not come first on ``sys.path``.
    """
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([path, str(_REPO)]))
    with tempfile.TemporaryDirectory() as cwd:
        done = subprocess.run(
            [sys.executable, *args], env=env, cwd=cwd, check=True, capture_output=True, text=True
        )
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def script_of(path: str, name: str) -> str:
    """The benchmark module ``name`` (``"pipeline"``) of the version whose packages are under
    ``path``: each version measures itself with its own code, so a baseline from before the
    tooling had its room (``server/bench/``) runs the loop written for its own modules."""
    for room in ("server/tooling/bench", "server/bench"):
        script = Path(path) / room / f"{name}.py"
        if script.is_file():
            return str(script)
    raise FileNotFoundError(f"no benchmark {name!r} in the version at {path}")


@contextlib.contextmanager
def versions(baseline: str | None) -> Iterator[dict[str, str]]:
    """Where each measured version's packages are: ``{"after": this repository}``, and with a
    ``baseline`` revision first ``"before"``: its packages extracted to a temporary directory
    (removed on exit)."""
    with tempfile.TemporaryDirectory() as tmp:
        paths = {"after": str(_REPO)}
        if baseline is not None:
            extract_revision(baseline, Path(tmp))
            paths = {"before": tmp, **paths}
        yield paths


def best_of(
    paths: Mapping[str, str],
    repeats: int,
    measure: Callable[[str], dict[str, Any]],
    cost: Callable[[dict[str, Any]], float],
) -> dict[str, dict[str, Any]]:
    """Each version's result of least ``cost`` over ``repeats`` rounds that run the versions
    one after the other (so a machine shared with other work slows both alike)."""
    best: dict[str, dict[str, Any]] = {}
    for _ in range(repeats):
        for name, path in paths.items():
            got = measure(path)
            if name not in best or cost(got) < cost(best[name]):
                best[name] = got
    return best


def side_by_side(
    baseline: str | None,
    repeats: int,
    name: str,
    params: Sequence[Any],
    measure: Callable[[Any, str], dict[str, Any]],
) -> list[dict[str, Any]]:
    """Per parameter (a fleet size, a commit size, …) each version's best result:
    ``[{name: param, "after": …, ["before": …, "after_over_before": …]}]``.

    ``measure(param, path)`` runs one case with the packages at ``path`` and returns a dict
    with a ``"total"`` cost; each version keeps its least ``"total"`` over ``repeats``
    alternating rounds (:func:`best_of`), and ``after_over_before`` is their ratio.
    """
    cases: list[dict[str, Any]] = []
    with versions(baseline) as paths:
        for param in params:
            case: dict[str, Any] = {
                name: param,
                **best_of(
                    paths,
                    repeats,
                    functools.partial(measure, param),
                    lambda got: float(got["total"]),
                ),
            }
            if "before" in case:
                case["after_over_before"] = case["after"]["total"] / case["before"]["total"]
            cases.append(case)
    return cases


def write_json(result: Any, json_path: Path | str | None) -> None:
    """Write a bench's result as indented JSON when a path is given."""
    if json_path is not None:
        Path(json_path).write_text(json.dumps(result, indent=2))


def percentile(values: Sequence[float], q: float) -> float:
    """The ``q``-th percentile (nearest rank) of ``values`` (not empty)."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, math.ceil(q / 100 * len(s)) - 1))]


def field_work_sources(seconds: float, runs: int) -> list[tuple[Any, list[Any]]]:
    """``runs`` simulated ``field_work`` drives (seeds 1…runs) for fleets that replay them.

    Returns ``(vehicle config with the run's noise figures, measurements in arrival order)``
    per run; ValueError if a run is shorter than ``seconds`` + 1 s. The estimator is imported
    here, not at module level, so a bench that measures another revision's estimator in a
    child process gets that revision's.
    """
    from estimator.sim import simulate

    out = []
    for k in range(runs):
        sim = simulate("field_work", seed=k + 1, start_ns=SOURCE_START_NS)
        if sim.duration_s < seconds + 1.0:
            raise ValueError(f"field_work runs {sim.duration_s:.0f} s, less than {seconds} s")
        config = dataclasses.replace(sim.config, noise=sim.sensor_noise)
        out.append((config, sim.in_arrival_order()))
    return out


def push_until(
    fleet: Any, ids: Sequence[str], streams: Sequence[Sequence[Any]], pos: list[int], now_ns: int
) -> None:
    """Push each vehicle's ``(arrival_ns, measurement)`` stream up to ``now_ns`` into ``fleet``.

    ``pos[k]`` is how far stream ``k`` has been pushed; it is advanced in place.
    """
    for k, vid in enumerate(ids):
        st, i = streams[k], pos[k]
        while i < len(st) and st[i][0] <= now_ns:
            fleet.push(vid, st[i][1])
            i += 1
        pos[k] = i

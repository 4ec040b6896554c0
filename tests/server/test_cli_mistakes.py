"""Every user mistake on the ``slipfleet`` command line is one clear line, never a traceback;
every option says what it is for. Runs the real command in a child process."""

from __future__ import annotations

import argparse
import json
import queue
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from estimator.sim.scenarios import scenario_names
from server.cli import _parser
from server.settings import Settings
from server.storage import open_store
from server.tokens import issue_token
from tests.server.cli_support import run_cli, serving, start_cli
from tests.server.fleet_stack import stack_settings
from tests.support import free_port

COMMANDS = ("serve", "demo", "simulate", "record", "replay", "loadtest")


def _one_line_error(result: subprocess.CompletedProcess[str]) -> str:
    assert result.returncode != 0, result.stdout
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    return lines[0]


def _subcommand(name: str) -> argparse.ArgumentParser:
    parser = _parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices[name]


@pytest.mark.parametrize("command", COMMANDS)
def test_every_option_has_help(command: str) -> None:
    missing = [
        a.option_strings or a.dest
        for a in _subcommand(command)._actions
        if not (a.help or "").strip()
    ]
    assert missing == []


@pytest.mark.parametrize("command", ["demo", "simulate", "record", "loadtest"])
def test_help_lists_the_scenarios(command: str) -> None:
    result = run_cli([command, "--help"])
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stdout.split())
    assert ", ".join(scenario_names()) in text


@pytest.mark.parametrize("command", ["demo", "simulate", "record", "loadtest"])
def test_a_wrong_scenario_is_one_line(command: str, tmp_path: Path) -> None:
    args = [command, "--scenario", "feild_work"]
    if command == "record":
        args.insert(1, str(tmp_path / "x.sfrec"))
    if command == "loadtest":
        args += ["--vehicles", "1", "--duration", "1"]
    result = run_cli(args, cwd=tmp_path)
    line = _one_line_error(result)
    assert "unknown scenario 'feild_work'" in line and "field_work" in line
    assert result.returncode == 2
    assert not (tmp_path / "x.sfrec").exists()


def test_replay_of_a_missing_or_foreign_file_is_one_line(tmp_path: Path) -> None:
    line = _one_line_error(run_cli(["replay", str(tmp_path / "none.sfrec")]))
    assert "no recording file" in line
    foreign = tmp_path / "notes.txt"
    foreign.write_text("not a recording")
    line = _one_line_error(run_cli(["replay", str(foreign), "--api", "http://127.0.0.1:1"]))
    assert "is not a slipfleet recording" in line


def test_replay_without_a_router_is_one_line(tmp_path: Path) -> None:
    rec = tmp_path / "drive.sfrec"
    made = run_cli(["record", str(rec), "--duration", "2"])
    assert made.returncode == 0, made.stderr
    port = free_port()  # nothing listens there
    line = _one_line_error(
        run_cli(["replay", str(rec), "--connect", f"tcp/127.0.0.1:{port}"], timeout_s=60)
    )
    assert f"no Zenoh router answers at tcp/127.0.0.1:{port}" in line


@pytest.fixture
def running_server(tmp_path: Path) -> Iterator[Settings]:
    with serving(stack_settings(tmp_path / "running", None, 0)) as settings:
        yield settings


@pytest.mark.zenoh
def test_demo_beside_a_running_server_is_one_line(tmp_path: Path, running_server: Settings) -> None:
    settings = running_server
    env = {
        "SLIPFLEET_STORAGE__DATA_DIR": str(tmp_path / "demo"),
        "SLIPFLEET_ZENOH__LISTEN": json.dumps(settings.zenoh.listen),
        "SLIPFLEET_VIEWER__ENABLED": "false",
    }
    result = run_cli(["demo", "--port", str(settings.api.port)], env=env, timeout_s=60)
    line = _one_line_error(result)
    assert f"port {settings.api.port}" in line and "already running" in line
    # the Zenoh port alone is taken: the same line names it
    env["SLIPFLEET_API__PORT"] = str(free_port())
    line = _one_line_error(run_cli(["demo"], env=env, timeout_s=60))
    assert "Zenoh router" in line and "already running" in line


def _stderr_until(proc: subprocess.Popen[str], text: str, timeout_s: float) -> str:
    """stderr of ``proc`` up to the first line holding ``text``, then ``proc`` ended ("" if no
    such line came within the time)."""
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stderr is not None and proc.stdout is not None
    stream = proc.stderr

    def read() -> None:
        for line in stream:
            lines.put(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    try:
        while time.monotonic() < deadline and not (seen and text in seen[-1]):
            try:
                seen.append(lines.get(timeout=0.2))
            except queue.Empty:
                continue
    finally:
        proc.terminate()
        proc.wait(30)
        reader.join(10)
        proc.stdout.close()
        stream.close()
    return "".join(seen) if seen and text in seen[-1] else ""


def _serve_log(data_dir: Path) -> str:
    env = {
        "SLIPFLEET_STORAGE__DATA_DIR": str(data_dir),
        "SLIPFLEET_API__PORT": str(free_port()),
        "SLIPFLEET_ZENOH__LISTEN": json.dumps([f"tcp/127.0.0.1:{free_port()}"]),
        "SLIPFLEET_VIEWER__ENABLED": "false",
    }
    return _stderr_until(start_cli(["serve"], env=env), "access tokens", 60)


@pytest.mark.zenoh
def test_serve_tells_whether_tokens_exist(tmp_path: Path) -> None:
    data_dir = tmp_path / "data"
    first = _serve_log(data_dir)
    assert "none exists yet" in first and "create the first one" in first
    store = open_store(Settings(storage={"data_dir": data_dir}).storage)
    try:
        issue_token(store, "ops", "admin", time.time_ns())
        issue_token(store, "wall display", "viewer", time.time_ns())
    finally:
        store.close()
    later = _serve_log(data_dir)
    assert "2 valid" in later and "create the first one" not in later

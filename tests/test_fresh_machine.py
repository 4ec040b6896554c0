"""The README's demo command, as written, from a clean clone in a fresh virtual environment.

The checkout's ``HEAD`` is cloned into a temporary folder; the command is read from the README's
"Two commands" section (so a README change that breaks it fails here) and run there with an
environment that knows nothing of this checkout (no ``PYTHONPATH``, no active virtual
environment, no ``SLIPFLEET_*`` settings), so it builds its own ``.venv`` from the system Python
as on a fresh Debian machine; pip's own cache and wheel sources are reused. The ports are the
settings the README documents for a second demo. The test waits until the dashboard, the REST
API and the 3D view answer with every simulated vehicle streaming, then stops the demo as Ctrl-C
would (SIGINT to its process group) and reads its output for a clean exit.

The README's other command, ``./scripts/test``, is what CI runs (``.ci/run``): this test does not
run the suite again.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator, Mapping
from pathlib import Path

import httpx
import pytest

from tests.support import free_port

pytestmark = [pytest.mark.zenoh, pytest.mark.slow, pytest.mark.timeout(1500)]

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
#: The demo's four tractors, its steered vehicle and its crawler (README, "Two commands").
DEMO_VEHICLES = ("sim-0001", "sim-0002", "sim-0003", "sim-0004", "sim-0005", "sim-0006")
INSTALL_AND_START_S = 1200.0
STOP_S = 60.0


def readme_demo_command(readme: str) -> str:
    """The one-line shell command of the ``sh`` block after "**Run the demo**" in the README's
    "Two commands" section."""
    section = re.search(r"^## Two commands\n(.*?)(?=^## )", readme, re.M | re.S)
    assert section, "README.md has no 'Two commands' section"
    demo = section.group(1).split("**Run the demo**", 1)
    assert len(demo) == 2, "the 'Two commands' section has no '**Run the demo**'"
    block = re.search(r"```sh\n(.*?)```", demo[1], re.S)
    assert block, "no ```sh block after '**Run the demo**'"
    lines = [ln for ln in block.group(1).splitlines() if ln.strip() and not ln.startswith("#")]
    assert len(lines) == 1, f"the demo block is not one command: {lines}"
    return lines[0].strip()


def test_readme_demo_command_is_parsed() -> None:
    assert readme_demo_command(README.read_text()) == "./scripts/demo"


def _fresh_environment(ports: Mapping[str, str]) -> dict[str, str]:
    """This process's environment without anything pointing at this checkout or its venv, plus
    ``ports`` (settings the README names)."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME") and not k.startswith("SLIPFLEET_")
    }
    venv_bin = str(Path(sys.prefix) / "bin")
    if sys.prefix != sys.base_prefix:
        env["PATH"] = os.pathsep.join(p for p in env["PATH"].split(os.pathsep) if p != venv_bin)
    env.update(ports)
    return env


@pytest.fixture
def clean_clone(tmp_path: Path) -> Iterator[Path]:
    """A clone of this checkout's ``HEAD`` (removed afterwards: its ``.venv`` is large)."""
    head = subprocess.run(
        ["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=True
    ).stdout.strip()
    clone = tmp_path / "slipfleet"
    subprocess.run(["git", "clone", "-q", str(REPO), str(clone)], check=True)
    subprocess.run(["git", "-C", str(clone), "checkout", "-q", head], check=True)
    try:
        yield clone
    finally:
        shutil.rmtree(clone, ignore_errors=True)


def _streaming(client: httpx.Client, seen: dict[str, int]) -> set[str]:
    """The demo vehicles whose latest estimate is newer than the one in ``seen`` (updated)."""
    fresh = set()
    for vid in DEMO_VEHICLES:
        r = client.get(f"/api/v1/vehicles/{vid}/latest")
        if r.status_code != 200:
            continue
        stamp_ns = int(r.json()["stamp_ns"])
        if vid in seen and stamp_ns > seen[vid]:
            fresh.add(vid)
        seen[vid] = stamp_ns
    return fresh


def _wait_until_streaming(
    proc: subprocess.Popen[bytes], api: str, log: Path, deadline: float
) -> None:
    """Until the vehicle list names every demo vehicle and each one's estimates advance."""
    seen: dict[str, int] = {}
    streaming: set[str] = set()
    with httpx.Client(base_url=api, timeout=10.0) as client:
        while streaming != set(DEMO_VEHICLES):
            assert proc.poll() is None, f"the demo exited {proc.returncode}:\n{log.read_text()}"
            assert time.monotonic() < deadline, (
                f"only {sorted(streaming)} streaming; output:\n{log.read_text()}"
            )
            time.sleep(2.0)
            try:
                listed = {v["vehicle_id"] for v in client.get("/api/v1/vehicles").json()["data"]}
            except httpx.TransportError:
                continue  # still installing or starting
            if set(DEMO_VEHICLES) <= listed:
                streaming |= _streaming(client, seen)


def _ctrl_c_as_at_a_terminal() -> None:
    """SIGINT handled by default in the demo, as in a terminal: a test run started as a
    background job of a non-interactive shell inherits SIGINT ignored, and Python then never
    raises KeyboardInterrupt."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _stop_with_ctrl_c(proc: subprocess.Popen[bytes]) -> int:
    os.killpg(proc.pid, signal.SIGINT)
    try:
        return proc.wait(timeout=STOP_S)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        raise AssertionError(f"the demo did not stop within {STOP_S:.0f} s of Ctrl-C") from None


def test_readme_demo_runs_from_a_clean_clone(clean_clone: Path, tmp_path: Path) -> None:
    command = readme_demo_command(README.read_text())
    api_port, viewer_port, zenoh_port = free_port(), free_port(), free_port()
    ports = {
        "SLIPFLEET_API__PORT": str(api_port),
        "SLIPFLEET_VIEWER__PORT": str(viewer_port),
        "SLIPFLEET_ZENOH__LISTEN": f'["tcp/127.0.0.1:{zenoh_port}"]',
    }
    readme = README.read_text()
    for name in ports:
        assert name in readme, f"the README does not document {name}"
    log = tmp_path / "demo.log"
    started = time.monotonic()
    with log.open("wb") as out:
        proc = subprocess.Popen(
            shlex.split(command),
            cwd=clean_clone,
            env=_fresh_environment(ports),
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
            preexec_fn=_ctrl_c_as_at_a_terminal,
        )
    try:
        api = f"http://127.0.0.1:{api_port}"
        _wait_until_streaming(proc, api, log, started + INSTALL_AND_START_S)
        up_s = time.monotonic() - started
        assert httpx.get(f"{api}/", timeout=10).text.lstrip().lower().startswith("<!doctype html")
        assert httpx.get(f"http://127.0.0.1:{viewer_port}/", timeout=10).status_code == 200
        returncode = _stop_with_ctrl_c(proc)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    output = log.read_text()
    print(f"fresh clone: venv, install and every vehicle streaming in {up_s:.0f} s")
    assert (clean_clone / ".venv" / "bin" / "slipfleet").exists(), "no .venv of the clone's own"
    assert "Traceback" not in output, output
    assert returncode == 0, f"exit {returncode}:\n{output}"
    assert f"dashboard  http://127.0.0.1:{api_port}/" in output

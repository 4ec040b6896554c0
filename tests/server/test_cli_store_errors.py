"""``serve`` and ``demo`` with a store that cannot be opened say so in one line before any part
starts (it was three chained tracebacks from the server's startup and a fourth from the CLI).
The real command in a child process, its ports free ones."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.server.cli_support import cli_env, run_cli
from tests.support import free_port


@pytest.mark.parametrize("command", ["serve", "demo"])
def test_a_data_dir_that_cannot_be_created_is_one_line(command: str, tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    data_dir = blocker / "data"
    env = cli_env(
        {
            "SLIPFLEET_STORAGE__DATA_DIR": str(data_dir),
            "SLIPFLEET_VIEWER__PORT": str(free_port()),
            "SLIPFLEET_ZENOH__LISTEN": f'["tcp/127.0.0.1:{free_port()}"]',
        }
    )
    result = run_cli([command, "--port", str(free_port())], env=env, cwd=tmp_path, timeout_s=60.0)
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"slipfleet {command}: sqlite: cannot create"), lines[0]
    assert str(data_dir) in lines[0]

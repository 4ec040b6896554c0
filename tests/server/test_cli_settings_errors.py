"""A settings mistake is one line naming it, before anything starts: a ``--config`` or
``SLIPFLEET_CONFIG`` file that is not there (it was silently ignored and the server ran on the
defaults), a file that is not TOML, a value of the wrong type in the file or the environment,
an environment list that is not JSON. The real command in a child process."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.server.cli_support import cli_env, run_cli

CASES = {
    "missing --config": (["--config", "FILE", "token", "list"], None, {}, "no settings file"),
    "missing SLIPFLEET_CONFIG": (
        ["token", "list"],
        None,
        {"SLIPFLEET_CONFIG": "FILE"},
        "SLIPFLEET_CONFIG: no settings file",
    ),
    "not TOML": (["--config", "FILE", "serve"], "bad = [\n", {}, "not TOML"),
    "wrong type in the file": (
        ["--config", "FILE", "demo"],
        '[api]\nport = "x"\n',
        {},
        "api.port: Input should be a valid integer",
    ),
    "wrong type in the environment": (
        ["token", "list"],
        None,
        {"SLIPFLEET_API__PORT": "abc"},
        "api.port: Input should be a valid integer",
    ),
    "a list that is not JSON": (
        ["demo"],
        None,
        {"SLIPFLEET_ZENOH__LISTEN": "tcp/127.0.0.1:7448"},
        "are JSON",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_settings_mistake_is_one_line(case: str, tmp_path: Path) -> None:
    args, text, env, says = CASES[case]
    config = tmp_path / "slipfleet.toml"
    if text is not None:
        config.write_text(text)
    args = [str(config) if a == "FILE" else a for a in args]
    env = {k: str(config) if v == "FILE" else v for k, v in env.items()}
    result = run_cli(args, env=cli_env(env), cwd=tmp_path, timeout_s=60.0)
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    assert result.returncode != 0 and len(lines) == 1, result.stderr
    assert says in lines[0], lines[0]
    assert not (tmp_path / "data").exists(), "a store was opened"

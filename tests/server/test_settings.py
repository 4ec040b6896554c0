"""Settings: defaults, environment, TOML file, precedence, secrets."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from pydantic import ValidationError

from server.settings import Settings, UnknownVehiclePolicy, load_settings


def test_defaults_bind_loopback_and_require_tokens(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SLIPFLEET_CONFIG", raising=False)
    s = Settings()
    assert s.api.host == "127.0.0.1" and s.viewer.host == "127.0.0.1"
    assert s.zenoh.listen == ["tcp/127.0.0.1:7447"] and s.zenoh.connect == []
    assert s.api.require_auth is True and s.api.cors_origins == []
    assert s.storage.url is None  # SQLite


def test_toml_then_env_then_arguments(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    toml = tmp_path / "slipfleet.toml"
    toml.write_text(
        '[api]\nport = 9001\n\n[ingest]\nlateness_ms = 300\nunknown_vehicle = "reject"\n'
        '\n[storage]\nurl = "postgresql://fleet:from-file@db/slipfleet"\n'
    )
    monkeypatch.setenv("SLIPFLEET_INGEST__LATENESS_MS", "250")
    s = load_settings(toml)
    assert s.api.port == 9001  # from the file
    assert s.ingest.lateness_ms == 250  # the environment beats the file
    assert s.ingest.unknown_vehicle is UnknownVehiclePolicy.REJECT
    assert s.storage.url is not None
    assert s.storage.url.get_secret_value().endswith("@db/slipfleet")
    assert "from-file" not in repr(s) and "from-file" not in str(s.model_dump())
    s2 = load_settings(toml, api={"port": 9002})  # explicit arguments beat both
    assert s2.api.port == 9002


def test_invalid_values_are_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("SLIPFLEET_CONFIG", raising=False)
    with pytest.raises(ValidationError, match="CORS"):
        Settings(api={"cors_origins": ["*"]})
    with pytest.raises(ValidationError):
        Settings(storage={"commit_interval_s": 5})  # the writer commits at least every second
    monkeypatch.setenv("SLIPFLEET_INGEST__LATENESS_MS", "-1")
    with pytest.raises(ValidationError):
        Settings()


def test_loading_a_file_leaves_the_environment_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("SLIPFLEET_CONFIG", raising=False)
    toml = tmp_path / "a.toml"
    toml.write_text("[api]\nport = 9005\n")
    assert load_settings(toml).api.port == 9005
    assert "SLIPFLEET_CONFIG" not in os.environ
    assert load_settings().api.port == 8000
    monkeypatch.setenv("SLIPFLEET_CONFIG", str(toml))  # the variable works on its own too
    assert load_settings().api.port == 9005


def test_alert_rule_limits_from_the_file_in_the_alert_engines_form(tmp_path: Path) -> None:
    from server.analytics.alerts import AlertEngine

    toml = tmp_path / "slipfleet.toml"
    toml.write_text('[alerts.rule_limits."friction:low_mu"]\nbelow = 0.2\nhold_s = 5\n')
    s = load_settings(toml)
    limits = s.alerts.engine_limits()
    assert limits == {"friction:low_mu": {"below": 0.2, "hold_s": 5.0}}
    AlertEngine(rule_limits=limits)  # accepted as the engine takes them


@pytest.mark.parametrize(
    "body",
    [
        '[alerts.rule_limits."low_mu"]\nbelow = 0.2\n',  # no estimator
        '[alerts.rule_limits."friction:low_mu"]\nhold = 5\n',  # not a limit
        '[alerts.rule_limits."friction:low_mu"]\nhold_s = -1\n',
    ],
)
def test_a_mistaken_alert_rule_limit_is_refused(tmp_path: Path, body: str) -> None:
    toml = tmp_path / "slipfleet.toml"
    toml.write_text(body)
    with pytest.raises(ValidationError, match="rule_limits"):
        load_settings(toml)

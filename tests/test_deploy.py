"""deploy/compose.yaml parses, every service has a health check, secrets are required."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import yaml

COMPOSE = Path(__file__).resolve().parents[1] / "deploy" / "compose.yaml"


def _compose() -> dict[str, Any]:
    data = yaml.safe_load(COMPOSE.read_text())
    assert isinstance(data, dict)
    return data


def test_every_service_has_a_healthcheck_and_waits_for_healthy_dependencies() -> None:
    services = _compose()["services"]
    assert {"postgres", "zenoh-router-a", "zenoh-router-b", "server-a", "server-b"} <= set(services)
    for name, service in services.items():
        assert "test" in service["healthcheck"], name
        for dep, cond in (service.get("depends_on") or {}).items():
            assert dep in services
            assert cond["condition"] == "service_healthy", (name, dep)


def test_secrets_are_required_and_never_defaulted() -> None:
    text = COMPOSE.read_text()
    assert re.search(r"\$\{POSTGRES_PASSWORD:\?", text)
    assert re.search(r"\$\{SLIPFLEET_IMAGE_TAG:\?", text)
    assert not re.search(r"\$\{POSTGRES_PASSWORD:-", text)


def test_replicas_own_disjoint_shares_of_one_database() -> None:
    services = _compose()["services"]
    env_a, env_b = services["server-a"]["environment"], services["server-b"]["environment"]
    # "$$" is compose's escape for a literal "$" (Zenoh's sub-chunk wildcard "$*")
    assert env_a["SLIPFLEET_ZENOH__VEHICLE_FILTER"] == "a-$$*"
    assert env_b["SLIPFLEET_ZENOH__VEHICLE_FILTER"] == "b-$$*"
    assert env_a["SLIPFLEET_STORAGE__URL"] == env_b["SLIPFLEET_STORAGE__URL"]
    # each replica runs its pipeline in worker processes, as many as the operator says
    for env in (env_a, env_b):
        assert re.fullmatch(r"\$\{INGEST_WORKERS:-\d+\}", env["SLIPFLEET_INGEST__WORKERS"])
    for service in services.values():
        for port in service.get("ports", []):
            assert port.startswith("${"), port  # host address comes from a variable (loopback)

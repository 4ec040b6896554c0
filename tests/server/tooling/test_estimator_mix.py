"""A mixed simulated fleet: the estimator rule, its command-line form, the configs it publishes."""

from __future__ import annotations

import threading

import pytest
import zenoh

from server.cli import _parser
from server.protocol.codec import decode_config
from server.tooling.estimator_mix import EstimatorMix
from server.tooling.fleet_commands import mix_summary
from server.tooling.fleet_sim import FleetSim
from tests.server.ingest.fakes import client_session, embedded_router

BOTH = ("mdsf", "reference_speed")


def test_every_kth_vehicle_by_number_runs_the_named_estimators() -> None:
    mix = EstimatorMix(3, BOTH)
    assert [mix.names_for(n) for n in range(1, 8)] == [(), (), BOTH, (), (), BOTH, ()]
    assert EstimatorMix(1, ("reference_speed",)).names_for(5) == ("reference_speed",)
    with pytest.raises(ValueError, match="every >= 1"):
        EstimatorMix(0, BOTH)
    with pytest.raises(ValueError, match="at least one name"):
        EstimatorMix(2, ())


def test_command_line_form_round_trips_and_refuses_unknown_names() -> None:
    mix = EstimatorMix.parse(" 4 : mdsf , reference_speed ")
    assert mix == EstimatorMix(4, BOTH)
    assert EstimatorMix.parse(str(mix)) == mix
    for bad in ("mdsf", "x:mdsf", "4:", "-1:mdsf"):
        with pytest.raises(ValueError, match="EVERY:NAME"):
            EstimatorMix.parse(bad)
    with pytest.raises(ValueError, match="unknown estimators \\['nope'\\]"):
        EstimatorMix.parse("2:mdsf,nope")


@pytest.mark.parametrize("command", ["demo", "simulate", "loadtest"])
def test_fleet_commands_take_the_rule(command: str) -> None:
    required = ["--vehicles", "3", "--duration", "1"] if command == "loadtest" else []
    args = _parser().parse_args([command, *required, "--estimator-mix", "2:mdsf,reference_speed"])
    assert args.estimator_mix == EstimatorMix(2, BOTH)
    assert _parser().parse_args([command, *required]).estimator_mix is None


def test_unknown_estimator_on_the_command_line_is_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as stop:
        _parser().parse_args(["simulate", "--estimator-mix", "2:nope"])
    assert stop.value.code == 2
    assert "unknown estimators ['nope']" in capsys.readouterr().err


@pytest.mark.zenoh
def test_published_configs_name_the_mixed_vehicles_estimators() -> None:
    """Over a real router: the configs say which vehicles run both estimators, and the demo's
    summary line names those vehicles."""
    got: dict[str, tuple[str, ...]] = {}
    arrived = threading.Event()

    def _on_config(sample: zenoh.Sample) -> None:
        vid, config = decode_config(str(sample.key_expr), sample.payload.to_bytes())
        got[vid] = config.estimators
        if len(got) == 4:
            arrived.set()

    with embedded_router() as (router, _, endpoint), client_session(endpoint) as session:
        sub = router.declare_subscriber("fleet/*/config", _on_config)
        sim = FleetSim(
            session,
            4,
            scenario="hard_braking",
            rate=50.0,
            distinct_runs=1,
            estimator_mix=EstimatorMix(2, BOTH),
        )
        sim.run(duration_s=0.2)
        assert arrived.wait(5.0), got
        sub.undeclare()
    assert got == {"sim-0001": (), "sim-0002": BOTH, "sim-0003": (), "sim-0004": BOTH}
    assert mix_summary(sim) == (
        "sim-0002: mdsf + reference_speed; sim-0004: mdsf + reference_speed; "
        "the others: their kind's defaults"
    )

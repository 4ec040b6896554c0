"""The load generator's fleet by kind (``--mix tractor=0.5,tracked=0.5``): shares parsed and
split into contiguous id ranges, a real server process loaded with crawlers beside tractors
losing nothing, and two runs printed side by side."""

from __future__ import annotations

import argparse

import httpx
import pytest

from server.tooling.loadtest import (
    LoadSpec,
    Target,
    add_arguments,
    assignments,
    format_side_by_side,
    local_server,
    parse_kind_mix,
    run_loadtest,
)


def test_kind_mix_is_parsed_and_normalised() -> None:
    assert parse_kind_mix("tractor=1,tracked=1") == (("tractor", 0.5), ("tracked", 0.5))
    assert parse_kind_mix("tracked=3, steered=1,tractor=0") == (
        ("tracked", 0.75),
        ("steered", 0.25),
    )
    for bad in (
        "tractor=0.5,boat=0.5",
        "tracked=x",
        "tracked=-1",
        "tracked=0",
        "tracked=1,tracked=1",
    ):
        with pytest.raises(ValueError):
            parse_kind_mix(bad)
    p = argparse.ArgumentParser()
    add_arguments(p)
    args = p.parse_args(["--vehicles", "4", "--duration", "1", "--mix", "tractor=1,tracked=1"])
    assert args.mix == (("tractor", 0.5), ("tracked", 0.5)) and not args.beside_tractors


def test_each_kind_gets_its_share_in_one_contiguous_id_range() -> None:
    spec = LoadSpec(
        vehicles=11,
        duration_s=1,
        scenario="mix",
        kind_mix=parse_kind_mix("tractor=0.5,tracked=0.3,steered=0.2"),
    )
    (groups,) = assignments(spec, ["sim-{:05d}"])
    by_kind: dict[str, int] = {}
    first = 1
    for g in groups:
        assert g["first"] == first  # contiguous, in the mix's order
        first += g["count"]
        by_kind[g["kind"]] = by_kind.get(g["kind"], 0) + g["count"]
    assert by_kind == {"tractor": 6, "tracked": 3, "steered": 2}  # 5.5, 3.3, 2.2: remainders
    tractors = [g["scenario"] for g in groups if g["kind"] == "tractor"]
    assert len(tractors) == 5  # spread over the scenarios of --scenario mix
    assert [g["scenario"] for g in groups if g["kind"] != "tractor"] == ["tracked", "steered"]


@pytest.mark.zenoh
@pytest.mark.slow
def test_crawlers_beside_tractors_load_a_server_process_and_lose_nothing() -> None:
    spec = LoadSpec(
        vehicles=4,
        duration_s=3.0,
        warmup_s=1.0,
        publishers=1,
        scenario="figure_eight",
        kind_mix=parse_kind_mix("tractor=0.5,tracked=0.5"),
    )
    with local_server() as server:
        target = Target((server.endpoint,), (server.api,), (server.pid,))
        r = run_loadtest(spec, target, progress=False)
        vehicles = httpx.get(f"{server.api}/api/v1/vehicles", timeout=10).json()["data"]
    estimators = sorted((v["vehicle_id"], v["estimators"][0]) for v in vehicles)
    assert estimators == [
        ("sim-00001", "mdsf"),
        ("sim-00002", "mdsf"),
        ("sim-00003", "tracked"),
        ("sim-00004", "tracked"),
    ]
    assert r["loss_free"] and r["packets_received"] == r["packets_sent"] > 4 * 3 * 20
    assert r["packets_rejected"] == 0 and r["packets_missing"] == 0
    assert r["estimates_stored"] == r["estimates_produced"] > 0
    for stage in ("live", "stored"):
        lat = r["latency"][stage]
        assert lat["rows"] > 0 and 0 < lat["p50_ms"] <= lat["p99_ms"]
    table = format_side_by_side([r, r]).splitlines()
    assert table[0] == "|  | run 1 | run 2 |" and len(table) == 2 + 16
    assert all(0.0 <= load < 1000.0 for load in r["machine_load_avg"])
    assert "| fleet (--mix) | tractor=0.5,tracked=0.5 | tractor=0.5,tracked=0.5 |" in table
    assert "| missing (seq gaps) | 0 (0) | 0 (0) |" in table

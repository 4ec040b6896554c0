"""The ``slipfleet`` command.

Subcommands::

    slipfleet serve    [--config FILE]                   server: REST, dashboard, ingest, 3D view
    slipfleet demo     [--vehicles N] [--scenario NAME]  router + server + SQLite + simulated fleet
    slipfleet simulate --vehicles N --scenario NAME --duration S [--connect ENDPOINT]
    slipfleet replay   PATH [--rate X] [--connect ENDPOINT]
    slipfleet record   PATH --scenario NAME --duration S [--vehicles N]
    slipfleet loadtest --vehicles N --duration S [--scenario mix] [--json PATH] [--connect ...]
    slipfleet bench    {accuracy,storage,series,live,viewer,throughput} [--json PATH]

Settings come from the environment (``SLIPFLEET_…``) and an optional TOML file; flags override
both. Heavy modules are imported inside each subcommand so ``--help`` stays instant.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["main"]

log = logging.getLogger("slipfleet")

BENCHES = ("accuracy", "storage", "series", "live", "viewer", "throughput")


def _settings(args: argparse.Namespace, **overrides: Any) -> Any:
    from server.settings import load_settings

    return load_settings(getattr(args, "config", None), **overrides)


def _cmd_serve(args: argparse.Namespace) -> int:
    from server.app_main import serve

    settings = _settings(args)
    if args.host:
        settings.api.host = args.host
    if args.port is not None:
        settings.api.port = args.port
    serve(settings)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from server.app_main import demo

    settings = _settings(args)
    if args.port is not None:
        settings.api.port = args.port
    if args.data_dir is not None:
        settings.storage.data_dir = args.data_dir
    demo(settings, vehicles=args.vehicles, scenario=args.scenario, duration_s=args.duration)
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from server.app_main import simulate

    settings = _settings(args)
    if args.connect:
        settings.zenoh.connect = [args.connect]
    simulate(
        settings,
        vehicles=args.vehicles,
        scenario=args.scenario,
        duration_s=args.duration,
        rate_scale=args.rate_scale,
    )
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from server.app_main import replay

    settings = _settings(args)
    if args.connect:
        settings.zenoh.connect = [args.connect]
    replay(settings, args.path, rate_scale=args.rate)
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from server.app_main import record

    record(args.path, vehicles=args.vehicles, scenario=args.scenario, duration_s=args.duration)
    return 0


def _cmd_loadtest(args: argparse.Namespace) -> int:
    from server.loadtest import run_from_args

    result = run_from_args(args)
    return 0 if result["loss_free"] else 1


def _cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(f"server.bench.{args.which}")
    module.run(json_path=args.json)
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="slipfleet", description="Per-wheel slip telemetry server.")
    p.add_argument("--config", type=Path, default=None, help="TOML settings file")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("serve", help="run the server")
    s.add_argument("--host", default=None, help="REST/dashboard bind address (default 127.0.0.1)")
    s.add_argument("--port", type=int, default=None)
    s.set_defaults(func=_cmd_serve)

    d = sub.add_parser("demo", help="embedded router + server + SQLite + simulated vehicles")
    d.add_argument("--vehicles", type=int, default=4)
    d.add_argument("--scenario", default="field_work")
    d.add_argument("--duration", type=float, default=0.0, help="seconds; 0 = until Ctrl-C")
    d.add_argument("--port", type=int, default=None)
    d.add_argument("--data-dir", type=Path, default=None)
    d.set_defaults(func=_cmd_demo)

    m = sub.add_parser("simulate", help="publish simulated vehicles over Zenoh")
    m.add_argument("--vehicles", type=int, default=1)
    m.add_argument("--scenario", default="field_work")
    m.add_argument("--duration", type=float, default=60.0, help="seconds")
    m.add_argument("--rate-scale", type=float, default=1.0, help="2 = twice real time")
    m.add_argument("--connect", default=None, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    m.set_defaults(func=_cmd_simulate)

    r = sub.add_parser("replay", help="publish a recorded drive over Zenoh")
    r.add_argument("path", type=Path)
    r.add_argument("--rate", type=float, default=1.0)
    r.add_argument("--connect", default=None)
    r.set_defaults(func=_cmd_replay)

    rec = sub.add_parser("record", help="write a simulated drive as a recording file")
    rec.add_argument("path", type=Path)
    rec.add_argument("--vehicles", type=int, default=1)
    rec.add_argument("--scenario", default="field_work")
    rec.add_argument("--duration", type=float, default=60.0)
    rec.set_defaults(func=_cmd_record)

    lt = sub.add_parser("loadtest", help="simulated fleet against a server process, measured")
    from server.loadtest import add_arguments as _loadtest_arguments

    _loadtest_arguments(lt)
    lt.set_defaults(func=_cmd_loadtest)

    b = sub.add_parser("bench", help="benchmarks that print tables")
    b.add_argument("which", choices=BENCHES)
    b.add_argument("--json", type=Path, default=None, help="also write the numbers as JSON")
    b.set_defaults(func=_cmd_bench)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``slipfleet`` console script."""
    args = _parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())

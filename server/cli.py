"""The ``slipfleet`` command.

Subcommands::

    slipfleet serve    [--config FILE]                   server: REST, dashboard, ingest, 3D view
    slipfleet demo     [--vehicles N] [--scenario NAME]  router + server + SQLite + simulated fleet
    slipfleet simulate --vehicles N --scenario NAME --duration S [--connect ENDPOINT]
    slipfleet replay   PATH [--rate X] [--connect ENDPOINT]
    slipfleet record   PATH --scenario NAME --duration S [--vehicles N]
    slipfleet loadtest --vehicles N --duration S [--scenario mix] [--json PATH] [--connect ...]
    slipfleet bench    NAME [OPTIONS…]      NAME: accuracy storage series live viewer throughput
                                          wheels frontend advance publisher ingest pipeline
                                          writes
    slipfleet token    create --name N --role {viewer,operator,admin} | list | revoke ID
    slipfleet zenoh-router-config [--out FILE]          standalone router config from settings

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

BENCHES = (
    "accuracy",
    "storage",
    "series",
    "live",
    "viewer",
    "throughput",
    "wheels",
    "frontend",
    "advance",
    "publisher",
    "ingest",
    "pipeline",
    "writes",
    "tracked",
)


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
    if settings.api.require_auth:
        log.info(
            "the REST API and live views need access tokens; create the first one with: "
            "slipfleet token create --name <who> --role admin"
        )
    serve(settings)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from server.tooling.fleet_commands import demo

    settings = _settings(args)
    if args.port is not None:
        settings.api.port = args.port
    if args.data_dir is not None:
        settings.storage.data_dir = args.data_dir
    demo(
        settings,
        vehicles=args.vehicles,
        scenario=args.scenario,
        duration_s=args.duration,
        estimator_mix=args.estimator_mix,
    )
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from server.tooling.fleet_commands import simulate

    settings = _settings(args)
    if args.connect:
        settings.zenoh.connect = [args.connect]
    simulate(
        settings,
        vehicles=args.vehicles,
        scenario=args.scenario,
        duration_s=args.duration,
        rate_scale=args.rate_scale,
        estimator_mix=args.estimator_mix,
    )
    return 0


def _cmd_replay(args: argparse.Namespace) -> int:
    from server.tooling.fleet_commands import replay

    settings = _settings(args)
    if args.connect:
        settings.zenoh.connect = [args.connect]
    replay(settings, args.path, rate_scale=args.rate)
    return 0


def _cmd_record(args: argparse.Namespace) -> int:
    from server.tooling.fleet_commands import record

    record(args.path, vehicles=args.vehicles, scenario=args.scenario, duration_s=args.duration)
    return 0


def _cmd_loadtest(args: argparse.Namespace) -> int:
    from server.tooling.loadtest import run_from_args

    result = run_from_args(args)
    return 0 if result["loss_free"] else 1


def _cmd_bench(args: argparse.Namespace) -> int:
    import importlib

    module = importlib.import_module(f"server.tooling.bench.{args.which}")
    return int(module.main(list(args.options)) or 0)


def _cmd_token(args: argparse.Namespace) -> int:
    import time

    from server.storage import open_store
    from server.timeparse import format_ns
    from server.tokens import issue_token

    settings = _settings(args)
    store = open_store(settings.storage)
    try:
        if args.token_command == "create":
            token, record = issue_token(store, args.name, args.role, time.time_ns())
            print(
                f"created token {record.id} ({record.name}, {record.role}). It is shown only "
                "this once; keep it secret:",
                file=sys.stderr,
            )
            print(token)
            return 0
        if args.token_command == "list":
            print(f"{'id':>5}  {'role':<8}  {'created':<20}  {'last used':<20}  status    name")
            for r in store.list_tokens():
                used = format_ns(r.last_used_ns)[:19] + "Z" if r.last_used_ns else "never"
                status = "revoked" if r.revoked else "valid"
                print(
                    f"{r.id:>5}  {r.role:<8}  {format_ns(r.created_ns)[:19] + 'Z':<20}  "
                    f"{used:<20}  {status:<8}  {r.name}"
                )
            return 0
        revoked = store.revoke_token(args.id, time.time_ns())
        if revoked is None:
            print(f"no token with id {args.id}", file=sys.stderr)
            return 1
        print(f"revoked token {revoked.id} ({revoked.name}, {revoked.role})")
        return 0
    finally:
        store.close()


def _cmd_zenoh_router_config(args: argparse.Namespace) -> int:
    import json

    from server.ingest.zenoh_session import router_config_dict

    settings = _settings(args)
    text = json.dumps(router_config_dict(settings.zenoh), indent=2) + "\n"
    if args.out is None:
        sys.stdout.write(text)
    else:
        args.out.write_text(text)
        print(f"wrote {args.out}", file=sys.stderr)
    return 0


def _token_name(text: str) -> str:
    name = text.strip()
    if not name or len(name) > 100 or any(ord(c) < 32 or ord(c) == 127 for c in name):
        raise argparse.ArgumentTypeError("1-100 printable characters")
    return name


def _token_id(text: str) -> int:
    value = int(text)
    if not 1 <= value < 2**63:
        raise argparse.ArgumentTypeError("a token id from `slipfleet token list`")
    return value


def _parser() -> argparse.ArgumentParser:
    from server.tooling.estimator_mix import add_estimator_mix_argument

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
    add_estimator_mix_argument(d, "default: the last vehicle runs mdsf,reference_speed")
    d.set_defaults(func=_cmd_demo)

    m = sub.add_parser("simulate", help="publish simulated vehicles over Zenoh")
    m.add_argument("--vehicles", type=int, default=1)
    m.add_argument("--scenario", default="field_work")
    m.add_argument("--duration", type=float, default=60.0, help="seconds")
    m.add_argument("--rate-scale", type=float, default=1.0, help="2 = twice real time")
    m.add_argument("--connect", default=None, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    add_estimator_mix_argument(m, "default: every vehicle its kind's defaults")
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
    from server.tooling.loadtest import add_arguments as _loadtest_arguments

    _loadtest_arguments(lt)
    lt.set_defaults(func=_cmd_loadtest)

    b = sub.add_parser("bench", help="benchmarks that print tables")
    b.add_argument("which", choices=BENCHES)
    b.add_argument(
        "options",
        nargs=argparse.REMAINDER,
        help="the benchmark's own options, e.g. --json PATH, --seeds 1,2,3 "
        "(slipfleet bench NAME --help lists them)",
    )
    b.set_defaults(func=_cmd_bench)

    t = sub.add_parser("token", help="REST access tokens in the configured store")
    tsub = t.add_subparsers(dest="token_command", required=True)
    tc = tsub.add_parser("create", help="create a token and print it (once)")
    tc.add_argument("--name", required=True, type=_token_name, help="whom or what it is for")
    tc.add_argument("--role", required=True, choices=("viewer", "operator", "admin"))
    tsub.add_parser("list", help="list tokens (never the tokens themselves)")
    tr = tsub.add_parser("revoke", help="revoke a token by id")
    tr.add_argument("id", type=_token_id)
    t.set_defaults(func=_cmd_token)

    z = sub.add_parser(
        "zenoh-router-config",
        help="JSON5 config for a standalone zenohd: vehicle credentials and ACL from settings",
    )
    z.add_argument("--out", type=Path, default=None, help="file to write (default: stdout)")
    z.set_defaults(func=_cmd_zenoh_router_config)
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

"""The ``slipfleet`` command.

Subcommands::

    slipfleet serve    [--config FILE]                   server: REST, dashboard, ingest, 3D view
    slipfleet demo     [--vehicles N] [--scenario NAME]  router + server + SQLite + simulated fleet
    slipfleet simulate --vehicles N --scenario NAME --duration S [--connect ENDPOINT]
    slipfleet replay   PATH [--rate X] [--connect ENDPOINT] [--as ID] [--shift auto|S] [--api URL]
    slipfleet record   PATH --scenario NAME --duration S [--vehicles N]
    slipfleet record   PATH --live [--connect ENDPOINT] [--duration S]
    slipfleet import   PATH --vehicle ID [--format csv|parquet|mcap|rosbag] [--dry-run] [--map FILE]
    slipfleet loadtest --vehicles N --duration S [--scenario mix] [--json PATH] [--connect ...]
    slipfleet bench    NAME [OPTIONS…]      NAME: accuracy storage series live viewer throughput
                                          wheels frontend advance publisher ingest pipeline
                                          writes friction friction_info tracked
    slipfleet token    create --name N --role {viewer,operator,admin} [--expires-in DURATION]
                       | list | revoke ID
    slipfleet zenoh-router-config [--out FILE]          standalone router config from settings

Settings come from the environment (``SLIPFLEET_…``) and an optional TOML file; flags override
both. Heavy modules are imported inside each subcommand so ``--help`` stays instant. A mistake
on the command line, or one the command finds (a port taken, no router, no such recording), is
one line on stderr, never a traceback.
"""

from __future__ import annotations

import argparse
import logging
import os
import socket
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from server.tooling.cli_args import count_arg, positive_arg, seconds_or_zero_arg

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
    "friction",
    "friction_info",
    "tracked",
)


def _settings(args: argparse.Namespace, **overrides: Any) -> Any:
    """The settings of file, environment and ``overrides``; SystemExit with one line naming
    what is wrong (a TOML syntax error, a value of the wrong type, an unreadable variable)."""
    from server.settings import load_settings

    config = getattr(args, "config", None)
    from_env = os.environ.get("SLIPFLEET_CONFIG")
    if config is None and from_env and not Path(from_env).is_file():
        raise SystemExit(
            f"slipfleet {args.command}: SLIPFLEET_CONFIG: no settings file {from_env!r}"
        )
    try:
        return load_settings(config, **overrides)
    except ValueError as exc:  # pydantic's ValidationError, SettingsError, TOMLDecodeError
        what = _settings_error(exc, config or os.environ.get("SLIPFLEET_CONFIG"))
        raise SystemExit(f"slipfleet {args.command}: settings: {what}") from None


def _connected_settings(args: argparse.Namespace) -> Any:
    """The settings (:func:`_settings`), connecting to the router ``--connect`` names when
    given."""
    settings = _settings(args)
    if args.connect:
        settings.zenoh.connect = [args.connect]
    return settings


def _settings_error(exc: ValueError, config: Path | str | None) -> str:
    """One line for a settings error: each invalid field with its value; a TOML error with its
    file; an environment variable that could not be read with the reason."""
    import tomllib

    from pydantic import ValidationError
    from pydantic_settings import SettingsError

    if isinstance(exc, ValidationError):
        return "; ".join(
            f"{'.'.join(map(str, e['loc']))}: {e['msg']} (got {e['input']!r})" for e in exc.errors()
        )
    if isinstance(exc, tomllib.TOMLDecodeError):
        return f"{config}: not TOML: {exc}"
    if isinstance(exc, SettingsError):
        return f"{exc} ({exc.__cause__}; lists and sections from the environment are JSON)"
    return str(exc)


def _config_file(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"no settings file {text!r}")
    return path


def _listen_addresses(settings: Any) -> list[tuple[str, str, int]]:
    """``(what, host, port)`` of every TCP port a server of ``settings`` listens on (port 0,
    any free one, left out)."""
    out = [("REST API and dashboard", settings.api.host, settings.api.port)]
    if settings.viewer.enabled:
        out.append(("3D view", settings.viewer.host, settings.viewer.port))
    if not settings.zenoh.connect:
        for endpoint in settings.zenoh.listen:
            proto, _, address = endpoint.partition("/")
            host, _, port = address.rpartition(":")
            if proto == "tcp" and port.isdigit():
                out.append(("Zenoh router", host.strip("[]"), int(port)))
    return [a for a in out if a[2] != 0]


def _refuse_busy_ports(settings: Any, command: str) -> None:
    """SystemExit with one line when a port ``command`` needs is taken (a server already up)."""
    for what, host, port in _listen_addresses(settings):
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        with socket.socket(family, socket.SOCK_STREAM) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind((host, port))
            except OSError as exc:
                raise SystemExit(
                    f"slipfleet {command}: port {port} on {host} ({what}) is taken "
                    f"({exc.strerror}): is a Slipfleet server or demo already running? Stop "
                    "it, or choose other ports (--port, SLIPFLEET_VIEWER__PORT, "
                    "SLIPFLEET_ZENOH__LISTEN)"
                ) from None


def _refuse_unusable_store(settings: Any, command: str) -> None:
    """SystemExit with one line when the configured store cannot be opened (a data directory
    that cannot be created, PostgreSQL not answering), before any server part starts."""
    from server.storage import open_store
    from server.storage.base import StorageError

    try:
        open_store(settings.storage).close()
    except StorageError as exc:
        raise SystemExit(f"slipfleet {command}: {exc}") from None


def _token_advice(settings: Any) -> str:
    """What ``serve`` says about access tokens: how to make the first, or how many there are."""
    import time

    from server.storage import open_store
    from server.storage.base import StorageError

    try:
        store = open_store(settings.storage)
    except StorageError:
        return "the REST API and live views need access tokens (slipfleet token --help)"
    try:
        now_ns = time.time_ns()
        valid = sum(1 for t in store.list_tokens() if t.valid_at(now_ns))
    finally:
        store.close()
    if valid == 0:
        return (
            "the REST API and live views need access tokens and none exists yet; create the "
            "first one with: slipfleet token create --name <who> --role admin"
        )
    return (
        f"the REST API and live views need access tokens ({valid} valid: slipfleet token list; "
        "more with slipfleet token create)"
    )


def _cmd_serve(args: argparse.Namespace) -> int:
    from server.app_main import serve

    settings = _settings(args)
    if args.host:
        settings.api.host = args.host
    if args.port is not None:
        settings.api.port = args.port
    _refuse_busy_ports(settings, "serve")
    _refuse_unusable_store(settings, "serve")
    if settings.api.require_auth:
        log.info(_token_advice(settings))
    serve(settings)
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from server.tooling.fleet_commands import demo

    settings = _settings(args)
    if args.port is not None:
        settings.api.port = args.port
    if args.data_dir is not None:
        settings.storage.data_dir = args.data_dir
    _refuse_busy_ports(settings, "demo")
    _refuse_unusable_store(settings, "demo")
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

    settings = _connected_settings(args)
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
    from server.tooling.cli_args import read_token
    from server.tooling.recording_commands import ReplayTarget, replay

    settings = _connected_settings(args)
    api = args.api or f"http://{settings.api.host}:{settings.api.port}"
    target = ReplayTarget(
        endpoints=list(settings.zenoh.connect or settings.zenoh.listen),
        api=api.rstrip("/"),
        api_given=args.api is not None,
        token=read_token(args.token_file),
        vehicle_as=args.vehicle_as,
        shift_ns=args.shift,
        rate=args.rate,
    )
    return replay(args.path, target)


def _cmd_record(args: argparse.Namespace) -> int:
    if args.live:
        from server.tooling.recording_commands import record_live

        settings = _connected_settings(args)
        record_live(settings, args.path, args.duration)
        return 0
    from server.tooling.fleet_commands import record

    if args.connect:
        raise SystemExit("slipfleet record: --connect is for --live (a simulated drive needs none)")
    duration_s = 60.0 if args.duration is None else args.duration
    record(args.path, vehicles=args.vehicles, scenario=args.scenario, duration_s=duration_s)
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from server.tooling.importer import ImportRequest, import_command
    from server.tooling.importer_bags import TopicChoice

    request = ImportRequest(
        path=args.path,
        vehicle_id=args.vehicle,
        fmt=args.format,
        dry_run=args.dry_run,
        column_map=args.map,
        topics=TopicChoice(
            imu=args.imu_topic,
            fix=args.fix_topic,
            vel=args.vel_topic,
            wheels=args.wheels_topic,
            wheel_joints=args.wheel_joints,
        ),
        vehicle_config=args.vehicle_config,
        batch=args.batch,
    )
    return import_command(_settings(args), request)


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
            token, record = issue_token(
                store, args.name, args.role, time.time_ns(), args.expires_in
            )
            expires = "never" if record.expires_ns is None else format_ns(record.expires_ns)
            print(
                f"created token {record.id} ({record.name}, {record.role}, expires {expires}). "
                "It is shown only this once; keep it secret:",
                file=sys.stderr,
            )
            print(token)
            return 0
        if args.token_command == "list":
            now_ns = time.time_ns()
            print(f"{'id':>5}  {'role':<8}  {'created':<20}  {'last used':<20}  status    name")
            for r in store.list_tokens():
                used = format_ns(r.last_used_ns)[:19] + "Z" if r.last_used_ns else "never"
                status = "revoked" if r.revoked else "expired" if r.expired(now_ns) else "valid"
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


def _token_lifetime(text: str) -> int:
    from server.tokens import parse_lifetime_ns

    try:
        return parse_lifetime_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _token_id(text: str) -> int:
    value = int(text)
    if not 1 <= value < 2**63:
        raise argparse.ArgumentTypeError("a token id from `slipfleet token list`")
    return value


def _vehicle_id(text: str) -> str:
    from server.protocol.keys import is_valid_vehicle_id

    if not is_valid_vehicle_id(text):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a vehicle id (letters, digits, '_', '.', '-'; at most 64)"
        )
    return text


def _shift(text: str) -> int | None:
    """``auto`` → None (the recording starts now); seconds → nanoseconds."""
    if text == "auto":
        return None
    try:
        seconds = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("'auto' or a number of seconds, e.g. -3600") from None
    if not abs(seconds) < 100 * 365 * 86_400:
        raise argparse.ArgumentTypeError("a shift within a hundred years")
    return round(seconds * 1e9)


def _recording(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        raise argparse.ArgumentTypeError(f"no recording file {text!r}")
    return path


def _add_serve(sub: Any) -> None:
    s = sub.add_parser("serve", help="run the server")
    s.add_argument("--host", default=None, help="REST/dashboard bind address (default 127.0.0.1)")
    s.add_argument("--port", type=int, default=None, help="REST/dashboard port (default 8000)")
    s.set_defaults(func=_cmd_serve)


def _add_demo(sub: Any) -> None:
    from server.tooling.cli_args import add_scenario_argument
    from server.tooling.estimator_mix import add_estimator_mix_argument

    d = sub.add_parser("demo", help="embedded router + server + SQLite + simulated vehicles")
    d.add_argument("--vehicles", type=count_arg, default=4, help="simulated tractors (default 4)")
    add_scenario_argument(d, "mix", mix=True)
    d.add_argument(
        "--duration", type=seconds_or_zero_arg, default=0.0, help="seconds; 0 = until Ctrl-C"
    )
    d.add_argument("--port", type=int, default=None, help="REST/dashboard port (default 8000)")
    d.add_argument(
        "--data-dir", type=Path, default=None, help="where the SQLite file goes (default ./data)"
    )
    add_estimator_mix_argument(d, "default: the last vehicle runs mdsf,reference_speed")
    d.set_defaults(func=_cmd_demo)


def _add_simulate(sub: Any) -> None:
    from server.tooling.cli_args import add_scenario_argument
    from server.tooling.estimator_mix import add_estimator_mix_argument

    m = sub.add_parser("simulate", help="publish simulated vehicles over Zenoh")
    m.add_argument("--vehicles", type=count_arg, default=1, help="simulated vehicles (default 1)")
    add_scenario_argument(m, "field_work")
    m.add_argument("--duration", type=positive_arg, default=60.0, help="seconds (default 60)")
    m.add_argument("--rate-scale", type=positive_arg, default=1.0, help="2 = twice real time")
    m.add_argument("--connect", default=None, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    add_estimator_mix_argument(m, "default: every vehicle its kind's defaults")
    m.set_defaults(func=_cmd_simulate)


def _add_replay(sub: Any) -> None:
    from server.tooling.cli_args import add_token_argument

    r = sub.add_parser(
        "replay",
        help="publish a recorded drive over Zenoh and say what the server made of it",
    )
    r.add_argument("path", type=_recording, help="recording file (slipfleet record)")
    r.add_argument("--rate", type=positive_arg, default=1.0, help="2 = twice real time (default 1)")
    r.add_argument("--connect", default=None, help="router endpoint, e.g. tcp/127.0.0.1:7447")
    r.add_argument(
        "--as",
        dest="vehicle_as",
        type=_vehicle_id,
        default=None,
        metavar="VEHICLE_ID",
        help="publish the recording's one vehicle under this id, e.g. beside the vehicle it "
        "came from (whose packets the server would count as duplicates)",
    )
    r.add_argument(
        "--shift",
        type=_shift,
        default=None,
        metavar="auto|SECONDS",
        help="move the sensor stamps: auto (default) so the recording starts now; SECONDS by "
        "that much (0: as recorded)",
    )
    r.add_argument(
        "--api",
        default=None,
        metavar="URL",
        help="REST API of the server, to read what it accepted (default: from the settings, "
        "http://127.0.0.1:8000; skipped if none answers there)",
    )
    add_token_argument(r)
    r.set_defaults(func=_cmd_replay)


def _add_record(sub: Any) -> None:
    from server.tooling.cli_args import add_scenario_argument

    rec = sub.add_parser(
        "record",
        help="write a simulated drive, or the fleet's live traffic (--live), as a recording",
    )
    rec.add_argument("path", type=Path, help="recording file to write")
    rec.add_argument(
        "--live",
        action="store_true",
        help="record the sensor packets and configs a router delivers, as the server receives "
        "them (docs/protocol.md §8), instead of simulating",
    )
    rec.add_argument(
        "--connect", default=None, help="with --live: router endpoint, e.g. tcp/127.0.0.1:7447"
    )
    rec.add_argument("--vehicles", type=count_arg, default=1, help="simulated vehicles (default 1)")
    add_scenario_argument(rec, "field_work")
    rec.add_argument(
        "--duration",
        type=positive_arg,
        default=None,
        help="seconds (default: 60 simulated; with --live until Ctrl-C)",
    )
    rec.set_defaults(func=_cmd_record)


def _log_path(text: str) -> Path:
    path = Path(text)
    if not path.exists():
        raise argparse.ArgumentTypeError(f"no log file or bag directory {text!r}")
    return path


def _joints(text: str) -> tuple[str, str]:
    left, sep, right = text.partition(",")
    if not sep or not left or not right or "," in right:
        raise argparse.ArgumentTypeError("LEFT,RIGHT: the two wheel joints' names")
    return left, right


def _batch(text: str) -> int:
    value = int(positive_arg(text))
    if value != float(text) or value > 10_000:
        raise argparse.ArgumentTypeError("a whole number of samples, 1-10000")
    return value


def _add_import(sub: Any) -> None:
    i = sub.add_parser(
        "import",
        help="read a log of another system (CSV, Parquet, MCAP, ROS bag) into the store, "
        "through the estimators, with its original timestamps (docs/import.md)",
    )
    i.add_argument("path", type=_log_path, help="log file, or a ROS 2 bag's directory")
    i.add_argument("--vehicle", required=True, type=_vehicle_id, help="vehicle id to store under")
    i.add_argument(
        "--format",
        choices=("csv", "parquet", "mcap", "rosbag"),
        default=None,
        help="default: by the name (.csv, .parquet, .mcap, .bag or a directory)",
    )
    i.add_argument("--dry-run", action="store_true", help="read and check, print what it holds")
    i.add_argument(
        "--map", type=Path, default=None, metavar="FILE", help="CSV/Parquet column map (TOML/JSON)"
    )
    i.add_argument(
        "--vehicle-config",
        type=Path,
        default=None,
        metavar="FILE",
        help="the vehicle's config (JSON, as REST takes it); default: its stored one, else "
        "the rear-drive defaults",
    )
    i.add_argument(
        "--batch", type=_batch, default=10, help="IMU and wheel samples per packet (default 10)"
    )
    for role, what in (
        ("imu", "sensor_msgs/Imu"),
        ("fix", "sensor_msgs/NavSatFix"),
        ("vel", "GNSS velocity (TwistWithCovarianceStamped or TwistStamped, ENU)"),
        ("wheels", "sensor_msgs/JointState of the wheels"),
    ):
        i.add_argument(
            f"--{role}-topic",
            default=None,
            metavar="TOPIC",
            help=f"MCAP/bag topic of {what} (default: the only one)",
        )
    i.add_argument(
        "--wheel-joints",
        type=_joints,
        default=None,
        metavar="LEFT,RIGHT",
        help="JointState names of the driven wheels (default: the joints named left and right)",
    )
    i.set_defaults(func=_cmd_import)


def _add_token(sub: Any) -> None:
    t = sub.add_parser("token", help="REST access tokens in the configured store")
    tsub = t.add_subparsers(dest="token_command", required=True)
    tc = tsub.add_parser("create", help="create a token and print it (once)")
    tc.add_argument("--name", required=True, type=_token_name, help="whom or what it is for")
    tc.add_argument(
        "--role",
        required=True,
        choices=("viewer", "operator", "admin"),
        help="viewer: read; operator: also register and configure vehicles; admin: everything",
    )
    tc.add_argument(
        "--expires-in",
        type=_token_lifetime,
        default=None,
        metavar="DURATION",
        help="lifetime from now: 90s, 30m, 12h, 7d or 2w (at most ten years); default: never",
    )
    tsub.add_parser("list", help="list tokens (never the tokens themselves)")
    tr = tsub.add_parser("revoke", help="revoke a token by id")
    tr.add_argument("id", type=_token_id, help="the token's id (slipfleet token list)")
    t.set_defaults(func=_cmd_token)


def _parser() -> argparse.ArgumentParser:
    from server.tooling.cli_args import OneLineParser
    from server.tooling.loadtest import add_arguments as _loadtest_arguments

    p = OneLineParser(prog="slipfleet", description="Per-wheel slip telemetry server.")
    p.add_argument("--config", type=_config_file, default=None, help="TOML settings file")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = p.add_subparsers(dest="command", required=True)
    _add_serve(sub)
    _add_demo(sub)
    _add_simulate(sub)
    _add_replay(sub)
    _add_record(sub)
    _add_import(sub)

    lt = sub.add_parser("loadtest", help="simulated fleet against a server process, measured")
    _loadtest_arguments(lt)
    lt.set_defaults(func=_cmd_loadtest)

    b = sub.add_parser("bench", help="benchmarks that print tables")
    b.add_argument("which", choices=BENCHES, help="which benchmark")
    b.add_argument(
        "options",
        nargs=argparse.REMAINDER,
        help="the benchmark's own options, e.g. --json PATH, --seeds 1,2,3 "
        "(slipfleet bench NAME --help lists them)",
    )
    b.set_defaults(func=_cmd_bench)
    _add_token(sub)

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
    logging.getLogger("httpx").setLevel(logging.WARNING)  # not a line per request of a tool
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())

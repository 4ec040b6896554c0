"""The one place every setting lives.

Settings come, in rising priority, from defaults here, a TOML file (``SLIPFLEET_CONFIG`` or the
``config_file`` argument), and environment variables prefixed ``SLIPFLEET_`` with ``__`` between
sections, e.g. ``SLIPFLEET_STORAGE__URL=postgresql://…``. Build with :func:`load_settings` in the
app factory or CLI, never at import.
"""

from __future__ import annotations

import ipaddress
import os
from enum import StrEnum
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, SecretStr, field_validator, model_validator
from pydantic_settings import (
    BaseSettings,
    PydanticBaseSettingsSource,
    SettingsConfigDict,
    TomlConfigSettingsSource,
)

__all__ = [
    "AlertSettings",
    "ApiSettings",
    "IngestSettings",
    "Settings",
    "StorageSettings",
    "UnknownVehiclePolicy",
    "ViewerSettings",
    "ZenohSettings",
    "load_settings",
]


class UnknownVehiclePolicy(StrEnum):
    """What the server does with packets from a vehicle it has no config for."""

    AUTO_REGISTER = "auto"  # register with default config on first packet
    REJECT = "reject"  # count as rejected (reason: unknown_vehicle)


class ZenohSettings(BaseModel):
    """Zenoh session.

    With ``connect`` empty the server starts an embedded router listening on ``listen``.
    """

    connect: list[str] = Field(
        default_factory=list, description="router endpoints, e.g. tcp/10.0.0.2:7447"
    )
    listen: list[str] = Field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    key_prefix: str = Field("fleet", description="root of every key expression")
    vehicle_filter: str = Field(
        "*", description="key-expression chunk selecting this server's vehicles"
    )
    username: str | None = Field(
        None,
        description=(
            "client mode: the name this server presents to a secured router; embedded router: "
            "the credentials-file entry that is the server itself (never given vehicle rules)"
        ),
    )
    password: SecretStr | None = Field(
        None, description="client mode: the password going with zenoh.username"
    )
    password_file: Path | None = Field(
        None,
        description="a file holding zenoh.password (a container secret), read when it is unset",
    )
    credentials_file: Path | None = Field(
        None,
        description=(
            "embedded router: file of 'user:password' lines, one per vehicle (user = vehicle "
            "id); set, every session must authenticate with one of them"
        ),
    )
    acl: bool = Field(
        True,
        description=(
            "embedded router with credentials_file: each vehicle may publish only under "
            "<key_prefix>/<its id>/**, everything else is denied"
        ),
    )
    trusted_users: list[str] = Field(
        default_factory=list,
        description=(
            "router with credentials_file and acl: entries of the file that are not vehicles "
            "but server replicas or linked routers, allowed to subscribe to and publish under "
            "<key_prefix>/**"
        ),
    )
    allow_anonymous: bool = Field(
        False,
        description=(
            "let an embedded router listen beyond loopback without credentials_file "
            "(anyone reaching the port may publish as any vehicle)"
        ),
    )
    channel_capacity: int = Field(65536, ge=16, description="bounded FIFO per subscriber, samples")


class StorageSettings(BaseModel):
    """Where estimates are kept: SQLite file in ``data_dir`` unless ``url`` names PostgreSQL."""

    url: SecretStr | None = Field(None, description="postgresql://user:pass@host/db; None = SQLite")
    data_dir: Path = Path("./data")
    sqlite_file: str = "slipfleet.sqlite"
    batch_max_rows: int = Field(5000, ge=1, description="rows per transaction at most")
    commit_interval_s: float = Field(
        0.02,
        gt=0,
        le=1.0,
        description=(
            "writer transactions start at most this often; rows arriving after a longer pause "
            "are committed at once, others wait up to this long (stored rows lag sensor time "
            "by up to this much more; longer intervals mean fewer, larger transactions)"
        ),
    )
    backlog_max_rows: int = Field(2_000_000, ge=1000, description="in-memory backlog bound")
    retention_days: float = Field(0, ge=0, description="delete estimates older than this; 0 = keep")
    store_raw_packets: bool = False
    raw_packets_queue_max_bytes: int = Field(
        64 * 2**20,
        ge=2**20,
        le=2**34,
        description=(
            "payload bytes of raw packets waiting for the writer (store_raw_packets); packets "
            "beyond are dropped and counted, never held in memory"
        ),
    )
    raw_packets_max_bytes: int = Field(
        2**30,
        ge=2**20,
        le=2**44,
        description=(
            "payload bytes of raw packets kept in the database (store_raw_packets); beyond, no "
            "more are stored and each is counted (raw_packets_over_budget) until retention "
            "deletes old ones"
        ),
    )


class IngestSettings(BaseModel):
    """Per-vehicle reorder buffer and registration policy."""

    lateness_ms: int = Field(150, ge=0, le=60_000, description="reorder window by sensor timestamp")
    stream_watermarks: bool = Field(
        True,
        description=(
            "release a vehicle's data as soon as each of its streams has arrived up to it "
            "(consecutive sequence numbers) instead of always waiting lateness_ms; the window "
            "still bounds the wait for a stream that is late or has stopped"
        ),
    )
    unknown_vehicle: UnknownVehiclePolicy = UnknownVehiclePolicy.AUTO_REGISTER
    process_interval_ms: int = Field(
        20,
        ge=1,
        description=(
            "how often the pipeline releases reorder buffers (estimator calls: "
            "estimate_interval_ms)"
        ),
    )
    gather_ms: int = Field(
        5,
        ge=0,
        le=50,
        description=(
            "the ingest thread waits this long after a burst's first packet for more to decode "
            "together (fewer, larger bursts cost less CPU per packet); 0 = decode what is there"
        ),
    )
    max_payload_bytes: int = Field(
        256 * 1024,
        ge=1024,
        description=(
            "larger sensor payloads are refused (rejected_oversize) from their length, before "
            "they are copied out of Zenoh, and never stored raw"
        ),
    )
    queue_max_bytes: int = Field(
        64 * 1024 * 1024,
        ge=1024 * 1024,
        description=(
            "undecoded payload bytes waiting for the pipeline, all vehicles together; beyond "
            "it the ingest thread waits (backpressure to Zenoh), as for the packet bound"
        ),
    )
    vehicle_max_bytes_per_s: int = Field(
        1024 * 1024,
        ge=0,
        description=(
            "payload bytes per second one vehicle may send (a token bucket of "
            "vehicle_burst_bytes); packets beyond it are refused as rejected_over_rate and "
            "not stored raw; 0 = no limit. A vehicle sends some kB/s"
        ),
    )
    vehicle_burst_bytes: int = Field(
        16 * 1024 * 1024,
        ge=0,
        description=(
            "the byte-rate bucket's size: what a vehicle may send at once above its rate "
            "(a backlog forwarded after a connectivity outage)"
        ),
    )
    max_vehicles: int = Field(
        20_000,
        ge=1,
        description=(
            "no vehicle registers itself (by its first packet, or by publishing its config) "
            "once this many are running; packets are refused as rejected_registration_cap"
        ),
    )
    max_registrations_per_min: int = Field(
        600,
        ge=1,
        description=(
            "unknown_vehicle = auto registers at most this many vehicles a minute by their "
            "first packet (a storm of new ids is refused as rejected_registration_cap, the "
            "ids are not kept); vehicles publishing their config are not held to it"
        ),
    )
    max_future_s: float = Field(
        600.0,
        gt=0,
        description=(
            "packets stamped further ahead of the server's wall clock are refused (clock_skew); "
            "a GNSS-disciplined clock is never minutes ahead, a time-zone bug is >= 30 min"
        ),
    )
    max_past_s: float = Field(
        7 * 86_400.0,
        gt=0,
        description=(
            "packets stamped further behind the wall clock are refused (clock_skew); a week "
            "covers a vehicle forwarding data it buffered through a long connectivity outage"
        ),
    )
    clock_jump_s: float = Field(
        10.0,
        gt=0,
        le=3_600,
        description=(
            "sensor-time jump within a vehicle's stream, beyond what the wall time explains, "
            "refused as clock_jump until confirmed (see reanchor_after_packets); also the "
            "longest time one packet's samples may span"
        ),
    )
    reanchor_after_packets: int = Field(
        5, ge=2, le=1000, description="consistent clock-jump packets in a row that re-anchor"
    )
    estimate_interval_ms: int = Field(
        50,
        ge=1,
        le=1_000,
        description=(
            "the estimators are called at most this often, for every vehicle with a tick due "
            "(a call has a fixed cost: fewer, larger calls hold more vehicles); live values lag "
            "by up to this much more"
        ),
    )
    workers: int = Field(
        0,
        ge=0,
        le=64,
        description=(
            "worker processes that decode, reorder and estimate, each for its share of the "
            "vehicles (one interpreter lock each: more cores for one server); 0 = all of it "
            "in the server process"
        ),
    )
    gc_gen0: int = Field(
        50_000,
        ge=0,
        description=(
            "net allocations between the garbage collector's young-generation passes in the "
            "server and worker processes, after start-up objects are frozen out of its sight "
            "(server.gc_policy); 0 = the interpreter's default (700, every pass walks more)"
        ),
    )
    advance_step_ms: int = Field(
        100,
        ge=1,
        le=5_000,
        description=(
            "a vehicle's estimators advance each time its released sensor time crosses a "
            "multiple of this (quiet tails and shutdown advance fully); with the MDSF tick "
            "(100 ms) every tick is computed as soon as it is due; longer steps mean fewer "
            "calls and live values that lag by up to this much more"
        ),
    )


class ApiSettings(BaseModel):
    """REST API and dashboard."""

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    cors_origins: list[str] = Field(default_factory=list)
    require_auth: bool = Field(
        True,
        description=(
            "every /api/v1 route except /health needs a bearer token with the route's role "
            "(viewer < operator < admin); off only for the loopback demo and tests"
        ),
    )
    heavy_per_token: int = Field(
        2,
        ge=1,
        le=64,
        description=(
            "reports, slip maps and series exports one caller (token) may run at once; "
            "more are answered 429 with Retry-After"
        ),
    )
    heavy_per_route: int = Field(
        4,
        ge=1,
        le=64,
        description=(
            "requests of one such route running at once, all callers together (each holds a "
            "worker thread of the 40 the API shares); more are answered 429 with Retry-After"
        ),
    )
    retry_after_s: int = Field(1, ge=1, le=3600, description="Retry-After of a 429 answer")
    map_tile_url: str | None = Field(
        None,
        description=(
            "dashboard basemap: an XYZ tile template such as "
            "https://tile.example.org/{z}/{x}/{y}.png (Web Mercator, 256 px tiles); none (the "
            "default) draws the maps on latitude/longitude axes and fetches nothing external"
        ),
    )

    report_max_vehicles: int = Field(
        20_000,
        ge=1,
        description=(
            "a fleet report over more vehicles answers 413 at once (before reading anything); "
            "ask /vehicles/{id}/report for each instead"
        ),
    )
    report_time_budget_s: float = Field(
        30.0,
        gt=0,
        le=3600,
        description=(
            "time a fleet report may work, s: past it the report stops between two vehicles "
            "and answers 413 (narrow start..end); one vehicle's report is never cut"
        ),
    )

    @field_validator("map_tile_url")
    @classmethod
    def _tile_template(cls, v: str | None) -> str | None:
        if v is not None and not all(k in v for k in ("{z}", "{x}", "{y}")):
            raise ValueError("map_tile_url must hold {z}, {x} and {y}")
        if v is not None and not v.startswith(("https://", "http://")):
            raise ValueError("map_tile_url must be an http(s) URL")
        return v


class ViewerSettings(BaseModel):
    """viser 3D fleet view.

    viser has no authentication: anyone reaching its port sees every vehicle's id and pose.
    So it binds loopback only (reach it through an SSH tunnel or an authenticating reverse
    proxy), and a non-loopback ``host`` is refused unless ``allow_remote`` says so.
    """

    enabled: bool = True
    host: str = Field(
        "127.0.0.1", description="bind address; loopback unless allow_remote (no tokens here)"
    )
    port: int = Field(8080, ge=0, le=65535)
    update_hz: float = Field(5.0, gt=0, le=60)
    allow_remote: bool = Field(
        False,
        description=(
            "let the 3D view bind a non-loopback host: it has no authentication, so everyone "
            "reaching the port sees every vehicle's id and position"
        ),
    )

    @model_validator(mode="after")
    def _loopback_unless_allowed(self) -> ViewerSettings:
        if self.enabled and not self.allow_remote and not _is_loopback_host(self.host):
            raise ValueError(
                f"viewer.host {self.host!r} is not a loopback address and the 3D view has no "
                "authentication (anyone reaching it sees every vehicle): keep 127.0.0.1 and "
                "tunnel or proxy to it, or set viewer.allow_remote = true to accept that"
            )
        return self


def _is_loopback_host(host: str) -> bool:
    """True for ``localhost`` and loopback IP addresses (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class AlertRuleLimit(BaseModel):
    """A server's own limit or hold time for one of a spec's alert rules."""

    model_config = ConfigDict(extra="forbid")

    above: float | None = Field(None, allow_inf_nan=False, description="alert above this")
    below: float | None = Field(None, allow_inf_nan=False, description="alert below this")
    hold_s: float | None = Field(None, ge=0, le=86_400, description="held this long (s)")


class AlertSettings(BaseModel):
    """Alert rules declared by the estimators' specs, set otherwise for this server."""

    model_config = ConfigDict(extra="forbid")

    rule_limits: dict[str, AlertRuleLimit] = Field(
        default_factory=dict,
        description=(
            "per '<estimator>:<rule>' (e.g. 'friction:low_mu'): above, below and hold_s in place "
            "of the spec's defaults"
        ),
    )

    @field_validator("rule_limits")
    @classmethod
    def _rule_keys(cls, v: dict[str, AlertRuleLimit]) -> dict[str, AlertRuleLimit]:
        for key in v:
            if key.count(":") != 1 or not all(key.split(":")):
                raise ValueError(f"rule_limits key {key!r}: write it '<estimator>:<rule>'")
        return v

    def engine_limits(self) -> dict[str, dict[str, float]]:
        """The limits as :class:`server.analytics.alerts.AlertEngine` takes them."""
        return {k: v.model_dump(exclude_none=True) for k, v in self.rule_limits.items()}


class Settings(BaseSettings):
    """All of the server's settings."""

    model_config = SettingsConfigDict(
        env_prefix="SLIPFLEET_",
        env_nested_delimiter="__",
        extra="forbid",
    )

    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    storage: StorageSettings = Field(default_factory=StorageSettings)
    ingest: IngestSettings = Field(default_factory=IngestSettings)
    api: ApiSettings = Field(default_factory=ApiSettings)
    viewer: ViewerSettings = Field(default_factory=ViewerSettings)
    alerts: AlertSettings = Field(default_factory=AlertSettings)

    @field_validator("api")
    @classmethod
    def _no_wildcard_cors(cls, v: ApiSettings) -> ApiSettings:
        if "*" in v.cors_origins:
            raise ValueError("CORS '*' is refused; list the dashboard origins explicitly")
        return v

    @classmethod
    def settings_customise_sources(
        cls,
        settings_cls: type[BaseSettings],
        init_settings: PydanticBaseSettingsSource,
        env_settings: PydanticBaseSettingsSource,
        dotenv_settings: PydanticBaseSettingsSource,
        file_secret_settings: PydanticBaseSettingsSource,
    ) -> tuple[PydanticBaseSettingsSource, ...]:
        sources: list[PydanticBaseSettingsSource] = [init_settings, env_settings]
        toml_path = settings_cls.model_config.get("toml_file") or os.environ.get("SLIPFLEET_CONFIG")
        if toml_path:
            sources.append(TomlConfigSettingsSource(settings_cls, toml_file=Path(str(toml_path))))
        return tuple(sources)


def load_settings(config_file: Path | None = None, **overrides: Any) -> Settings:
    """Build settings: explicit ``overrides`` beat the environment, which beats the TOML file
    (``config_file``, else ``$SLIPFLEET_CONFIG``), which beats the defaults."""
    if config_file is None:
        return Settings(**overrides)

    class _FromFile(Settings):
        model_config = SettingsConfigDict(**{**Settings.model_config, "toml_file": config_file})

    return _FromFile(**overrides)

"""PostgreSQL administration helpers for tests, benchmarks and tooling (not used by the server).

Each test gets its own database (``create_database`` / ``drop_database``); the outage test makes
one database refuse connections (``set_connections_allowed``), which works on any server where
the user owns the database, without stopping the server.
"""

from __future__ import annotations

from urllib.parse import urlsplit, urlunsplit

import psycopg
from psycopg import sql

__all__ = ["create_database", "database_url", "drop_database", "set_connections_allowed"]


def database_url(url: str, dbname: str) -> str:
    """``url`` with its database name replaced by ``dbname``."""
    parts = urlsplit(url)
    return urlunsplit(parts._replace(path="/" + dbname))


def create_database(admin_url: str, dbname: str) -> str:
    """Create an empty database; return its URL."""
    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(dbname)))
    return database_url(admin_url, dbname)


def drop_database(admin_url: str, dbname: str) -> None:
    """Drop a database, disconnecting its sessions."""
    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(
            sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(dbname))
        )


def set_connections_allowed(admin_url: str, dbname: str, allowed: bool) -> None:
    """Let a database accept connections again, or refuse new ones and end the current ones."""
    with psycopg.connect(admin_url, autocommit=True) as conn:
        conn.execute(
            sql.SQL("ALTER DATABASE {} ALLOW_CONNECTIONS {}").format(
                sql.Identifier(dbname), sql.SQL("true" if allowed else "false")
            )
        )
        if not allowed:
            conn.execute(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity "
                "WHERE datname = %s AND pid <> pg_backend_pid()",
                (dbname,),
            )

"""Small helpers shared by tests."""

from __future__ import annotations

from server.ports import free_port

__all__ = ["free_port"]

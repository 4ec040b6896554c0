"""``/dashboard``: what the dashboard needs of the server's settings (its basemap).

The page reads this once. ``map_tile_url`` is the ``api.map_tile_url`` setting: null (the
default) means no basemap, so the page fetches nothing beyond this server.
"""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from server.api.deps import SettingsDep

__all__ = ["DashboardConfigPublic", "router"]

router = APIRouter(prefix="/dashboard", tags=["dashboard"])


class DashboardConfigPublic(BaseModel):
    """The settings the dashboard draws with."""

    map_tile_url: str | None = Field(
        description="XYZ tile template ({z}/{x}/{y}, Web Mercator) of the maps' basemap; null: "
        "no basemap, latitude/longitude axes only"
    )


@router.get(
    "",
    response_model=DashboardConfigPublic,
    summary="The dashboard's settings: the basemap's tile URL template, if any",
)
def get_dashboard_config(settings: SettingsDep) -> DashboardConfigPublic:
    return DashboardConfigPublic(map_tile_url=settings.api.map_tile_url)

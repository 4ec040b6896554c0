"""viser 3D fleet view: pure scene maps (`scene`, `colors`) and the server (`fleet_view`)."""

from server.live.viewer.colors import SLIP_COLOR_NONE, SLIP_COLOR_STOPS, slip_rgb
from server.live.viewer.fleet_view import FleetViewer
from server.live.viewer.scene import FleetFrame, attitude_from_wxyz, fleet_frame, wxyz_from_attitude

__all__ = [
    "SLIP_COLOR_NONE",
    "SLIP_COLOR_STOPS",
    "FleetFrame",
    "FleetViewer",
    "attitude_from_wxyz",
    "fleet_frame",
    "slip_rgb",
    "wxyz_from_attitude",
]

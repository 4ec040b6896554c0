"""REST API: the app factory, its dependencies, models and error mapping."""

from server.api.app import API_PREFIX, API_ROUTERS, create_app
from server.api.deps import ApiLimits, ApiRuntime, NoVehicleEvents, VehicleEvents

__all__ = [
    "API_PREFIX",
    "API_ROUTERS",
    "ApiLimits",
    "ApiRuntime",
    "NoVehicleEvents",
    "VehicleEvents",
    "create_app",
]

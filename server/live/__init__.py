"""Live views: the hub of latest estimates and sliding windows (``hub``) and the viser 3D fleet
view that reads it (``viewer``). The dashboard's WebSockets (``server.api.routes.live``) read
the same hub."""

"""Frame update cost of the 3D fleet view: batched meshes vs one handle per vehicle part.

Run ``python -m server.tooling.bench.viewer [--vehicles 1000] [--frames 30]``.

Both modes start a real viser server on a free 127.0.0.1 port and draw the same fleet (the
synthetic fleet of :mod:`server.tooling.bench.live`, fed into a :class:`~server.live.hub.LiveHub`),
advancing sensor time by 0.2 s per frame (5 Hz):

* ``batched`` — :meth:`server.live.viewer.fleet_view.FleetViewer.update`: read the hub, map rows to
  poses and colours (:func:`server.live.viewer.scene.fleet_frame`), assign six arrays to the two
  batched meshes inside one ``server.atomic()``.
* ``per-vehicle`` — the same frame mapping, then for each vehicle a body box and two wheel meshes
  (``/fleet/<id>/body``, ``/fleet/<id>/wheel_left``, ``/fleet/<id>/wheel_right``) whose
  ``position``, ``wxyz`` and ``color`` are assigned one by one (also inside ``atomic()``).

The table gives per-frame wall time (p50, p99) and the ratio per-vehicle / batched. A frame must
fit well inside the 200 ms of a 5 Hz update.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Sequence
from typing import Any

import viser

from estimator.config import VehicleGeometry
from estimator.mdsf_spec import MDSF_SPEC
from estimator.types import EstimateBatch
from server.live.hub import LiveHub
from server.live.viewer.fleet_view import FleetViewer
from server.live.viewer.scene import BODY_SIZE_M, FleetFrame, cylinder_mesh_x, fleet_frame
from server.settings import ViewerSettings
from server.tooling.bench import percentile
from server.tooling.bench.live import SyntheticFleet
from server.tooling.ports import free_port as _free_port

__all__ = ["main"]

_T0 = 1_700_000_000 * 1_000_000_000
_STEP_NS = 200_000_000


def bench_batched(n: int, frames: int) -> list[float]:
    fleet = SyntheticFleet(n, seed=2)
    hub = LiveHub(initial_slots=n)
    viewer = FleetViewer(hub, ViewerSettings(host="127.0.0.1", port=_free_port()))
    viewer.open()
    times = []
    try:
        for k in range(frames + 1):
            hub.on_estimates(EstimateBatch.of(fleet.rows_at(_T0 + k * _STEP_NS), MDSF_SPEC))
            t0 = time.perf_counter()
            viewer.update()
            if k:  # the first frame builds the meshes
                times.append(time.perf_counter() - t0)
    finally:
        viewer.stop()
    return times


def _add_handles(
    server: viser.ViserServer,
    ids: Sequence[str],
    f: FleetFrame,
    wheel_mesh: tuple[Any, Any],
    bodies: list[viser.BoxHandle],
    wheels: list[viser.MeshHandle],
) -> None:
    """A body box and two wheel meshes per vehicle, one handle at a time (the former way)."""
    wv, wf = wheel_mesh
    for i, vid in enumerate(ids):
        bodies.append(
            server.scene.add_box(
                f"/fleet/{vid}/body",
                dimensions=BODY_SIZE_M,
                color=f.body_rgb[i],
                position=f.body_position_m[i],
                wxyz=f.body_wxyz[i],
            )
        )
        for side, j in (("left", 2 * i), ("right", 2 * i + 1)):
            wheels.append(
                server.scene.add_mesh_simple(
                    f"/fleet/{vid}/wheel_{side}",
                    vertices=wv,
                    faces=wf,
                    color=f.wheel_rgb[j],
                    position=f.wheel_position_m[j],
                    wxyz=f.wheel_wxyz[j],
                )
            )


def _place(handles: Sequence[Any], position_m: Any, wxyz: Any, rgb: Any) -> None:
    """Handle ``i``'s position, orientation and colour set from row ``i`` of each array."""
    for i, h in enumerate(handles):
        h.position = position_m[i]
        h.wxyz = wxyz[i]
        h.color = (int(rgb[i, 0]), int(rgb[i, 1]), int(rgb[i, 2]))


def _move_handles(
    f: FleetFrame, bodies: list[viser.BoxHandle], wheels: list[viser.MeshHandle]
) -> None:
    """Each handle's position, orientation and colour set from the frame ``f``."""
    _place(bodies, f.body_position_m, f.body_wxyz, f.body_rgb)
    _place(wheels, f.wheel_position_m, f.wheel_wxyz, f.wheel_rgb)


def bench_per_vehicle(n: int, frames: int) -> list[float]:
    """Seconds per frame with a handle per body and wheel, added once and then moved."""
    fleet = SyntheticFleet(n, seed=2)
    hub = LiveHub(initial_slots=n)
    server = viser.ViserServer(host="127.0.0.1", port=_free_port(), verbose=False)
    g = VehicleGeometry()
    wheel_mesh = cylinder_mesh_x(g.wheel_radius_left_m, 0.45)
    bodies: list[viser.BoxHandle] = []
    wheels: list[viser.MeshHandle] = []
    times = []
    try:
        for k in range(frames + 1):
            hub.on_estimates(EstimateBatch.of(fleet.rows_at(_T0 + k * _STEP_NS), MDSF_SPEC))
            t0 = time.perf_counter()
            spec = hub.specs()[0]
            ids, rows, arrivals = hub.latest_all(spec.name)
            f = fleet_frame(ids, rows, spec, g, hub.status_of_rows(rows["stamp_ns"], arrivals))
            with server.atomic():
                if not bodies:
                    _add_handles(server, ids, f, wheel_mesh, bodies, wheels)
                else:
                    _move_handles(f, bodies, wheels)
            if k:
                times.append(time.perf_counter() - t0)
    finally:
        server.stop()
    return times


def main(argv: Sequence[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--vehicles", type=int, default=1000)
    p.add_argument("--frames", type=int, default=30)
    args = p.parse_args(argv)
    batched = bench_batched(args.vehicles, args.frames)
    per_vehicle = bench_per_vehicle(args.vehicles, args.frames)
    print(f"\n3D fleet view, frame update cost, {args.vehicles} vehicles, {args.frames} frames\n")
    print(f"{'mode':<14}{'handles':>9}{'p50 ms':>9}{'p99 ms':>9}{'mean ms':>9}")
    for name, vals, handles in (
        ("batched", batched, 2),
        ("per-vehicle", per_vehicle, 3 * args.vehicles),
    ):
        print(
            f"{name:<14}{handles:>9}{statistics.median(vals) * 1e3:>9.2f}"
            f"{percentile(vals, 99) * 1e3:>9.2f}{statistics.mean(vals) * 1e3:>9.2f}"
        )
    ratio = statistics.median(per_vehicle) / statistics.median(batched)
    print(f"\nper-vehicle / batched (p50): {ratio:.1f}x")


if __name__ == "__main__":
    main()

"""A revision's estimator package beside this tree's: imports renamed, values rebuilt."""

from __future__ import annotations

import dataclasses
import importlib
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from estimator.types import GnssFix, ImuBatch
from server.tooling.bench import field_work_sources
from server.tooling.bench.renamed import _rewrite, renamed_estimator, to_package


def _leaks(package: str) -> list[str]:
    """Names in ``package``'s modules bound to this tree's ``estimator`` modules or types."""
    out = []
    for name, module in list(sys.modules.items()):
        if name != package and not name.startswith(package + "."):
            continue
        for attr, value in vars(module).items():
            home = value.__name__ if isinstance(value, types.ModuleType) else None
            if isinstance(value, type) or callable(value):
                home = getattr(value, "__module__", None)
            if home is not None and home.partition(".")[0] == "estimator":
                out.append(f"{name}.{attr} -> {home}")
    return out


def test_head_estimators_load_under_their_own_name_and_leave_no_trace() -> None:
    with renamed_estimator("HEAD") as package:
        for estimator in ("mdsf", "tracked", "friction"):
            importlib.import_module(f"{package}.{estimator}")
        root = Path(sys.modules[package].__file__ or "").parent
        assert root.name == package and not root.is_relative_to(Path(__file__).parents[4])
        assert _leaks(package) == []
    assert not [m for m in sys.modules if m.startswith(package)]
    assert str(root.parent) not in sys.path


def test_measurements_and_configs_rebuilt_as_the_renamed_package_types() -> None:
    config, stream = field_work_sources(3.0, 1)[0]
    imu = next(m for _, m in stream if isinstance(m, ImuBatch))
    with renamed_estimator("HEAD") as package:
        got_config, got_imu, got_fix = to_package((config, imu, GnssFix.RTK_FIXED), package)
        assert type(got_config).__module__ == f"{package}.config"
        assert type(got_imu).__module__ == f"{package}.types"
        assert type(got_fix).__name__ == "GnssFix" and got_fix.value == GnssFix.RTK_FIXED.value
        for f in dataclasses.fields(imu):
            a, b = getattr(imu, f.name), getattr(got_imu, f.name)
            if isinstance(a, np.ndarray):
                assert b is not a and a.tobytes() == b.tobytes()
            else:
                assert a == b
        assert got_config.geometry.track_width_m == config.geometry.track_width_m

        @dataclasses.dataclass
        class Unknown:
            x: int

        Unknown.__module__ = "estimator.not_there"
        with pytest.raises(ValueError, match=r"has no estimator\.not_there"):
            to_package(Unknown(1), package)


def test_imports_that_would_still_reach_this_tree_are_refused(tmp_path: Path) -> None:
    ok = tmp_path / "ok.py"
    ok.write_text(
        "from estimator.types import (\n    Wheel,\n)\n\ndef f():\n    import estimator.x as x\n"
    )
    _rewrite(ok, "renamed")
    assert ok.read_text() == (
        "from renamed.types import (\n    Wheel,\n)\n\ndef f():\n    import renamed.x as x\n"
    )
    bare = tmp_path / "bare.py"
    bare.write_text("import estimator.types\n")
    with pytest.raises(ValueError, match=r"cannot rename import of renamed\.types"):
        _rewrite(bare, "renamed")

"""A git revision's ``estimator`` package imported beside this tree's, under a private name.

For benches that run two versions of the estimators in one interpreter
(``bench advance --interleave``). The revision's ``estimator/`` is extracted and its
``estimator`` imports rewritten to the private name on extraction: every import the
baseline runs, at module level or inside a function, then names its own package, and the
rewritten files can be read in the temporary directory. (An import hook would have to tell,
at every ``from estimator… import`` executed, which of the two packages asked; rewriting
needs no such guess.) The package only imports itself, numpy, scipy and filterpy, so its
imports are the only place its name is written.

The measurements and configs a bench builds with this tree's types are turned into the
renamed package's (:func:`to_package`), since the estimators check them with ``isinstance``.
"""

from __future__ import annotations

import ast
import contextlib
import dataclasses
import enum
import importlib
import itertools
import re
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from server.tooling.bench import extract_revision

__all__ = ["renamed_estimator", "to_package"]

_PACKAGE = "estimator"
_IMPORT = re.compile(r"^(\s*)(from|import)(\s+)estimator(?=[.\s])", re.MULTILINE)
_counter = itertools.count()


def _rewrite(path: Path, name: str) -> None:
    """Point ``path``'s ``estimator`` imports at ``name``; ValueError where an import would
    still reach this tree's package, or bind a name the module's code does not use."""
    text = _IMPORT.sub(rf"\1\2\3{name}", path.read_text())
    for node in ast.walk(ast.parse(text, str(path))):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            left = [node.module] if node.module.partition(".")[0] == _PACKAGE else []
        elif isinstance(node, ast.Import):
            # a missed one, or ``import estimator[.x]`` whose code still reads ``estimator``
            tops = [(a.name, a.name.partition(".")[0], a.asname) for a in node.names]
            left = [m for m, top, alias in tops if top == _PACKAGE or (top == name and not alias)]
        else:
            continue
        if left:
            raise ValueError(f"{path}: line {node.lineno}: cannot rename import of {left[0]}")
    path.write_text(text)


@contextlib.contextmanager
def renamed_estimator(rev: str) -> Iterator[str]:
    """The ``estimator`` package of git revision ``rev`` importable as the returned name;
    its modules are dropped from ``sys.modules`` and ``sys.path`` on exit."""
    name = f"_estimator_at_{re.sub(r'[^0-9A-Za-z]', '_', rev)}_{next(_counter)}"
    with tempfile.TemporaryDirectory() as tmp:
        extract_revision(rev, Path(tmp), (_PACKAGE,))
        root = Path(tmp) / name
        (Path(tmp) / _PACKAGE).rename(root)
        for path in root.rglob("*.py"):
            _rewrite(path, name)
        sys.path.insert(0, tmp)
        try:
            importlib.invalidate_caches()
            yield name
        finally:
            sys.path.remove(tmp)
            for module in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
                del sys.modules[module]


def to_package(obj: Any, package: str, _cache: dict[type, Any] | None = None) -> Any:
    """``obj`` rebuilt with the types of ``package`` (a renamed ``estimator``): dataclasses
    field by field (the target's ``init`` fields, by name), enums by value, tuples, lists and
    dicts item by item, arrays copied, everything else as it is. ValueError when the target
    type is missing or needs a field ``obj`` lacks."""
    cache: dict[type, Any] = {} if _cache is None else _cache
    if isinstance(obj, np.ndarray):
        return obj.copy()
    if isinstance(obj, tuple) and not hasattr(obj, "_fields"):
        return tuple(to_package(v, package, cache) for v in obj)
    if isinstance(obj, list):
        return [to_package(v, package, cache) for v in obj]
    if isinstance(obj, dict):
        return {
            to_package(k, package, cache): to_package(v, package, cache) for k, v in obj.items()
        }
    cls = type(obj)
    if cls.__module__.partition(".")[0] != _PACKAGE:
        return obj
    if cls not in cache:
        cache[cls] = _target(cls, package)
    target = cache[cls]
    if isinstance(obj, enum.Enum):
        return target(obj.value)
    if dataclasses.is_dataclass(obj):
        kwargs = {}
        for f in dataclasses.fields(target):
            if not f.init:
                continue
            if hasattr(obj, f.name):
                kwargs[f.name] = to_package(getattr(obj, f.name), package, cache)
            elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ValueError(f"{target.__qualname__} of {package} needs {f.name!r}")
        return target(**kwargs)
    raise ValueError(f"cannot rebuild a {cls.__module__}.{cls.__qualname__} as {package}'s")


def _target(cls: type, package: str) -> Any:
    """The class of ``package`` at ``cls``'s module and name."""
    module = package + cls.__module__[len(_PACKAGE) :]
    try:
        found = importlib.import_module(module)
        for part in cls.__qualname__.split("."):
            found = getattr(found, part)
    except (ImportError, AttributeError):
        raise ValueError(f"{package} has no {cls.__module__}.{cls.__qualname__}") from None
    return found

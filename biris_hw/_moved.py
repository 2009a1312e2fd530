"""Old import paths of the modules that moved into :mod:`biris_hw.io` (and ``biris_hw.remote``,
now :mod:`biris_hw.simlink`): they keep working for one release, with a ``DeprecationWarning``.

An old name is not a second copy of the module: the finder hands the import system the module
already loaded under its new name, so ``biris_hw.record.Recorder is biris_hw.io.record.Recorder``
and an ``isinstance`` check holds whichever path a caller used. Submodules of a moved package
follow it (``biris_hw.net.service`` is ``biris_hw.io.net.service``).

A module whose names went to several modules (:data:`JOINED`: ``ros2``'s messages went to
:mod:`biris_hw.io.codec`, its reader to :mod:`biris_hw.io.feed`) cannot be one of them: its old
name is a small module that looks each name up in the new ones, in turn, so that
``biris_hw.ros2.SensorFeed is biris_hw.io.feed.SensorFeed`` all the same.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import ModuleType

__all__ = ["JOINED", "MOVED", "install"]

MOVED: dict[str, str] = {
    "biris_hw.net.protocol": "biris_hw.io.net.keys",
    "biris_hw.net": "biris_hw.io.net",
    "biris_hw.record": "biris_hw.io.record",
    "biris_hw.replay": "biris_hw.io.record.replay",
    "biris_hw.liveview": "biris_hw.io.liveview",
    "biris_hw.scanfile": "biris_hw.io.scanfile",
    "biris_hw.plots": "biris_hw.io.plots",
    "biris_hw.sweeps": "biris_hw.io.sweeps",
    "biris_hw.wire": "biris_hw.io.codec",
    "biris_hw.io.wire": "biris_hw.io.codec",
    "biris_hw.remote": "biris_hw.simlink",
}
"""Old module name -> the name it has now."""

JOINED: dict[str, tuple[str, ...]] = {
    "biris_hw.ros2": ("biris_hw.io.codec", "biris_hw.io.feed"),
    "biris_hw.io.ros2": ("biris_hw.io.codec", "biris_hw.io.feed"),
}
"""Old module name -> the modules its names are in now, looked up in this order."""

_PACKAGES = ("biris_hw.net", "biris_hw.record")


def new_name(old: str) -> str | None:
    """Where module ``old`` is now, or None if it did not move."""
    if old in MOVED:
        return MOVED[old]
    for package in _PACKAGES:
        if old.startswith(package + "."):
            return MOVED[package] + old[len(package) :]
    return None


class _Alias(importlib.abc.Loader):
    def __init__(self, old: str, new: str) -> None:
        self._old = old
        self._new = new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warnings.warn(
            f"{self._old} moved to {self._new}; the old name goes in the next release",
            DeprecationWarning,
            stacklevel=2,
        )
        return importlib.import_module(self._new)

    def exec_module(self, module: ModuleType) -> None:
        """The module was run under its new name already."""


def _joined(old: str, modules: tuple[ModuleType, ...]) -> ModuleType:
    """A module named ``old`` whose every name is looked up in ``modules`` in turn (PEP 562's
    module ``__getattr__``): the same objects, never copies of them, read when asked."""
    joined = ModuleType(old, f"{old}: its names are in {', '.join(m.__name__ for m in modules)}")
    names = sorted({name for m in modules for name in getattr(m, "__all__", ())})

    def look_up(name: str) -> object:
        for module in modules:
            if hasattr(module, name):
                return getattr(module, name)
        raise AttributeError(f"module {old!r} has no attribute {name!r}")

    def listed() -> list[str]:
        return names

    joined.__dict__.update(__all__=names, __getattr__=look_up, __dir__=listed)
    return joined


class _Joined(importlib.abc.Loader):
    def __init__(self, old: str, new: tuple[str, ...]) -> None:
        self._old = old
        self._new = new

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType:
        warnings.warn(
            f"{self._old} moved to {' and '.join(self._new)}; the old name goes in the next "
            "release",
            DeprecationWarning,
            stacklevel=2,
        )
        return _joined(self._old, tuple(importlib.import_module(n) for n in self._new))

    def exec_module(self, module: ModuleType) -> None:
        """The new modules were run under their own names already."""


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(
        self, fullname: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname in JOINED:
            return importlib.machinery.ModuleSpec(fullname, _Joined(fullname, JOINED[fullname]))
        new = new_name(fullname)
        if new is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _Alias(fullname, new))


_FINDER = _Finder()


def install() -> None:
    """Put the finder on ``sys.meta_path`` once (``biris_hw/__init__`` calls it)."""
    if _FINDER not in sys.meta_path:
        sys.meta_path.insert(0, _FINDER)

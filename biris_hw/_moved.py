"""Old import paths of the modules that moved into :mod:`biris_hw.io` (and ``biris_hw.remote``,
now :mod:`biris_hw.simlink`): they keep working for one release, with a ``DeprecationWarning``.

An old name is not a second copy of the module: the finder hands the import system the module
already loaded under its new name, so ``biris_hw.record.Recorder is biris_hw.io.record.Recorder``
and an ``isinstance`` check holds whichever path a caller used. Submodules of a moved package
follow it (``biris_hw.net.service`` is ``biris_hw.io.net.service``).
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings
from types import ModuleType

__all__ = ["MOVED", "install"]

MOVED: dict[str, str] = {
    "biris_hw.net.protocol": "biris_hw.io.net.keys",
    "biris_hw.net": "biris_hw.io.net",
    "biris_hw.record": "biris_hw.io.record",
    "biris_hw.replay": "biris_hw.io.record.replay",
    "biris_hw.liveview": "biris_hw.io.liveview",
    "biris_hw.scanfile": "biris_hw.io.scanfile",
    "biris_hw.plots": "biris_hw.io.plots",
    "biris_hw.sweeps": "biris_hw.io.sweeps",
    "biris_hw.wire": "biris_hw.io.wire",
    "biris_hw.ros2": "biris_hw.io.ros2",
    "biris_hw.remote": "biris_hw.simlink",
}
"""Old module name -> the name it has now."""

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


class _Finder(importlib.abc.MetaPathFinder):
    def find_spec(
        self, fullname: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        new = new_name(fullname)
        if new is None:
            return None
        return importlib.machinery.ModuleSpec(fullname, _Alias(fullname, new))


_FINDER = _Finder()


def install() -> None:
    """Put the finder on ``sys.meta_path`` once (``biris_hw/__init__`` calls it)."""
    if _FINDER not in sys.meta_path:
        sys.meta_path.insert(0, _FINDER)

"""One mechanism for everything chosen by name: bus windows and interrupt lines.

A target description names its windows (``kind = "mmap"``) and its lines (``kind = "uio"``); both
are resolved here, in the manner of python-can's interface registry. Built-in kinds are imported
lazily, so a kind whose optional dependency is missing costs nothing until it is asked for, and
third parties add kinds through an entry-point group.

Each registry module (:mod:`biris_hw.bus.registry`, :mod:`biris_hw.irq.registry`) is one
:class:`KindRegistry` and its bound methods under the names users call (``open_window``,
``register_line``, ...).
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any, Generic, TypeVar

from biris_hw.errors import UnknownKind

__all__ = ["KindRegistry"]

T = TypeVar("T")


class KindRegistry(Generic[T]):
    """Kind name -> class deriving from ``base``, by ``module:Class`` or by registration."""

    def __init__(self, what: str, base: type[Any], builtins: dict[str, str], group: str) -> None:
        self.what = what
        self.base = base
        self.group = group
        self.kinds: dict[str, str] = dict(builtins)
        """Kind name -> ``module:Class``; also lists registered kinds."""
        self._loaded: dict[str, type[T]] = {}

    def register(self, kind: str, cls: type[T]) -> None:
        """Make ``open(kind, ...)`` build ``cls``; replaces an earlier entry of that name."""
        self._loaded[kind] = cls
        self.kinds[kind] = f"{cls.__module__}:{cls.__qualname__}"

    def unregister(self, kind: str) -> None:
        """Forget a kind (tests and plugins that clean up after themselves)."""
        self._loaded.pop(kind, None)
        self.kinds.pop(kind, None)

    def resolve(self, kind: str) -> type[T]:
        """The class of a kind: registered, built in, or from the entry-point group.

        Raises :class:`~biris_hw.errors.UnknownKind` (a ``LookupError``) for a name nobody
        provides, or one whose target does not derive from ``base``.
        """
        if kind in self._loaded:
            return self._loaded[kind]
        target = self.kinds.get(kind)
        if target is None:
            for ep in entry_points(group=self.group):
                if ep.name == kind:
                    target = ep.value
                    break
        if target is None:
            known = ", ".join(sorted(self.kinds))
            raise UnknownKind(f"no {self.what} kind {kind!r} (known: {known})")
        module_name, _, attr = target.partition(":")
        cls: type[T] = getattr(importlib.import_module(module_name), attr)
        if not (isinstance(cls, type) and issubclass(cls, self.base)):
            raise UnknownKind(f"{target} is not a {self.base.__name__}")
        self._loaded[kind] = cls
        return cls

    def open(self, kind: str, **options: Any) -> T:
        """Build the named kind with its keyword options, e.g. ``open("memory", size=0x1000)``."""
        return self.resolve(kind)(**options)

"""The BIRIS server: the report's Harmony task structure on Python threads.

Loaded lazily: importing one of the server's modules (the administrator, a component) does not
start loading the whole server with its tasks and interrupt routines.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from biris_hw.server.server import BirisServer

__all__ = ["BirisServer"]


def __getattr__(name: str) -> Any:
    if name == "BirisServer":
        from biris_hw.server.server import BirisServer

        return BirisServer
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

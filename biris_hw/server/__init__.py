"""The BIRIS server: the report's Harmony task structure on Python threads."""

from biris_hw.server.server import BirisServer

__all__ = ["BirisServer"]

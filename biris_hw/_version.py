"""The package's version, in a module of its own: what writes it into a file (a recording's
header) reads it without loading the package root's façade over the server."""

__version__ = "0.1.0"

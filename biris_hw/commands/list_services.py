"""``biris list``: the BIRIS services that can be reached, with their name and state.

``biris list`` scouts the local network (multicast); ``biris list --endpoint tcp/robot:7447``
looks behind that endpoint (a service, or a Zenoh router with several behind it), as do
``$BIRIS_ENDPOINT`` and the profile's ``endpoint`` (:mod:`biris_hw.commands.profile`). One line
per service: its name (what ``--connect`` takes), its sensor's state, whether a controller is
connected and how many clients it has (``?`` from a service that does not say), and whether it
serves a sensor or a recording::

    NAME    STATE     CONTROLLER  CLIENTS  SERVES
    biris0  scanning  yes         3        sensor
    rec0    idle      no          1        recording

``--json`` prints the same as a JSON list. An endpoint that cannot be reached is an error with
its reason (exit 2); finding no service is not (the list is empty, stderr says where it
looked). Credentials are sent only with ``--read-credentials`` (a service whose reading needs
them shows ``needs credentials`` otherwise): they would go to every service found.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import TYPE_CHECKING, TextIO

from biris_hw.commands.argtypes import seconds
from biris_hw.commands.console import prog_of
from biris_hw.commands.failures import SetupError
from biris_hw.commands.options import (
    add_debug_argument,
    add_quiet_argument,
    add_service_client_arguments,
    connect_options,
)

if TYPE_CHECKING:
    from biris_hw.io.net.discovery import ServiceInfo

__all__ = ["add_arguments", "run"]

_LOOK_S = 2.0
"""``--timeout``'s default (:data:`biris_hw.io.net.discovery.LOOK_S`, not imported here: the
flags load nothing of Zenoh)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_service_client_arguments(parser)
    shown = parser.add_argument_group("listing")
    shown.add_argument(
        "--timeout",
        type=seconds,
        default=_LOOK_S,
        metavar="S",
        help=f"look for S seconds at most (default {_LOOK_S:g}; endpoints given end the look "
        "as soon as each is linked)",
    )
    shown.add_argument("--json", action="store_true", help="print the services as JSON")
    add_quiet_argument(parser)
    add_debug_argument(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """List the services; 0 whether or not any was found."""
    stream = out or sys.stdout
    options = connect_options(args)
    try:
        from biris_hw.io.net.discovery import find_services
        from biris_hw.io.net.zconfig import tls_options
    except ImportError as exc:
        raise SetupError(
            f"biris list needs the net extra (pip install 'biris-hw[net]'): {exc}"
        ) from exc
    zenoh = dict(options["zenoh_options"] or {})
    if options["tls_ca"] is not None:
        zenoh.update(tls_options(root_ca=options["tls_ca"]))
    endpoints = options["endpoints"] or []
    send = options["reader_credentials"] and options["user"] is not None
    from biris_hw.errors import ConnectionClosed

    try:
        found = find_services(
            endpoints,
            options=zenoh,
            timeout=args.timeout,
            user=options["user"] if send else None,
            password=options["password"] if send else None,
        )
    except ConnectionClosed as exc:  # no endpoint can be reached: the reasons
        raise SetupError(str(exc)) from exc
    if args.json:
        print(json.dumps([each.to_dict() for each in found], indent=2), file=stream)
    elif found:
        print(table(found), file=stream)
    if not found:
        where = ", ".join(endpoints) if endpoints else "multicast scouting"
        print(
            f"{prog_of(args)}: no BIRIS service found ({where}, {args.timeout:g} s)",
            file=sys.stderr,
        )
    stream.flush()
    return 0


def table(services: list[ServiceInfo]) -> str:
    """The services as aligned columns, a header first."""
    rows = [("NAME", "STATE", "CONTROLLER", "CLIENTS", "SERVES")]
    for each in services:
        controller = "?" if each.controllers is None else ("yes" if each.controllers else "no")
        serves = "?" if each.playback is None else ("recording" if each.playback else "sensor")
        clients = "?" if each.clients is None else str(each.clients)
        rows.append((each.name, each.state, controller, clients, serves))
    widths = [max(len(row[i]) for row in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True)).rstrip()
        for row in rows
    )

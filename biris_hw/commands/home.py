"""``biris home``: initialise the server (which finds the zero index) and stand at 0 degrees.

Starting a server already homes the head: initialisation turns it until the encoder's zero index
passes and then drives to it. The command then sends the report's BIRIS_HOME as a client would
and waits until the head stands still, so what it prints is where the head has come to rest.
On a real target, a head that stands more than half a turn from 0 degrees once the server has
started is not driven home without ``--yes``.
"""

from __future__ import annotations

import argparse
import sys
from typing import TextIO

from biris_hw.angles import counts_to_deg
from biris_hw.commands.options import add_target_arguments, add_timeout_argument, add_yes_argument
from biris_hw.commands.session import confirm_moves, open_session

__all__ = ["add_arguments", "run"]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_yes_argument(parser)
    add_timeout_argument(parser)
    add_target_arguments(parser)


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    stream = out or sys.stdout
    with open_session(args) as session:
        with session.server.open() as conn:
            confirm_moves(session, args, [("driving home to 0\N{DEGREE SIGN}", 0)])
            conn.home()
            conn.wait_idle(timeout=args.timeout)
        counts = int(session.server.status()["azimuth"])
        line = f"homed: azimuth {counts_to_deg(counts):+.2f} deg ({counts} counts)"
        if session.rig is not None:
            line += f"; simulated head at {counts_to_deg(session.rig.azimuth_counts):+.2f} deg"
    print(line, file=stream)
    return 0

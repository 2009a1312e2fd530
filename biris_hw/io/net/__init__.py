"""The sensor as a network service on Zenoh (the report's "planned Ethernet server").

``serve(server, name=..., listen=[...], controllers={...})`` makes one BirisServer available to
several programs on several machines; ``connect(name, endpoints=[...], user=, password=)`` gives
an object used like the server itself (``open``, ``status``, ``close``), whose connections have
the methods, results and errors of local ones. Reading is free unless the service is told
otherwise; motion and configuration need a controller's credentials
(:class:`~biris_hw.errors.AccessDenied` otherwise). The key expressions, requests and payloads
are written down for non-Python clients in ``docs/wire-format.md``; payloads are
:mod:`biris_hw.io.codec`'s ROS 2 messages in CDR. Needs the ``net`` extra (eclipse-zenoh).
"""

from __future__ import annotations

from biris_hw.io.net.keys import Keys
from biris_hw.io.net.remote import RemoteConnection, RemoteSensor, Subscription, connect
from biris_hw.io.net.service import Sensor, Service, serve
from biris_hw.io.net.zconfig import tls_options

__all__ = [
    "Keys",
    "RemoteConnection",
    "RemoteSensor",
    "Sensor",
    "Service",
    "Subscription",
    "connect",
    "serve",
    "tls_options",
]

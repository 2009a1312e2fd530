"""Zenoh's access control on the service's session (docs/wire-format.md, "Security", point 3):
default deny, peers told apart by the user name of their link (usrpwd authentication), readers
allowed the seven read RPCs, the data keys and their own client tokens, controllers ``rpc/**``
besides.

What the ACL does, seen from a client: a reader's control request never reaches the service,
whatever controller password it carries. Zenoh drops the query where it enters the service's
session and answers it at once with a final, empty response, so the client's call raises
TimeoutError ("no reply") within a round trip, not after its own reply timeout, and the
service never sees (or counts) the request. A link user that no subject names gets nothing at
all, not even the service's liveliness token.

The rules are written per direction as seen from the service's session: what a client may send
in (``ingress``), and what the service may send out to it (``egress``: its queryable, replies,
publications and token). A rule without ``flows`` applies both ways, and with the service's
own messages left out no client finds the service at all. The rule set (:data:`RULES`) is the
minimal one: drop any rule, or any message kind from one, and a test below fails.

On a router between the service and its clients (:data:`ROUTER_RULES`), the service is a
subject too: what it sends comes in from it and goes out to the clients, what the clients send
the other way round. That is where the ACL stops an impostor: a peer declaring a queryable on
``rpc/**`` would otherwise be sent every controller's requests, passwords included.
"""

from __future__ import annotations

import contextlib
import json
import queue
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh

from biris_hw import BirisServer, ConnectionKind
from biris_hw.data import DeliveryPolicy, Scan
from biris_hw.errors import AccessDenied, ConnectionClosed
from biris_hw.io.net import RemoteSensor, Service, connect, serve
from biris_hw.io.net.keys import READ_OPS, Keys
from biris_hw.io.net.zconfig import make_config
from biris_hw.status import ServerStatus
from tests.conftest import WAIT, until
from tests.net_helpers import FakeSensor, endpoint, free_port, warm_up_zenoh

pytestmark = [pytest.mark.slow, pytest.mark.realtime]  # the service's own threads

NAME = "acl"
KEYS = Keys(NAME)
P = KEYS.prefix

CONTROLLER = {"user": "op", "password": "s3cret"}
"""The service's own controller credentials, checked per request behind the ACL."""

LINK_PASSWORDS = {
    "reader": "reader-link-pw",
    "controller": "controller-link-pw",
    "guest": "g-pw",
    "service": "service-link-pw",
}
"""The usrpwd dictionary: ``guest`` may open a link but no ACL subject names it; ``service`` is
the service's own link to a router."""

READ_RPCS = (
    "open",
    "close",
    "status",
    "request_point",
    "request_scan_data",
    "ready_for_data",
    "wait_idle",
)
"""The seven read RPCs, as docs/wire-format.md names them."""

DATA_KEYS = [KEYS.point, KEYS.scans, KEYS.status, KEYS.fault]

RULES: list[tuple[str, str, list[str], list[str]]] = [
    # (id, flow, messages, key expressions), the flow as seen from the service's session.
    # Each rule is needed: drop any one and some test below fails (named where only one does).
    #
    # What the service sends out to its clients. Without the first, every request gets "no
    # reply"; without the token, no client finds the service.
    ("service-rpc", "egress", ["declare_queryable", "reply"], [f"{P}/rpc/**"]),
    ("service-data", "egress", ["put"], DATA_KEYS),
    ("service-token", "egress", ["liveliness_token"], [KEYS.service_token]),
    # What a reader (and a controller) may send in.
    ("read", "ingress", ["query"], [KEYS.rpc(op) for op in READ_RPCS]),
    ("subscribe", "ingress", ["declare_subscriber"], DATA_KEYS),
    # without it the service never sees a client leave: test_a_reader_that_vanishes_...
    ("client-token", "ingress", ["liveliness_token"], [KEYS.client_tokens]),
    # a peer (the Python client) is sent the service's token unasked; a client-mode session
    # (or a router) asks for it: test_a_client_mode_reader_finds_the_service
    (
        "watch-service",
        "ingress",
        ["declare_liveliness_subscriber", "liveliness_query"],
        [KEYS.service_token],
    ),
    # What a controller may send in besides: test_a_controller_controls_...
    ("control", "ingress", ["query"], [f"{P}/rpc/**"]),
]
"""The rule set; :func:`access_control` gives ``control`` to controllers only, the rest to
readers and controllers."""


def _allow(ident: str, flow: str, messages: list[str], keys: list[str]) -> dict[str, Any]:
    """One allowing rule in Zenoh's configuration form."""
    return {
        "id": ident,
        "permission": "allow",
        "flows": [flow],
        "messages": messages,
        "key_exprs": keys,
    }


def access_control() -> dict[str, Any]:
    """The ``access_control`` section of the service's Zenoh configuration."""
    rules = [_allow(*rule) for rule in RULES]
    everyone = [ident for ident, *_ in RULES if ident != "control"]
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [
            {"id": "readers", "usernames": ["reader"]},
            {"id": "controllers", "usernames": ["controller"]},
        ],
        "policies": [
            {"id": "serve and read", "rules": everyone, "subjects": ["readers", "controllers"]},
            {"id": "control", "rules": ["control"], "subjects": ["controllers"]},
        ],
    }


ROUTER_RULES: list[tuple[str, str, str, list[str], list[str]]] = [
    # (id, flow, subject, messages, key expressions) on a router between the service and its
    # (client-mode) clients, where the service is a subject too. What the service sends comes
    # in from it and goes out to the clients; what the clients send, the other way round.
    ("from-service-rpc", "ingress", "service", ["declare_queryable", "reply"], [f"{P}/rpc/**"]),
    ("from-service-data", "ingress", "service", ["put"], DATA_KEYS),
    ("from-service-token", "ingress", "service", ["liveliness_token"], [KEYS.service_token]),
    # the service's subscription to the clients' tokens: through a router it must ask for
    # them, where a direct peer is sent them unasked (its check on a token that went is
    # answered from what that subscription knows: no liveliness_query needed)
    (
        "from-service-watch",
        "ingress",
        "service",
        ["declare_liveliness_subscriber"],
        [KEYS.client_tokens],
    ),
    ("to-service-rpc", "egress", "service", ["query"], [f"{P}/rpc/**"]),
    ("to-service-subscribers", "egress", "service", ["declare_subscriber"], DATA_KEYS),
    ("to-service-tokens", "egress", "service", ["liveliness_token"], [KEYS.client_tokens]),
    # the clients' side: the rules of the service's own session (RULES), by subject
    *(
        (ident, flow, "controllers" if ident == "control" else "clients", messages, keys)
        for ident, flow, messages, keys in RULES
    ),
]
"""The rule set of a router (the service's own session needs none then; it may have RULES)."""


def router_access_control() -> dict[str, Any]:
    """The ``access_control`` section of the router's Zenoh configuration."""
    rules = [_allow(ident, flow, messages, keys) for ident, flow, _, messages, keys in ROUTER_RULES]
    subjects = {
        "service": ["service"],
        "clients": ["readers", "controllers"],
        "controllers": ["controllers"],
    }
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": [
            {"id": "service", "usernames": ["service"]},
            {"id": "readers", "usernames": ["reader"]},
            {"id": "controllers", "usernames": ["controller"]},
        ],
        "policies": [
            {
                "id": who,
                "rules": [ident for ident, _, subject, _, _ in ROUTER_RULES if subject == who],
                "subjects": subjects[who],
            }
            for who in subjects
        ],
    }


DENIED_WITHIN_S = 1.0
"""A denied request is answered (empty) within a round trip on loopback; the client's own reply
timeout (:data:`~biris_hw.io.net.remote.REPLY_MARGIN_S`, 5 s) is far longer, so this bound tells
Zenoh's answer from the client giving up."""

REFUSED_WAIT_S = 1.0
"""How long a peer the ACL gives nothing waits for the service before connect() gives up."""


@pytest.fixture(scope="module", autouse=True)
def _zenoh_runtime() -> None:
    warm_up_zenoh()


@pytest.fixture
def time_scale() -> float:
    """The ACL does not depend on the simulator's pace: x30 only (conftest's default runs x10
    too, for timing bugs the service's other tests look for)."""
    return 30.0


def _dictionary(tmp_path: Path) -> Path:
    dictionary = tmp_path / "zenoh-users.txt"
    dictionary.write_text("".join(f"{u}:{pw}\n" for u, pw in LINK_PASSWORDS.items()))
    dictionary.chmod(0o600)
    return dictionary


def _serve_with_acl(
    sensor: Any, tmp_path: Path
) -> tuple[str, contextlib.AbstractContextManager[Service]]:
    dictionary = _dictionary(tmp_path)
    where = endpoint(free_port())
    return where, serve(
        sensor,
        name=NAME,
        listen=[where],
        controllers={CONTROLLER["user"]: CONTROLLER["password"]},
        multicast=False,
        options={
            "transport/auth/usrpwd/dictionary_file": str(dictionary),
            "access_control": access_control(),
        },
    )


@pytest.fixture
def acl_service(server: BirisServer, tmp_path: Path) -> Iterator[tuple[Service, str]]:
    """The service on a simulated sensor, behind link authentication and the ACL."""
    where, serving = _serve_with_acl(server, tmp_path)
    with serving as svc:
        yield svc, where


@pytest.fixture
def fake_acl_service(tmp_path: Path, no_leaks: None) -> Iterator[tuple[Service, str]]:
    """The same on a sensor in memory, for what needs no motion."""
    where, serving = _serve_with_acl(FakeSensor(), tmp_path)
    with serving as svc:
        yield svc, where


def _link(user: str, **extra: Any) -> dict[str, Any]:
    return {
        "transport/auth/usrpwd/user": user,
        "transport/auth/usrpwd/password": LINK_PASSWORDS[user],
        **extra,
    }


def _connect(where: str, link_user: str, **kwargs: Any) -> RemoteSensor:
    options = _link(link_user, **kwargs.pop("options", {}))
    return connect(NAME, [where], multicast=False, options=options, **kwargs)


def test_the_documented_example_is_the_tested_rule_set() -> None:
    """docs/wire-format.md's JSON (for service ``biris0``) is :func:`access_control`'s, so the
    example a reader copies is the one these tests prove."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "wire-format.md").read_text()
    block = text.split("takes them (JSON):\n\n", 1)[1].splitlines()
    code = []
    for line in block:
        if not line.startswith("       "):  # the list item's 3 spaces and the code block's 4
            break
        code.append(line)
    documented = json.loads("\n".join(code))
    tested = json.loads(json.dumps(access_control()).replace(f"biris/{NAME}/", "biris/biris0/"))
    assert documented == tested


def test_the_rules_name_every_read_rpc() -> None:
    """The reader's rule is the protocol's read operations, no more and no fewer."""
    assert set(READ_RPCS) == READ_OPS


def test_a_reader_reads_but_its_control_requests_never_reach_the_service(
    server: BirisServer, acl_service: tuple[Service, str]
) -> None:
    svc, where = acl_service
    # the right controller password, on a reader's link
    with _connect(where, "reader", **CONTROLLER) as reader:
        statuses: queue.Queue[ServerStatus] = queue.Queue()
        subscription = reader.subscribe("status", statuses.put)
        assert reader.status()["state"] == "idle"
        conn = reader.open()
        assert conn.request_point() is None  # answered: nothing acquired yet
        conn.wait_idle(timeout=0)  # a blocking read, polled
        assert statuses.get(timeout=WAIT)["state"] == "idle"  # a publication came through

        before, asked = server.status(), svc.requests
        for op, request in (("home", conn.home), ("single_scan", lambda: conn.single_scan(10.0))):
            start = time.monotonic()
            with pytest.raises(TimeoutError, match=f"^{op}: no reply from service") as denied:
                request()
            took = time.monotonic() - start
            assert type(denied.value) is TimeoutError
            assert took < DENIED_WITHIN_S, f"{op} refused after {took:.2f} s"
        assert svc.requests == asked  # dropped by Zenoh: the service never saw them
        after = server.status()
        assert (after.state, after.azimuth, after.elevation, after.counters["scans"]) == (
            before.state,
            before.azimuth,
            before.elevation,
            before.counters["scans"],
        )
        assert reader.status()["state"] == "idle"  # the link survives a denial
        conn.close()
        subscription.close()


def test_a_controller_controls_and_readers_get_the_data(
    server: BirisServer, acl_service: tuple[Service, str]
) -> None:
    svc, where = acl_service
    with (
        _connect(where, "controller", **CONTROLLER) as controller,
        _connect(where, "reader") as reader,
    ):
        published: queue.Queue[Scan] = queue.Queue()
        subscription = reader.subscribe("scan", published.put)
        pulled = reader.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER)
        before = server.status()
        conn = controller.open()
        conn.home()
        assert conn.single_scan(10.0) == 114
        conn.wait_idle(timeout=WAIT)
        after = server.status()
        assert after.counters["scans"] == before.counters["scans"] + 1
        assert after.azimuth == 114 != before.azimuth
        scan = published.get(timeout=WAIT)
        got = pulled.ready_for_data(timeout=WAIT)
        assert isinstance(got, Scan) and (got.direction, got.seq) == (scan.direction, scan.seq)
        again = reader.open().request_scan_data(scan.direction)
        assert again is not None and again.seq == scan.seq
        subscription.close()

    # the service's own controller check still stands behind the ACL (and its error reply
    # passes the ACL like any reply)
    with _connect(where, "controller", user="op", password="wrong") as impostor:
        denied = impostor.open()
        with pytest.raises(AccessDenied):
            denied.single_scan(-10.0)
    assert server.status().azimuth == 114
    until(lambda: svc.clients() == {}, what="every client's connections released")


def test_a_link_user_in_no_subject_gets_nothing(
    fake_acl_service: tuple[Service, str],
) -> None:
    """Default deny: authenticated on the link, but no rule for it, so not even the service's
    liveliness token reaches it."""
    _, where = fake_acl_service
    with pytest.raises(ConnectionClosed, match="no BIRIS service"):
        _connect(where, "guest", timeout=REFUSED_WAIT_S).close()
    with _connect(where, "reader") as reader:  # the same service, to a subject it names
        assert reader.status()["state"] == "idle"


def test_a_client_mode_reader_finds_the_service(
    fake_acl_service: tuple[Service, str],
) -> None:
    """A client-mode session (or a router) asks for liveliness tokens, unlike a peer: the
    ``watch-service`` rule lets it subscribe to, and query, the service's token."""
    _, where = fake_acl_service
    with _connect(where, "reader", options={"mode": "client"}, timeout=WAIT) as reader:
        assert reader.status()["state"] == "idle"
    session = zenoh.open(make_config(connect=[where], options=_link("reader", mode="client")))
    try:
        replies = session.liveliness().get(KEYS.service_token, timeout=WAIT)
        assert [str(r.ok.key_expr) for r in replies if r.ok is not None] == [KEYS.service_token]
    finally:
        session.close()  # type: ignore[no-untyped-call]


def test_a_reader_that_vanishes_is_released(
    fake_acl_service: tuple[Service, str],
) -> None:
    """The ``client-token`` rule: the service sees a client's token come and go, and frees its
    connections when it goes (a raw session here, which vanishes without closing them)."""
    svc, where = fake_acl_service
    ident = uuid.uuid4().hex
    session = zenoh.open(make_config(connect=[where], options=_link("reader")))
    try:
        service_up = threading.Event()
        watch = session.liveliness().declare_subscriber(
            KEYS.service_token, lambda _: service_up.set(), history=True
        )
        assert service_up.wait(WAIT)  # and so its queryable, declared before its token
        watch.undeclare()  # type: ignore[no-untyped-call]
        token = session.liveliness().declare_token(KEYS.client_token(ident))
        replies = list(
            session.get(
                KEYS.rpc("open"),
                payload=json.dumps({"client": ident}).encode(),
                timeout=WAIT,
            )
        )
        assert len(replies) == 1 and replies[0].ok is not None, replies
        assert svc.clients() == {ident: 1}
        token.undeclare()  # type: ignore[no-untyped-call]
        until(lambda: ident not in svc.clients(), what="the vanished reader released")
        assert svc.released_clients == 1
    finally:
        session.close()  # type: ignore[no-untyped-call]


def test_through_a_router_nobody_else_can_pose_as_the_service(
    tmp_path: Path, no_leaks: None
) -> None:
    """The threat the ACL is for: a router forwards a controller's requests, password and all,
    to every queryable on ``rpc/**``. With the router's rules (:data:`ROUTER_RULES`), a
    reader's queryable and token on the service's keys go nowhere, its control requests are
    refused at the router, and a controller's reach the service only; publications and the
    clients' tokens go through."""
    router_at = endpoint(free_port())
    router = zenoh.open(
        make_config(
            listen=[router_at],
            options={
                "mode": "router",
                "transport/auth/usrpwd/dictionary_file": str(_dictionary(tmp_path)),
                "access_control": router_access_control(),
            },
        )
    )
    sensor = FakeSensor()
    impostor: zenoh.Session | None = None
    try:
        with serve(
            sensor,
            name=NAME,
            listen=[endpoint(free_port())],
            connect=[router_at],
            controllers={CONTROLLER["user"]: CONTROLLER["password"]},
            multicast=False,
            options=_link("service"),
            status_period=0.05,  # the sensor in memory never changes: publish it often
        ) as svc:
            impostor = zenoh.open(
                make_config(connect=[router_at], options=_link("reader", mode="client"))
            )
            service_up = threading.Event()
            watch = impostor.liveliness().declare_subscriber(
                KEYS.service_token, lambda _: service_up.set(), history=True
            )
            assert service_up.wait(WAIT)  # through the router (and so its queryable)
            watch.undeclare()  # type: ignore[no-untyped-call]
            overheard: list[str] = []
            queryable = impostor.declare_queryable(
                KEYS.rpcs,
                lambda query: overheard.append(str(query.key_expr)),
                allowed_origin=zenoh.Locality.REMOTE,  # others' queries, not its own
            )
            fake = impostor.liveliness().declare_token(KEYS.service_token)
            # a round trip after the declarations: the router has taken (or refused) them
            asked = json.dumps({"client": "impostor"}).encode()
            status = list(impostor.get(KEYS.rpc("status"), payload=asked, timeout=WAIT))
            assert len(status) == 1 and status[0].ok is not None, status

            client_mode = {"mode": "client"}
            with (
                _connect(router_at, "controller", options=client_mode, **CONTROLLER) as controller,
                _connect(router_at, "reader", options=client_mode) as reader,
            ):
                statuses: queue.Queue[ServerStatus] = queue.Queue()
                subscription = reader.subscribe("status", statuses.put)
                controller.open().stop_scan()
                assert sensor.calls == ["stop_scan"]
                conn = reader.open()
                start = time.monotonic()
                with pytest.raises(TimeoutError, match=r"^stop_scan: no reply"):
                    conn.stop_scan()
                assert time.monotonic() - start < DENIED_WITHIN_S
                assert sensor.calls == ["stop_scan"]
                assert statuses.get(timeout=WAIT)["state"] == "idle"
                subscription.close()
                gone = {controller.client, reader.client}
            assert overheard == []
            until(lambda: not gone & svc.clients().keys(), what="the clients seen to leave")
            fake.undeclare()  # type: ignore[no-untyped-call]
            queryable.undeclare()  # type: ignore[no-untyped-call]
    finally:
        if impostor is not None:
            impostor.close()  # type: ignore[no-untyped-call]
        router.close()  # type: ignore[no-untyped-call]

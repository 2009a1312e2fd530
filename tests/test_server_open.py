"""``BirisServer.open`` refuses what is no connection kind with the library's own error."""

from __future__ import annotations

import pytest

from biris_hw import BirisServer
from biris_hw.errors import RequestError


def test_an_unknown_connection_kind_is_a_request_error(server: BirisServer) -> None:
    before = server.status().connections
    with pytest.raises(RequestError, match="no connection kind 99"):
        server.open(kind=99)  # type: ignore[arg-type]
    assert server.status().connections.keys() == before.keys()  # nothing opened

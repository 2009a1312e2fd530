"""The suite's own leak check (tests/conftest.py): a descriptor a library closes in its own time
after its ``close()`` has returned is not a leak; one that stays open is, and is named."""

from __future__ import annotations

import os
import threading

from tests.conftest import WAIT, _fds, _fds_left_open


def _opened(before: set[str], *fds: int) -> set[str]:
    """What the check can see of ``fds``: the listing that took ``before`` held a descriptor of
    its own, which the first of them may reuse (the check cannot tell that one from it)."""
    seen = {str(fd) for fd in fds} - before
    assert seen  # the second end of a pipe is always new
    return seen


def test_a_descriptor_closed_by_another_thread_soon_after_is_not_a_leak() -> None:
    before = _fds()
    read_end, write_end = os.pipe()
    closing = threading.Event()

    def close_later() -> None:  # as Zenoh's runtime drops a closed session's socket
        closing.wait(WAIT)
        os.close(read_end)
        os.close(write_end)

    closer = threading.Thread(target=close_later)
    closer.start()
    try:
        assert _fds_left_open(before, grace_s=0.0) == _opened(before, read_end, write_end)
        closing.set()  # closed while the check below waits for it
        assert _fds_left_open(before) == set()
    finally:
        closing.set()
        closer.join(WAIT)


def test_a_descriptor_that_stays_open_is_a_leak() -> None:
    before = _fds()
    read_end, write_end = os.pipe()
    try:
        assert _fds_left_open(before, grace_s=0.05) == _opened(before, read_end, write_end)
    finally:
        os.close(read_end)
        os.close(write_end)

"""A Zenoh session that ends with its owner: at interpreter exit, or when the owner is collected.

zenoh-python runs every callback handler (a subscriber's, a liveliness subscriber's) on a Python
thread of its own, and those threads are not daemons: they end when their subscriber is
undeclared or the session closes. So a script that forgets ``close()`` would never exit -- the
interpreter joins non-daemon threads before it runs :mod:`atexit` handlers, and nothing would
close the session. Files and sockets close themselves at exit; a client must too.

:class:`SessionLife` holds a session and closes it once (idempotent, from any thread): first
the subscribers it was given (:meth:`SessionLife.track`), which ends their threads at once, then
the session, waited for at most :data:`CLOSE_WAIT_S` -- Zenoh's close waits up to 10 s for a
peer that does not answer (a link cut without a word), and it goes on in the background then.
Every open one is closed by a hook that runs when the interpreter starts to shut down, *before*
it joins threads (``threading._register_atexit``, what :mod:`concurrent.futures` uses for the
same reason); owners registered with :func:`close_at_exit` are closed first, politely (a remote
sensor tells the service it leaves). :meth:`SessionLife.collect_with` closes the session when
its owner is garbage-collected, which needs the owner's callbacks to hold it weakly
(:func:`weak_callback`): a callback held by Zenoh would otherwise keep it alive for ever.
"""

from __future__ import annotations

import atexit
import contextlib
import logging
import threading
import weakref
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

__all__ = ["CLOSE_WAIT_S", "SessionLife", "close_at_exit", "weak_callback"]

log = logging.getLogger(__name__)

CLOSE_WAIT_S = 2.0
"""Longest :meth:`SessionLife.close` waits for Zenoh's close (a few milliseconds on a live link;
up to 10 s, Zenoh's own bound, when the peer has silently gone)."""

T = TypeVar("T")


class _Closable(Protocol):
    def close(self) -> None: ...


_LOCK = threading.Lock()
_OPEN: set[SessionLife] = set()
"""Sessions not closed yet (strongly held: an owner that was collected may have left one)."""
_OWNERS: weakref.WeakSet[Any] = weakref.WeakSet()
"""Owners to close politely at exit, if they are still alive then."""
_HOOKED = False


class SessionLife:
    """One Zenoh session, closed once: by its owner, at exit, or when its owner is collected."""

    def __init__(self, session: Any, what: str) -> None:
        self.session = session
        self.what = what
        """What owns it, for the log."""
        self._lock = threading.Lock()
        self._closed = False
        self._tracked: list[Any] = []
        _hook()
        with _LOCK:
            _OPEN.add(self)

    @property
    def closed(self) -> bool:
        return self._closed

    def track(self, entity: Any) -> None:
        """Undeclare ``entity`` (a subscriber with a callback) before the session closes."""
        with self._lock:
            self._tracked.append(entity)

    def untrack(self, entity: Any) -> None:
        """``entity`` was undeclared by its owner."""
        with self._lock:
            self._tracked = [e for e in self._tracked if e is not entity]

    def close(self) -> None:
        """Undeclare what is tracked, then close the session, waiting for that at most
        :data:`CLOSE_WAIT_S` (idempotent; a second caller returns at once)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            tracked, self._tracked = self._tracked, []
        for entity in tracked:
            with contextlib.suppress(Exception):  # undeclared already, or the session gone
                entity.undeclare()
        closing = threading.Thread(target=self._close, name="biris-net-close", daemon=True)
        closing.start()
        closing.join(CLOSE_WAIT_S)
        if closing.is_alive():
            log.debug(
                "the Zenoh session of %s is still closing (its peer does not answer)", self.what
            )

    def _close(self) -> None:
        try:
            self.session.close()
        except Exception as exc:  # Zenoh's own bound ran out, or the runtime is gone at exit
            log.debug("closing the Zenoh session of %s: %s", self.what, exc)
        finally:
            with _LOCK:
                _OPEN.discard(self)

    def close_soon(self) -> None:
        """Close on a thread of its own: what a garbage collection does, since it may run on
        any thread -- a Zenoh callback's among them, where closing the session would wait for
        that very callback to return."""
        if self._closed:
            return
        log.debug("%s was collected unclosed: closing its Zenoh session", self.what)
        threading.Thread(target=self.close, name="biris-net-collect", daemon=True).start()

    def collect_with(self, owner: object) -> weakref.finalize[Any, Any]:
        """Close this session when ``owner`` is garbage-collected (see the module)."""
        finalizer = weakref.finalize(owner, self.close_soon)
        finalizer.atexit = False  # the exit hook closes it earlier, and politely
        return finalizer


def close_at_exit(owner: _Closable) -> None:
    """Call ``owner.close()`` at exit, before its session is closed, if it is still alive."""
    _hook()
    with _LOCK:
        _OWNERS.add(owner)


def weak_callback(method: Callable[[T], None]) -> Callable[[T], None]:
    """A callback for Zenoh that calls the bound ``method`` while its object lives and does
    nothing afterwards, without keeping the object alive."""
    ref = weakref.WeakMethod(method)

    def call(item: T) -> None:
        bound = ref()
        if bound is not None:
            bound(item)

    return call


def _at_exit() -> None:
    """Close every owner still alive, then every session still open (the interpreter is
    about to join its threads: Zenoh's handler threads must end first)."""
    with _LOCK:
        owners = list(_OWNERS)
    for owner in owners:
        with contextlib.suppress(Exception):
            owner.close()
    with _LOCK:
        lives = list(_OPEN)
    for life in lives:
        life.close()


def _hook() -> None:
    """Install :func:`_at_exit` once, to run before the interpreter joins non-daemon threads
    (where that hook exists: CPython 3.9+; else at the usual atexit time)."""
    global _HOOKED
    with _LOCK:
        if _HOOKED:
            return
        _HOOKED = True
    register = getattr(threading, "_register_atexit", None)
    if register is None:
        atexit.register(_at_exit)
        return
    try:
        register(_at_exit)
    except RuntimeError:  # the interpreter is shutting down already: atexit still runs
        atexit.register(_at_exit)

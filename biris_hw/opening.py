"""Any sensor from a description: ``with open_sensor(replay="run.mcap") as sensor: ...``.

A program that reads scans does not care where they come from, so it should not have to know
five ways of getting a sensor. :func:`open_sensor` takes exactly one description and yields an
object that answers to :class:`biris_hw.sensor.Sensor` (``open``, ``status``, ``close``...):

* ``sim=RIG``: a :class:`~biris_hw.BirisServer` on a simulator the caller built
  (:class:`sim.SimulatedBiris`);
* ``target=FILE``: a :class:`~biris_hw.BirisServer` on the real VME target a TOML file
  describes (:func:`biris_hw.target.load_target`);
* ``attach=NAME``: a :class:`~biris_hw.BirisServer` on a ``biris sim --shm NAME`` process
  (:func:`biris_hw.simlink.attach`);
* ``connect=NAME``: a running service on Zenoh (``biris serve --name NAME``), as a
  :class:`~biris_hw.io.net.RemoteSensor`;
* ``replay=FILE``: an MCAP recording played back by a :class:`~biris_hw.io.record.ReplayServer`.

Each kind takes its own options as keywords, and only those (:func:`open_sensor` lists them).
Everything is checked when :func:`open_sensor` is called, before anything is opened, so a
mistake costs nothing: no server is started, no device opened, no service contacted. Leaving
the block takes down what was opened, in order: the server before the hardware under it. What
the caller passed in (a simulator) is the caller's to close.

This module imports the server, the hardware layers and the outside world only when a sensor is
opened, and never the simulator (``sim=`` is duck-typed: :class:`SimulatorRig`), so importing it
costs nothing and ``biris --help`` stays instant.
"""

from __future__ import annotations

import contextlib
import math
import os
import re
from collections.abc import Iterator, Mapping, Sequence
from typing import TYPE_CHECKING, Any, Protocol, overload

from biris_hw.errors import (
    BirisError,
    BusError,
    ConnectionClosed,
    HardwareFault,
    RequestError,
    SetupError,
)

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    from biris_hw.hardware import BirisHardware
    from biris_hw.io.net import RemoteSensor
    from biris_hw.io.pose import PoseBuffer
    from biris_hw.io.record import ReplayServer
    from biris_hw.records import BirisInitRecord
    from biris_hw.sensor import Sensor
    from biris_hw.server import BirisServer

    StrPath = str | os.PathLike[str]

__all__ = ["SetupError", "SimulatorRig", "load_init_record", "open_poses", "open_sensor"]


class SimulatorRig(Protocol):
    """What ``open_sensor(sim=...)`` uses of a simulator (:class:`sim.SimulatedBiris` has it):
    its hardware bundle, and ``start()`` (idempotent) in case the caller has not started it."""

    @property
    def hardware(self) -> BirisHardware: ...

    def start(self) -> object: ...


_KINDS = ("sim", "target", "attach", "connect", "replay")

_SERVER_OPTIONS = frozenset({"init", "continuous"})
_OPTIONS: dict[str, frozenset[str]] = {
    "sim": _SERVER_OPTIONS,
    "target": _SERVER_OPTIONS,
    "attach": _SERVER_OPTIONS,
    "connect": frozenset(
        {
            "endpoints",
            "user",
            "password",
            "tls_ca",
            "zenoh_options",
            "multicast",
            "timeout",
            "reader_credentials",
        }
    ),
    "replay": frozenset({"speed", "autostart"}),
}
"""The options each kind takes; any other is refused (TypeError) rather than ignored, since an
option that silently does nothing (``continuous=True`` on a service whose acquisition is not
ours) is a run that is not what its author thinks."""


@overload
def open_sensor(
    *,
    sim: SimulatorRig,
    init: BirisInitRecord | StrPath | None = ...,
    continuous: bool | None = ...,
) -> AbstractContextManager[BirisServer]: ...


@overload
def open_sensor(
    *,
    target: StrPath,
    init: BirisInitRecord | StrPath | None = ...,
    continuous: bool | None = ...,
) -> AbstractContextManager[BirisServer]: ...


@overload
def open_sensor(
    *,
    attach: str,
    init: BirisInitRecord | StrPath | None = ...,
    continuous: bool | None = ...,
) -> AbstractContextManager[BirisServer]: ...


@overload
def open_sensor(
    *,
    connect: str,
    endpoints: Sequence[str] | None = ...,
    user: str | None = ...,
    password: str | None = ...,
    tls_ca: StrPath | None = ...,
    zenoh_options: Mapping[str, Any] | None = ...,
    multicast: bool | None = ...,
    timeout: float | None = ...,
    reader_credentials: bool = ...,
) -> AbstractContextManager[RemoteSensor]: ...


@overload
def open_sensor(
    *,
    replay: StrPath,
    speed: float | None = ...,
    autostart: bool = ...,
) -> AbstractContextManager[ReplayServer]: ...


@overload
def open_sensor(
    *,
    sim: SimulatorRig | None = ...,
    target: StrPath | None = ...,
    attach: str | None = ...,
    connect: str | None = ...,
    replay: StrPath | None = ...,
    **options: Any,
) -> AbstractContextManager[Sensor]: ...


def open_sensor(
    *,
    sim: SimulatorRig | None = None,
    target: StrPath | None = None,
    attach: str | None = None,
    connect: str | None = None,
    replay: StrPath | None = None,
    **options: Any,
) -> AbstractContextManager[Any]:
    """Open the one sensor described; a context manager that yields it and takes it down.

    Exactly one of:
        sim: a simulator built by the caller (:class:`sim.SimulatedBiris`); started if it is
            not yet, never closed here (it is the caller's). Yields a
            :class:`~biris_hw.BirisServer` on its hardware.
        target: a TOML target description (``docs/target-example.toml``). Yields a
            :class:`~biris_hw.BirisServer`; the hardware is closed after it.
        attach: the name of a ``biris sim --shm NAME`` process. Yields a
            :class:`~biris_hw.BirisServer`; the link is closed after it.
        connect: the name of a running service (``biris serve --name NAME``). Yields a
            :class:`~biris_hw.io.net.RemoteSensor`; nothing on the service is stopped.
        replay: an MCAP recording (``biris record``). Yields a
            :class:`~biris_hw.io.record.ReplayServer`.

    Options, as keywords, each for the kinds named:
        init (sim, target, attach): the server's :class:`~biris_hw.BirisInitRecord`, or a TOML
            file holding one (default: the report's, ``BirisInitRecord()``).
        continuous (sim, target, attach): True for Appendix D's continuous acquisition, False
            for BI_ACQUIRE per scan, None (default) for what ``init`` says.
        endpoints (connect): Zenoh endpoints of the service (``["tcp/robot:7447"]``); None
            (default) finds it by multicast scouting.
        user, password (connect): a controller's credentials (motion and configuration).
        tls_ca (connect): the root CA (PEM file) for ``tls/`` endpoints.
        zenoh_options (connect): further Zenoh settings, ``{"key/path": value}``.
        multicast (connect): scouting on or off (default: on only without endpoints).
        timeout (connect): seconds to wait for the service to answer (default 10).
        reader_credentials (connect): send the credentials with reads too (default False).
        speed (replay): times the recorded pace (default 1.0); None plays as fast as the
            readers take it.
        autostart (replay): start playing when the first DATA connection opens (default True);
            False waits for ``ReplayServer.start()``.

    Raised when called, before anything is opened:
        TypeError: none or more than one kind; an option that is unknown or does not apply to
            the kind given; an argument of the wrong type (``sim=`` without ``hardware`` and
            ``start``, ``endpoints="tcp/..."`` instead of a list, ``continuous="yes"``).
        RequestError: (a ValueError) a value of the right type that cannot be: an empty name
            or file name, a speed or timeout that is not a positive finite number.
        SetupError: ``init`` names a file that cannot be read or holds an impossible record.

    Raised on entering the block:
        SetupError: the sensor cannot be reached as described (see the class); the original
            error is its ``__cause__``.
        RequestError: what the sensor itself refuses of its description: a service name that
            cannot be a Zenoh key, CPUs in the init record that this host does not have.
        HardwareFault: the server met a fault while it started (homing, booting BIRIS). A
            ``timeout`` fault names the BIRIS command left unanswered, from COMMAND, when its
            message does not (``BI_BOOT``, not a code).
    """
    kind, where = _one_kind(
        {"sim": sim, "target": target, "attach": attach, "connect": connect, "replay": replay}
    )
    checked = _checked_options(kind, where, options)
    if connect is not None:
        return _remote(connect, checked)
    if replay is not None:
        return _replay(replay, checked)
    return _local_server(kind, where, checked["record"])


def load_init_record(
    init: BirisInitRecord | StrPath | None = None, *, continuous: bool | None = None
) -> BirisInitRecord:
    """The init record ``open_sensor(init=init, continuous=continuous)`` gives its server: a
    program that starts a simulator can read and check the record first, so that a bad file
    costs no boot.

    Raises:
        TypeError: ``init`` is neither a record, a file name nor None; ``continuous`` neither a
            bool nor None.
        SetupError: the file cannot be read, or holds an impossible record.
    """
    import dataclasses

    from biris_hw.records import BirisInitRecord

    if continuous is not None and not isinstance(continuous, bool):
        raise TypeError(f"continuous= takes True, False or None, not {_kind_of(continuous)}")
    if init is None:
        record = BirisInitRecord()
    elif isinstance(init, BirisInitRecord):
        record = init
    elif isinstance(init, (str, os.PathLike)):
        try:
            record = BirisInitRecord.load(init)
        except OSError as exc:
            raise SetupError(f"cannot read init record {init}: {exc.strerror or exc}") from exc
        except RequestError as exc:
            raise SetupError(str(exc)) from exc
    else:
        raise TypeError(
            f"init= takes a BirisInitRecord or the name of a TOML file, not {_kind_of(init)}"
        )
    if continuous is not None and record.continuous_acquisition != continuous:
        record = dataclasses.replace(record, continuous_acquisition=continuous)
    return record


@contextlib.contextmanager
def open_poses(*, sim: Any, **options: Any) -> Iterator[PoseBuffer]:
    """``with open_poses(sim=rig) as poses:`` the simulated vehicle's odometry
    (``rig.odometry``), pumped on the rig's time base into a
    :class:`~biris_hw.io.pose.PoseBuffer` while the block runs (docs/moving.md).

    ``options`` are the buffer's (``capacity``, ``max_gap_s``, ``max_extrapolation_s``;
    ``clock_offset_s`` is 0: the odometry is stamped on the hardware clock). A real base's poses
    come from :func:`biris_hw.io.pose.subscribe_poses` or a recording's
    (:func:`biris_hw.io.pose.read_poses`).

    Raises:
        TypeError: ``sim=`` is not a simulator with odometry (``odometry`` and ``timebase``).
    """
    odometry = getattr(sim, "odometry", None)
    timebase = getattr(sim, "timebase", None)
    if odometry is None or timebase is None:
        raise TypeError(
            f"sim= takes a simulator with odometry (sim.SimulatedBiris), not {_kind_of(sim)}"
        )
    from biris_hw.io.pose import follow

    with follow(odometry, timebase, **options) as buffer:
        yield buffer


# -- checking, before anything opens -----------------------------------------------------------


def _kind_of(value: object) -> str:
    return type(value).__name__


def _one_kind(given: Mapping[str, object]) -> tuple[str, object]:
    """The one kind given and its value; TypeError for none or several."""
    chosen = [kind for kind in _KINDS if given[kind] is not None]
    if not chosen:
        raise TypeError(
            "open_sensor() needs the sensor to open: one of sim=, target=, attach=, connect= "
            "or replay="
        )
    if len(chosen) > 1:
        named = " and ".join(f"{kind}=" for kind in chosen)
        raise TypeError(f"open_sensor() opens one sensor: give one of {named}, not both")
    return chosen[0], given[chosen[0]]


def _checked_options(kind: str, where: object, options: Mapping[str, Any]) -> dict[str, Any]:
    """``where`` and ``options`` checked for ``kind``; the options as the opener uses them."""
    for name in options:
        if name in _OPTIONS[kind]:
            continue
        owners = [k for k in _KINDS if name in _OPTIONS[k]]
        if not owners:
            raise TypeError(f"open_sensor() got an unknown option {name}=")
        goes_with = " or ".join(f"{k}=" for k in owners)
        raise TypeError(
            f"open_sensor(): {name}= does not apply to {kind}= (it goes with {goes_with})"
        )
    if kind == "sim":
        if not hasattr(where, "hardware") or not callable(getattr(where, "start", None)):
            raise TypeError(f"sim= takes a simulator (sim.SimulatedBiris), not {_kind_of(where)}")
    elif kind in ("target", "replay"):
        _file_name(kind, where)
    else:
        _name(kind, where)
    if kind in ("sim", "target", "attach"):
        return {
            "record": load_init_record(options.get("init"), continuous=options.get("continuous"))
        }
    if kind == "replay":
        return _replay_options(options)
    return _connect_options(options)


def _file_name(key: str, value: object) -> None:
    if not isinstance(value, (str, os.PathLike)):
        raise TypeError(f"{key}= takes a file name, not {_kind_of(value)}")
    if not os.fspath(value):
        raise RequestError(f"{key}=: an empty file name")


def _name(key: str, value: object) -> None:
    if not isinstance(value, str):
        raise TypeError(f"{key}= takes a name (str), not {_kind_of(value)}")
    if not value:
        raise RequestError(f"{key}=: an empty name")


def _positive(key: str, value: object) -> float:
    """A positive finite number (not a bool): RequestError for a number that is not one."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"{key}= takes a number of seconds, not {_kind_of(value)}")
    if not (math.isfinite(value) and value > 0):
        raise RequestError(f"{key}= must be a positive finite number, not {value!r}")
    return float(value)


def _flag(key: str, value: object, *, optional: bool) -> bool | None:
    if value is None and optional:
        return None
    if not isinstance(value, bool):
        allowed = "True, False or None" if optional else "True or False"
        raise TypeError(f"{key}= takes {allowed}, not {_kind_of(value)}")
    return value


def _replay_options(options: Mapping[str, Any]) -> dict[str, Any]:
    speed = options.get("speed", 1.0)
    if speed is not None:
        if isinstance(speed, bool) or not isinstance(speed, (int, float)):
            raise TypeError(f"speed= takes a number or None, not {_kind_of(speed)}")
        if not (math.isfinite(speed) and speed > 0):
            raise RequestError(f"speed= must be a positive finite number or None, not {speed!r}")
        speed = float(speed)
    autostart = _flag("autostart", options.get("autostart", True), optional=False)
    return {"speed": speed, "autostart": autostart}


def _connect_options(options: Mapping[str, Any]) -> dict[str, Any]:
    checked: dict[str, Any] = {}
    endpoints = options.get("endpoints")
    if endpoints is not None:
        if isinstance(endpoints, str) or not isinstance(endpoints, Sequence):
            raise TypeError(
                f"endpoints= takes a list of endpoints (['tcp/host:7447']), not "
                f"{_kind_of(endpoints)}"
            )
        if not all(isinstance(e, str) and e for e in endpoints):
            raise RequestError(f"endpoints=: each must be a non-empty string, not {endpoints!r}")
        checked["endpoints"] = list(endpoints)
    for key in ("user", "password"):
        value = options.get(key)
        if value is not None and not isinstance(value, str):
            raise TypeError(f"{key}= takes a str, not {_kind_of(value)}")
        checked[key] = value
    ca = options.get("tls_ca")
    if ca is not None:
        _file_name("tls_ca", ca)
        checked["tls_ca"] = os.fspath(ca)
    zenoh = options.get("zenoh_options")
    if zenoh is not None:
        if not isinstance(zenoh, Mapping) or not all(isinstance(k, str) for k in zenoh):
            raise TypeError(
                f"zenoh_options= takes a mapping of Zenoh keys to values, not {_kind_of(zenoh)}"
            )
        checked["zenoh_options"] = dict(zenoh)
    if "multicast" in options:
        checked["multicast"] = _flag("multicast", options["multicast"], optional=True)
    if options.get("timeout") is not None:
        checked["timeout"] = _positive("timeout", options["timeout"])
    checked["reader_credentials"] = _flag(
        "reader_credentials", options.get("reader_credentials", False), optional=False
    )
    return checked


# -- opening -----------------------------------------------------------------------------------


@contextlib.contextmanager
def _local_server(kind: str, where: Any, record: BirisInitRecord) -> Iterator[BirisServer]:
    """A server of our own on the hardware ``kind`` names; server closed, then the hardware
    (unless it is a simulator's, which its owner closes)."""
    from biris_hw.server import BirisServer

    with contextlib.ExitStack() as stack:
        if kind == "sim":
            hardware = _started(where)
        elif kind == "target":
            hardware = _open_target(where)
            stack.callback(hardware.close)
        else:
            hardware = _attach(where)
            stack.callback(hardware.close)
        try:
            server = BirisServer(hardware, record)
            stack.callback(server.close)
            yield server
        except HardwareFault as exc:  # still inside the stack: COMMAND is read before closing
            named = _name_unanswered(exc, hardware)
            if named is exc:
                raise
            raise named from exc


def _started(rig: SimulatorRig) -> BirisHardware:
    try:
        rig.start()
    except RuntimeError as exc:  # SimulatedBiris.start on a rig that has been closed
        raise SetupError(f"the simulator cannot start: {exc}") from exc
    return rig.hardware


def _open_target(file: StrPath) -> BirisHardware:
    from biris_hw.target import load_target

    try:
        return load_target(file)
    except BusError as exc:
        raise SetupError(f"cannot open the target: {exc}") from exc
    except OSError as exc:
        raise SetupError(f"cannot read target file {file}: {exc.strerror or exc}") from exc
    except RequestError as exc:
        raise SetupError(str(exc)) from exc


def _attach(name: str) -> BirisHardware:
    from biris_hw.simlink import attach

    try:
        return attach(name)
    except OSError as exc:
        raise SetupError(f"cannot attach to simulator {name!r}: {exc.strerror or exc}") from exc


@contextlib.contextmanager
def _remote(name: str, options: Mapping[str, Any]) -> Iterator[RemoteSensor]:
    """A running service: nothing is started, homed or stopped on the way out."""
    try:
        from biris_hw.io.net import RemoteSensor, tls_options
    except ImportError as exc:
        raise SetupError(
            f"connecting to a service needs the net extra (pip install 'biris-hw[net]'): {exc}"
        ) from exc
    zenoh: dict[str, Any] = {}
    if options.get("tls_ca") is not None:
        zenoh.update(tls_options(root_ca=options["tls_ca"]))
    zenoh.update(options.get("zenoh_options") or {})
    extra: dict[str, Any] = {}
    for key in ("multicast", "timeout", "reconnect"):
        if key in options:
            extra[key] = options[key]
    try:
        remote = RemoteSensor(
            name,
            options.get("endpoints"),
            options.get("user"),
            options.get("password"),
            options=zenoh or None,
            reader_credentials=options["reader_credentials"],
            **extra,
        )
    except ConnectionClosed as exc:  # no such service answered in time
        raise SetupError(str(exc)) from exc
    with remote:
        yield remote


@contextlib.contextmanager
def _replay(file: StrPath, options: Mapping[str, Any]) -> Iterator[ReplayServer]:
    try:
        from biris_hw.io.record.replay import ReplayError, ReplayServer
    except ImportError as exc:
        raise SetupError(
            f"replaying a recording needs the record extra (pip install 'biris-hw[record]'): {exc}"
        ) from exc
    try:
        replay = ReplayServer(file, speed=options["speed"], autostart=options["autostart"])
    except ReplayError as exc:  # missing, not MCAP, no lossless channels
        raise SetupError(str(exc)) from exc
    with replay:
        yield replay


# -- faults, in a person's terms -----------------------------------------------------------------


_COMMAND_NAME = re.compile(r"\bBI_[A-Z_]+")


def _name_unanswered(exc: HardwareFault, hardware: BirisHardware) -> HardwareFault:
    """A ``timeout`` fault, naming the BIRIS command that was not answered if it does not.

    The server's message says what it waited for; if it names no command (an older server,
    or a wait the message does not describe), BIRIS's COMMAND register still holds the one it
    never finished, and a person needs its name (BI_STOP_CONTINUOUS), not its code, to know
    what the sensor was doing. Reading COMMAND has no side effect; if even that fails, the
    fault stays as it was.
    """
    if exc.kind != "timeout" or _COMMAND_NAME.search(exc.message):
        return exc
    try:
        code = hardware.devices.link.command()
    except (BirisError, OSError):
        return exc
    if code == 0:
        return exc
    from regs.biexec import BiCommand

    try:
        name = BiCommand(code).name
    except ValueError:
        name = f"unknown BIRIS command {code}"
    return HardwareFault(exc.kind, f"{exc.message} (waiting for BIRIS to finish {name})")

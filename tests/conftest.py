"""Shared fixtures and checks: a simulated target, a server on it, one wait helper, and the leak
and audit checks every test that builds a simulator gets without asking.

Every test that builds a :class:`~sim.rig.SimulatedBiris` (directly, through ``make_rig``, or
through the CLI) is checked at teardown: every rig it built is closed, no thread or file
descriptor is left behind, and the simulator's audit is clean. A test that provokes violations on
purpose says so with ``@pytest.mark.audit_violations_expected`` (or clears the audit itself once
it has checked what it expected). Tests that build no rig can ask for the leak check with the
``no_leaks`` fixture.

Every Scan a server completes during a test (``ScanSequencer.complete``, whatever built the
server: a fixture, the CLI, the thread-free core) is checked at teardown too, per sequencer, by
:class:`biris_hw.scancheck.ScanChecker` (issue 21: no scan silently short or empty, none with
another's rows). A test that makes the server deliver bad scans on purpose says so with
``@pytest.mark.scan_violations_expected``.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING, Any

import pytest

from biris_hw.records import BirisInitRecord
from biris_hw.scancheck import ScanChecker
from biris_hw.status import ServerState, ServerStatus
from biris_hw.timebase import HwThread, VirtualTime
from sim.rig import SimulatedBiris
from sim.scene import Scene
from sim.scene.shapes import Cylinder
from tests import live_rigs

pytest_plugins = ["tests.module_order", "tests.run_figures"]

if TYPE_CHECKING:
    from biris_hw.data import Scan
    from biris_hw.server import BirisServer
    from tests.core import Core

if "BIRIS_STATE_DIR" not in os.environ:
    # a target's pan journal (biris_hw.pan_reference) goes to a directory of this run's own,
    # never the user's ~/.local/state, and the subprocesses tests start inherit it
    import atexit
    import shutil
    import tempfile

    os.environ["BIRIS_STATE_DIR"] = tempfile.mkdtemp(prefix="biris-test-state-")
    atexit.register(shutil.rmtree, os.environ["BIRIS_STATE_DIR"], True)

WAIT = 5.0
"""Timeout for things that should happen almost at once; only reached when a test fails."""


def idle_status(**changes: Any) -> ServerStatus:
    """An idle server's status, nothing done yet, with ``changes`` (field values) applied: for
    tests of what carries a status (the wire, diagnostics, watch, fakes) without a server."""
    fields: dict[str, Any] = {
        "state": ServerState.IDLE,
        "fault": None,
        "azimuth": 0,
        "elevation": 0,
        "calibration": None,
        "continuous": False,
        "acquisition": "single",
        "ring": "off",
        "counters": {"scans": 0},
        "connections": {},
    }
    fields.update(changes)
    return ServerStatus(**fields)


def until(
    predicate: Callable[[], object],
    timeout: float = WAIT,
    what: str = "",
    *,
    wake: threading.Condition | None = None,
) -> bool:
    """Wait until ``predicate()`` is true, or fail the test after ``timeout`` seconds.

    With ``wake``, a condition another thread notifies whenever it changes what ``predicate``
    reads, the wait is event-driven (``Condition.wait_for``). Without it -- for state no event
    announces, such as how many threads are blocked in a call -- ``predicate`` is polled, every
    0.5 ms at first and backing off to 10 ms, so a quick change is seen at once and a slow one
    costs little CPU. The failure names ``what`` (or the predicate's source line). Returns True,
    so ``assert until(...)`` reads naturally too.
    """
    __tracebackhide__ = True
    domain = _virtual_domain()
    if domain is not None:
        if _until_virtual(domain, predicate, timeout):
            return True
        pytest.fail(
            f"timed out after {timeout:g} s (x{domain.nominal_scale:g}: "
            f"{domain.timeout_hw(timeout):g} s of virtual time) waiting for "
            f"{what or _describe(predicate)}"
        )
    if wake is not None:
        with wake:
            if wake.wait_for(predicate, timeout):
                return True
    elif _poll(predicate, timeout):
        return True
    pytest.fail(f"timed out after {timeout:g} s waiting for {what or _describe(predicate)}")


def _poll(predicate: Callable[[], object], timeout: float) -> bool:
    """Whether ``predicate()`` became true within ``timeout`` real seconds, looked at every 0.5 ms
    at first, backing off to 10 ms: for state no event announces (looked at once at least).
    The sleep is the look's period, not a synchronisation: the answer is the predicate's."""
    deadline = time.monotonic() + timeout
    interval = 0.0005
    while not predicate():
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        time.sleep(min(interval, left))
        interval = min(2 * interval, 0.01)
    return True


def _virtual_domain() -> VirtualTime | None:
    """The virtual time base the calling thread drives (the newest open virtual rig's), if any:
    :func:`until` then waits in it, since a real sleep would hold its time still."""
    me = threading.current_thread()
    for rig in reversed(live_rigs.rigs):
        tb = rig.timebase
        if isinstance(tb, VirtualTime) and not rig._closed and tb.driver is me:
            return tb
    return None


def _until_virtual(domain: VirtualTime, predicate: Callable[[], object], timeout: float) -> bool:
    """:func:`until` on virtual time: look, then sleep in the domain, every 0.5 ms of hardware
    time at first backing off to 10 ms (the same schedule in hardware time, so a run is one
    run), for ``timeout`` seconds read at the rig's nominal scale."""
    deadline = domain.now() + domain.timeout_hw(timeout)
    interval = 0.0005
    while not predicate():
        left = deadline - domain.now()
        if left <= 0:
            return False
        domain.sleep(min(interval, left), what="the test's until()")
        interval = min(2 * interval, 0.01)
    return True


def spawn(
    target: Callable[..., object], *args: object, name: str | None = None
) -> threading.Thread:
    """Start a thread for the test (a concurrent client, a consumer): on a virtual rig the test
    drives, through its time base, so that the domain counts it and its waits (a thread outside
    would see time run on behind its back, or hold it still when joined); a plain thread
    otherwise. Join it with :func:`join`."""
    domain = _virtual_domain()
    thread: threading.Thread
    if domain is not None:
        thread = domain.Thread(target, name=name, args=args, daemon=True)
    else:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
    thread.start()
    return thread


def join(thread: threading.Thread, timeout: float = WAIT) -> bool:
    """Wait for a thread of :func:`spawn` to end, at most ``timeout`` seconds (read at the
    rig's nominal scale on virtual time); True if it has."""
    if isinstance(thread, HwThread) and isinstance(thread.timebase, VirtualTime):
        tb = thread.timebase
        return tb.join_thread(thread, tb.timeout_hw(timeout))
    thread.join(timeout)
    return not thread.is_alive()


def _describe(predicate: Callable[[], object]) -> str:
    code = getattr(predicate, "__code__", None)
    if code is None:
        return repr(predicate)
    return f"the condition at {os.path.basename(code.co_filename)}:{code.co_firstlineno}"


def affinity_allowed() -> bool:
    """Whether a thread may choose its CPUs here (Linux, and not forbidden by a sandbox): setting
    the affinity it already has is the harmless probe."""
    from biris_hw.affinity import pin_current_thread
    from biris_hw.errors import RequestError

    if not hasattr(os, "sched_getaffinity"):
        return False
    try:
        pin_current_thread(os.sched_getaffinity(0))
    except RequestError:
        return False
    return True


# -- leak and audit checks -------------------------------------------------------------------------


def _fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def _threads() -> set[threading.Thread]:
    return set(threading.enumerate())


class _Watch:
    """What one test started with, and the rigs it built."""

    def __init__(self) -> None:
        self.threads = _threads()
        self.fds = _fds()
        self.rigs: list[SimulatedBiris] = []
        self.rig_options: list[dict[str, Any]] = []
        """The keywords each rig was built with (``noise``, ``trajectory``), in ``rigs``' order."""
        self.check_leaks = False

    def problems(self, audit: bool) -> list[str]:
        found: list[str] = []
        open_rigs = [rig for rig in self.rigs if not rig._closed]
        for rig in open_rigs:
            rig.close()  # so one forgotten rig does not fail the tests after this one
        if open_rigs:
            found.append(f"{len(open_rigs)} simulator(s) left open (closed now)")
        if audit:
            for rig in self.rigs:
                if rig.audit.violations:
                    found.append(
                        "the simulator's audit recorded driver rule violations:\n  "
                        + "\n  ".join(map(str, rig.audit.violations))
                    )
                if rig.drive_violations:
                    found.append(
                        "a simulated CiA 402 drive recorded driver rule violations:\n  "
                        + "\n  ".join(rig.drive_violations)
                    )
                if rig.crate is not None and rig.crate.violations:
                    found.append(
                        "the simulated VME crate recorded misuse of its CAN protocol:\n  "
                        + "\n  ".join(map(str, rig.crate.violations))
                    )
                if rig.usb_device is not None and rig.usb_device.violations:
                    found.append(
                        "the simulated VM-USB recorded protocol misuse:\n  "
                        + "\n  ".join(map(str, rig.usb_device.violations))
                    )
        for rig in self.rigs:
            tb = rig.timebase
            if isinstance(tb, VirtualTime) and tb.deadlock is not None:
                found.append(f"the rig's virtual time deadlocked:\n{tb.deadlock}")
        if self.check_leaks or self.rigs:
            left = [t for t in _threads() - self.threads if t.is_alive()]
            for thread in left:  # ending on its own (a library's callback thread after its
                thread.join(WAIT)  # session closed, on a loaded host): a leak only if it stays
            left = [t for t in left if t.is_alive()]
            if left:
                found.append(f"threads left running: {left}")
            fds = _fds_left_open(self.fds)
            if fds:
                found.append(f"file descriptors left open: {_describe_fds(fds)}")
        return found


def _fds_left_open(before: set[str], grace_s: float = WAIT) -> set[str]:
    """The descriptors opened since ``before`` that stay open, given ``grace_s`` (by default as
    long as a leftover thread, :data:`WAIT`) to close on their own.

    A descriptor closed as the listing is taken (the listing's own) is not a leak, nor is one a
    library closes in its own time: Zenoh's runtime drops a closed session's link socket from a
    thread of its own, after ``close()`` has returned (in a quiet CI run, once, as the check
    looked). No event announces a descriptor's close, so it is polled (:func:`_poll`); the usual
    case, nothing new, costs one listing."""
    left: set[str] = set()

    def all_closed() -> bool:
        nonlocal left
        left = {fd for fd in _fds() - before if os.path.lexists(f"/proc/self/fd/{fd}")}
        return not left

    _poll(all_closed, grace_s)
    return left


def _describe_fds(fds: set[str]) -> str:
    names = []
    for fd in sorted(fds, key=int):
        try:
            names.append(f"{fd} -> {os.readlink(f'/proc/self/fd/{fd}')}")
        except OSError:
            names.append(fd)  # closed since the listing (the listing's own descriptor)
    return ", ".join(names)


_CLOCK_TALLY = {"virtual": 0, "scaled": 0}
"""End-to-end tests (those that built a rig) by the clock their rigs ran on: every rig on
virtual time, or at least one on scaled real time. Shown at the end of the run."""


_SCALED_BY_MODULE: dict[str, int] = {}


def pytest_collection_finish(session: pytest.Session) -> None:
    """Everything collection imported (the package, the simulator, numpy, Zenoh, matplotlib,
    every test module) lives as long as the process: out of the cyclic collector's reach, so
    that each of its full collections during the run walks only what the tests made (what
    every long-running ``biris`` command does once its sensor is open,
    :func:`biris_hw.commands.session.quiet_collector`)."""
    import gc

    gc.collect()
    gc.freeze()


def pytest_sessionfinish(session: pytest.Session) -> None:
    """An xdist worker hands its tally to the controller, which prints the summary."""
    workeroutput = getattr(session.config, "workeroutput", None)
    if workeroutput is not None:
        workeroutput["clock_tally"] = dict(_CLOCK_TALLY)
        workeroutput["scaled_by_module"] = dict(_SCALED_BY_MODULE)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node: Any, error: object) -> None:
    """(xdist controller) add a finished worker's tally to this process's."""
    output = getattr(node, "workeroutput", {})
    for kind, n in output.get("clock_tally", {}).items():
        _CLOCK_TALLY[kind] += n
    for module, n in output.get("scaled_by_module", {}).items():
        _SCALED_BY_MODULE[module] = _SCALED_BY_MODULE.get(module, 0) + n


def pytest_terminal_summary(terminalreporter: Any) -> None:
    """The virtual-time tier's share of the end-to-end tests run (issue 22: at least 80 %)."""
    total = _CLOCK_TALLY["virtual"] + _CLOCK_TALLY["scaled"]
    if total:
        virtual, scaled = _CLOCK_TALLY["virtual"], _CLOCK_TALLY["scaled"]
        terminalreporter.write_line(
            f"end-to-end tests on virtual time: {virtual} of {total} ({virtual / total:.0%}); "
            f"on scaled real time: {scaled}"
        )
        if _SCALED_BY_MODULE:
            by = sorted(_SCALED_BY_MODULE.items(), key=lambda item: (-item[1], item[0]))
            terminalreporter.write_line(
                "  scaled, by module: " + ", ".join(f"{name} {n}" for name, n in by)
            )


_watch: _Watch | None = None
"""The running test's watch; rigs built while it is set are recorded in it."""


@pytest.fixture(scope="session", autouse=True)
def _track_rigs() -> Iterator[None]:
    """Record every SimulatedBiris built during a test in that test's watch.

    Patched here (not at import) because test modules import this file a second time as
    ``tests.conftest``; a fixture runs once, from the copy pytest loaded.
    """
    original = SimulatedBiris.__init__

    def tracked(self: SimulatedBiris, *args: Any, **kwargs: Any) -> None:
        original(self, *args, **kwargs)
        if _watch is not None:
            _watch.rigs.append(self)
            _watch.rig_options.append(dict(kwargs))
            live_rigs.rigs.append(self)

    SimulatedBiris.__init__ = tracked  # type: ignore[method-assign]
    yield
    SimulatedBiris.__init__ = original  # type: ignore[method-assign]


@pytest.fixture(autouse=True)
def _leak_and_audit_check(request: pytest.FixtureRequest, _track_rigs: None) -> Iterator[_Watch]:
    """Set up before, and torn down after, every other fixture of the test (autouse, function
    scope): the snapshot precedes any rig and the check follows every rig's close."""
    global _watch
    watch = _Watch()
    _watch = watch
    live_rigs.rigs.clear()
    try:
        yield watch
    finally:
        _watch = None
        live_rigs.rigs.clear()
    if watch.rigs:
        kind = "virtual" if all(rig.timebase.virtual for rig in watch.rigs) else "scaled"
        _CLOCK_TALLY[kind] += 1
        if kind == "scaled":
            module = request.node.nodeid.split("::")[0].rsplit("/", 1)[-1]
            _SCALED_BY_MODULE[module] = _SCALED_BY_MODULE.get(module, 0) + 1
    audit = request.node.get_closest_marker("audit_violations_expected") is None
    problems = watch.problems(audit)
    if problems:
        pytest.fail("\n".join(problems), pytrace=False)


# -- the scan invariants ---------------------------------------------------------------------------


class _Delivered:
    """Every Scan the server completed during one test, per ScanSequencer, in order.

    Recording is all the server's thread does (an append under a lock): checking there would
    add to the administrator's time per scan, which timing-sensitive tests would feel.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._by_sequencer: dict[int, tuple[object, list[Scan]]] = {}

    def add(self, sequencer: object, scan: Scan) -> None:
        with self._lock:
            # the sequencer itself is kept so that its id is not reused within the test
            self._by_sequencer.setdefault(id(sequencer), (sequencer, []))[1].append(scan)

    def streams(self) -> list[list[Scan]]:
        with self._lock:
            return [list(scans) for _, scans in self._by_sequencer.values()]


_delivered: _Delivered | None = None
"""The running test's delivered scans; scans completed while it is set are recorded in it."""


@pytest.fixture(scope="session", autouse=True)
def _track_scans() -> Iterator[None]:
    """Record every Scan ``ScanSequencer.complete`` returns in the running test's log (patched
    once per session, as ``_track_rigs`` does, for the same reason)."""
    from biris_hw.server.scanning import ScanSequencer

    original = ScanSequencer.complete

    def tracked(self: ScanSequencer, scan: Any) -> Scan:
        result = original(self, scan)
        log = _delivered
        if log is not None:
            log.add(self, result)
        return result

    ScanSequencer.complete = tracked  # type: ignore[method-assign]
    yield
    ScanSequencer.complete = original  # type: ignore[method-assign]


def _returns_everywhere(rig: SimulatedBiris, options: dict[str, Any]) -> bool:
    """Whether every acquisition of ``rig`` must see light somewhere along its line, so that an
    all-zero row can only be a frame BIRIS never wrote: a round wall centred on the pan axis
    (:meth:`Scene.circle`), well within the optics' reach and bright enough there, and a head
    that does not travel. The margins (1.25x the closest range, 0.8x the furthest, twice the
    weakest return) leave room for the tilt, which lengthens the upper rows' depth, and for the
    range noise; the lower rows of a head tilted up to 60 degrees still see the wall."""
    if options.get("trajectory") is not None:
        return False
    shapes = rig.scene.shapes
    if len(shapes) != 1 or not isinstance(shapes[0], Cylinder):
        return False
    wall, optics = shapes[0], rig.optics.params
    brightness = optics.intensity_scale * wall.albedo / (0.8 * optics.max_range_m) ** 2
    return (
        tuple(wall.center) == (0.0, 0.0)
        and 1.25 * optics.min_range_m <= wall.radius <= 0.8 * optics.max_range_m
        and brightness >= 2.0 * optics.min_return
    )


def _scan_problems(log: _Delivered, watch: _Watch) -> list[str]:
    """The violations of every sequencer's stream of scans, by :class:`ScanChecker`.

    The rules that depend on the simulator are on only when every rig of the test allows them:
    "no all-zero row" needs a scene that returns light everywhere, "no row in two scans" needs
    the optics' noise (without it two sweeps over one azimuth give identical rows). A test with
    no rig feeds the server made-up acquisitions (the thread-free core: one profile, azimuths
    that climb whichever way the head turns), so only the server's bookkeeping is judged there
    (``physical=False``: an empty scan is partial, a partial one says why).
    """
    rigs = list(zip(watch.rigs, watch.rig_options, strict=True))
    expect_returns = bool(rigs) and all(_returns_everywhere(r, o) for r, o in rigs)
    repeats = all(o.get("noise", True) for _, o in rigs)
    found: list[str] = []
    for stream in log.streams():
        checker = ScanChecker(expect_returns=expect_returns, repeats=repeats, physical=bool(rigs))
        checker.extend(stream)
        if not checker.ok:
            shown = checker.violations[:20]
            cut = len(checker.violations) - len(shown)
            found.append(
                f"the server delivered scans that break the scan invariants "
                f"(biris_hw.scancheck; {checker.summary()}):\n  "
                + "\n  ".join(shown)
                + (f"\n  ... and {cut} more" if cut else "")
            )
    return found


@pytest.fixture(autouse=True)
def _scan_invariants(
    request: pytest.FixtureRequest, _track_scans: None, _leak_and_audit_check: _Watch
) -> Iterator[None]:
    """Check every scan the test's servers completed, at teardown (after every other fixture
    of the test: its servers have stopped by then, and its rigs are known to the watch)."""
    global _delivered
    log = _Delivered()
    _delivered = log
    try:
        yield
    finally:
        _delivered = None
    if request.node.get_closest_marker("scan_violations_expected") is not None:
        return
    problems = _scan_problems(log, _leak_and_audit_check)
    if problems:
        pytest.fail("\n".join(problems), pytrace=False)


@pytest.fixture
def no_leaks(_leak_and_audit_check: _Watch) -> None:
    """Fail the test if it leaves a thread or a file descriptor behind, rig or no rig.

    The baseline is taken again here unless a rig exists already, so fixtures listed before
    ``no_leaks`` may open what the process keeps for good (matplotlib's fonts, the resource
    tracker's pipe) without it counting as a leak.
    """
    watch = _leak_and_audit_check
    watch.check_leaks = True
    if not watch.rigs:
        watch.threads, watch.fds = _threads(), _fds()


# -- a simulated target and a server on it ---------------------------------------------------------

RigFactory = Callable[..., SimulatedBiris]


@pytest.fixture(
    params=[pytest.param(10.0, id="x10", marks=pytest.mark.slow), pytest.param(30.0, id="x30")]
)
def time_scale(request: pytest.FixtureRequest) -> float:
    """End-to-end tests run at two time scales: timing bugs show at one or the other.

    The fast tier (``make test``) runs x30 only: the report's rules are checked without threads
    in test_core_rules.py, so the end-to-end tier is there for what only real threads and scaled
    time show; ``make test-slow`` adds x10.
    """
    return float(request.param)


@pytest.fixture
def sim_clock(request: pytest.FixtureRequest, time_scale: float) -> str:
    """The clock ``make_rig`` gives a rig: virtual time (the run does not depend on the host's
    speed or load, docs/simulator.md), or scaled real time for a test marked ``realtime``
    (its point is real-time behaviour, or threads the time base cannot see). Virtual runs are
    the same at any nominal scale in all but timeouts, so the slow tier's x10 runs only the
    ``realtime`` tests."""
    if time_scale != 30.0:
        pytest.skip(
            "the x30 run is the run: on virtual time the scale is only nominal, and a "
            f"realtime test's scaled rigs run at x{SCALED_TIME_SCALE:g} at most"
        )
    if request.node.get_closest_marker("realtime") is not None:
        return "scaled"
    return "virtual"


@pytest.fixture
def make_rig(time_scale: float, sim_clock: str) -> Iterator[RigFactory]:
    """Build started rigs that are closed after the test (and checked like every rig): on the
    test's :func:`sim_clock`, unless the rig is one only scaled time can run (VM-USB, CAN, a
    crate) or the test names a clock itself."""
    rigs: list[SimulatedBiris] = []

    def make(**options: object) -> SimulatedBiris:
        options.setdefault("scene", Scene.circle(2.0))
        options.setdefault("time_scale", time_scale)
        scaled_only = (
            options.get("transport", "memory") != "memory"
            or options.get("axes", "hctl1000") != "hctl1000"
            or bool(options.get("crate", False))
        )
        options.setdefault("clock", "scaled" if scaled_only else sim_clock)
        if options["clock"] == "scaled":
            # real time: a host 0.1 s late must stay well inside the hardware's deadlines
            options["time_scale"] = min(float(options["time_scale"]), SCALED_TIME_SCALE)
        # seed 3 wakes the pan 170 counts from its index (seed 7: 1220, 0.33 s more homing at
        # x30 for every server); homing from afar and from either side has tests of its own
        options.setdefault("seed", 3)
        rig = SimulatedBiris(**options)  # type: ignore[arg-type]
        rigs.append(rig)
        return rig.start()

    yield make
    for rig in rigs:
        rig.close()


@pytest.fixture
def rig(make_rig: RigFactory) -> SimulatedBiris:
    return make_rig()


@pytest.fixture
def core() -> Core:
    """The administrator without threads (tests.core), initialised: the thread-free tier."""
    from tests.core import Core  # here, so tests below the server collect without it

    c = Core()
    c.initialise()
    return c


@pytest.fixture(scope="session")
def fonts_open(tmp_path_factory: pytest.TempPathFactory) -> None:
    """matplotlib keeps the font files it has used open for the life of the process (a cache,
    not a leak): draw once, in the first test that asks, before a leak check (``no_leaks``)
    takes its snapshot; they stay open for every later one."""
    from biris_hw.io.plots import save_polar

    save_polar(tmp_path_factory.mktemp("fonts") / "warm-up.png", [])


# -- the biris command, in-process -----------------------------------------------------------------

Run = Callable[..., tuple[int, str, str]]
"""``biris ARGS`` run in-process: (exit status, stdout, stderr)."""


@pytest.fixture
def no_target_env(monkeypatch: pytest.MonkeyPatch) -> None:
    """No BIRIS_TARGET from the shell running the tests: a command without --target means it."""
    from biris_hw.commands.options import TARGET_ENV

    monkeypatch.delenv(TARGET_ENV, raising=False)


SCALED_TIME_SCALE = 10.0
"""The fastest a test's simulator runs on scaled real time (``make_rig`` and the ``biris``
fixture): at x30 a host that is 0.13 s late (a loaded 2-core machine) is a whole BIRIS timeout
late, at x10 it takes 0.4 s."""

_CLI_ONE_SHOT = frozenset({"scan", "point", "home", "motor-params"})
"""Commands whose in-process simulator the ``biris`` fixture puts on virtual time (``--clock
virtual``): they ask, get an answer and end. The others serve or show the sensor as time passes
and keep scaled time, as they do for a user."""


@pytest.fixture
def biris(
    capsys: pytest.CaptureFixture[str], no_leaks: None, request: pytest.FixtureRequest
) -> Run:
    """Run ``biris ARGS`` in-process: (exit status, stdout, stderr); nothing may be left running.

    A one-shot command on ``--sim`` runs its simulator on virtual time unless the test is marked
    ``realtime`` or names a clock itself: what it answers then depends on the seed, not on the
    host's load."""
    from biris_hw.cli import main

    virtual = request.node.get_closest_marker("realtime") is None

    def run(*argv: str) -> tuple[int, str, str]:
        args = list(argv)
        if "--sim" in args and "--clock" not in args and "-h" not in args:
            if virtual and args[0] in _CLI_ONE_SHOT:
                args += ["--clock", "virtual"]
            elif "--time-scale" in args:
                # scaled time: a host 0.1 s late must stay well inside the 4 s BIRIS timeout
                at = args.index("--time-scale") + 1
                args[at] = str(min(float(args[at]), SCALED_TIME_SCALE))
        code = main(args)
        out, err = capsys.readouterr()
        return code, out, err

    return run


@pytest.fixture
def server(rig: SimulatedBiris) -> Iterator[BirisServer]:
    from biris_hw.server import BirisServer  # here, so tests below the server collect without it

    with BirisServer(rig.hardware, BirisInitRecord()) as srv:
        yield srv

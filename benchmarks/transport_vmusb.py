"""The server over USB: round trips per acquisition, the latency it survives, and the cost of one
register access through a (simulated) Wiener VM-USB.

Over the ``vmusb`` transport every register access is a bulk OUT and a bulk IN transfer, and
while an interrupt is armed the bridge must stop data taking around every immediate list. What
limits the driver there is the number of USB round trips and their latency, not Python speed,
so this section counts round trips and raises the modelled latency until something breaks:

* **round trips per acquisition** during the steady middle of a 360 degree single scan (between
  two REQUEST_POINTs, which read no register), in report mode and in continuous acquisition
  (Appendix D); target: at most 2 immediate lists per acquisition. The same over the whole scan
  (motion start, settling polls, commands) for context.
* **sustained rate**: continuous scanning at 128 samples (3 video fields, 19.98 acquisitions per
  hardware second) with a DATA connection, at the default modelled round trip and then at
  larger ones, until an acquisition is lost or the server faults: the ceiling is the largest
  round trip at which nothing was lost.
* **register access**: ``VmUsbWindow`` read8 / read16 / a 129-element frame against the
  in-memory window, on the host, with no interrupt armed (2 transfers) and with one armed
  (5: stop, last buffer, list, answer, start), and what the timing model charges for them.

Everything is the driver's real code through real pyusb; the far side is ``sim.vmusb``, whose
timing model charges each transfer ``latency + bytes / bandwidth`` of hardware time and waits it
in real time divided by time_scale.
"""

from __future__ import annotations

import math
import random
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from itertools import pairwise
from time import perf_counter_ns
from typing import Any

from benchmarks.common import HOME_NEAR_COUNTS, acquisition_period_s
from benchmarks.harness import (
    BenchContext,
    Figure,
    Target,
    benchmark,
    interleaved_rounds,
    percentile,
)
from benchmarks.registers import call_loop
from biris_hw import BirisInitRecord, BirisServer, ConnectionKind, DeliveryPolicy
from biris_hw.bus.memory import MemoryWindow
from biris_hw.bus.vmusb import VmUsbWindow
from biris_hw.client import Connection
from biris_hw.errors import BirisError
from biris_hw.irq.vmusb import VmUsbLine
from sim import Scene, SimulatedBiris
from sim.rig import USB_ROUND_TRIP_S, VME_MAP
from sim.vmusb import SimulatedVmUsb, VmUsbBackend

__all__ = ["register_costs", "transport_vmusb"]

SAMPLES = 128
TIME_SCALE = 3.0
"""x3 for the server figures. The simulated bridge waits out each transfer's modelled cost with
``Event.wait``, which on a 2-vCPU VM overshoots by ~0.09 ms of real time (timer slack), i.e.
~0.25 ms of hardware time per transfer at x3: the default round trip's figures are therefore
pessimistic (the counts are not affected), but at the >= 16 ms round trips where the ceiling
lies it is about 3 % of a transfer or less. x1 would be the most faithful but takes ~3x as
long."""
SCAN_DEG = -360.0
STEADY_FROM = 8
"""First acquisition (index in the scan) counted as the steady middle: the head is at speed."""
SWEEP_DEG = 45.0
MAX_LISTS_PER_ACQ = 2.0
POLL_S = 0.001
"""Wall seconds between REQUEST_POINTs (no bus traffic; one acquisition is ~17 ms at x3)."""
WAIT_S = 60.0
"""Wall seconds for anything that should take a few: only reached when something is broken."""
MODES = (
    ("report_mode", BirisInitRecord()),
    ("continuous_acquisition", BirisInitRecord(continuous_acquisition=True)),
)

_LOSS_COUNTERS = (
    "lost_acquisitions",
    "dropped_acquisitions",
    "stale_acquisitions",
    "aborted_acquisitions",
)
"""Server counters of acquisitions BIRIS made that no scan got: overwritten before they were
read, dropped, stale, or abandoned with a scan a fault ended."""


@benchmark("transport_vmusb")
def transport_vmusb(ctx: BenchContext) -> list[Figure]:
    """The VM-USB transport: lists per acquisition, the round-trip ceiling, access cost."""
    steady = ctx.pick(full=40, quick=12)
    sweeps = ctx.pick(full=3, quick=2)
    round_trips = (
        (USB_ROUND_TRIP_S, 1e-3, 2e-3, 4e-3, 8e-3, 16e-3, 32e-3)
        if not ctx.quick
        else (USB_ROUND_TRIP_S, 8e-3)
    )
    bisections = ctx.pick(full=2, quick=0)
    ctx.log("bench: transport_vmusb register access")
    figures = register_costs(rounds=ctx.pick(full=11, quick=3), batch_ms=ctx.pick(full=20, quick=5))
    for mode, record in MODES:
        with _usb_server(record) as (rig, server, device):
            ctx.log(f"bench: transport_vmusb.{mode} round trips per acquisition")
            figures += _per_acquisition(mode, rig, server, device, steady)
            ctx.log(f"bench: transport_vmusb.{mode} sustained rate")
            figures += _sustained(mode, rig, server, device, round_trips, bisections, sweeps, ctx)
    return figures


@contextmanager
def _usb_server(
    record: BirisInitRecord,
) -> Iterator[tuple[SimulatedBiris, BirisServer, SimulatedVmUsb]]:
    """A rig whose boards sit behind the simulated VM-USB, and an initialised server on it."""
    with SimulatedBiris(
        scene=Scene.circle(2.0),
        samples=SAMPLES,
        time_scale=TIME_SCALE,
        seed=1,
        initial_azimuth_counts=HOME_NEAR_COUNTS,
        transport="vmusb",
    ) as rig:
        device = rig.usb_device
        assert device is not None
        with BirisServer(rig.hardware, record) as server:
            yield rig, server, device


# -- what crossed the cable ----------------------------------------------------------------------


@dataclass(frozen=True)
class _Snap:
    """The bridge's counters, BIRIS's acquisition count and both clocks at one moment."""

    lists: int
    out: int
    inn: int
    irq: int
    nbytes: int
    busy_s: float
    made: int
    hw_s: float
    wall_s: float

    @classmethod
    def take(cls, rig: SimulatedBiris, device: SimulatedVmUsb) -> _Snap:
        c = device.counters
        return cls(
            c.immediate_lists,
            c.out_transfers,
            c.in_transfers,
            c.irq_events,
            c.bytes_out + c.bytes_in,
            device.modelled_busy_s,
            rig.supervisor.acquisitions_made,
            rig.clock.now(),
            time.perf_counter(),
        )

    def minus(self, other: _Snap) -> _Snap:
        return _Snap(
            self.lists - other.lists,
            self.out - other.out,
            self.inn - other.inn,
            self.irq - other.irq,
            self.nbytes - other.nbytes,
            self.busy_s - other.busy_s,
            self.made - other.made,
            self.hw_s - other.hw_s,
            self.wall_s - other.wall_s,
        )

    def per(self, n: int) -> dict[str, float]:
        """Counts per acquisition (``n`` of them), and the share of time the USB was busy."""
        return {
            "lists_per_acq": self.lists / n,
            "transfers_per_acq": (self.out + self.inn) / n,
            "out_per_acq": self.out / n,
            "in_per_acq": self.inn / n,
            "irq_events_per_acq": self.irq / n,
            "bytes_per_acq": self.nbytes / n,
            "usb_busy_percent": 100.0 * self.busy_s / self.hw_s if self.hw_s > 0 else 0.0,
        }


def _per_acquisition(
    mode: str, rig: SimulatedBiris, server: BirisServer, device: SimulatedVmUsb, steady: int
) -> list[Figure]:
    """Counters at each new REQUEST_POINT of a 360 degree single scan: the steady middle, and
    the whole scan from the command to idle."""
    with server.open() as conn:
        before = conn.request_point()
        t_before = before.t if before is not None else -math.inf
        acq0 = int(server.status().counters["acquisitions"])
        start = _Snap.take(rig, device)  # status() reads registers: counted from here
        conn.single_scan(SCAN_DEG)
        seen: list[tuple[int, _Snap]] = []
        deadline = time.monotonic() + WAIT_S
        while not seen or seen[-1][0] < STEADY_FROM + steady:
            point = conn.request_point()
            if point is not None and point.t > t_before and (not seen or point.acq > seen[-1][0]):
                seen.append((point.acq, _Snap.take(rig, device)))
            if time.monotonic() > deadline:
                raise TimeoutError(f"{mode}: {len(seen)} acquisitions in {WAIT_S:g} s")
            time.sleep(POLL_S)
        conn.wait_idle(timeout=WAIT_S)
        end = _Snap.take(rig, device)
        in_scan = int(server.status().counters["acquisitions"]) - acq0
    middle = [(acq, snap) for acq, snap in seen if acq >= STEADY_FROM]
    (a0, s0), (a1, s1) = middle[0], middle[-1]
    n = a1 - a0
    one = [b.lists - a.lists for (i, a), (j, b) in pairwise(middle) if j - i == 1]
    mid = s1.minus(s0)
    whole = end.minus(start)
    record = (
        "BirisInitRecord(continuous_acquisition=True)"
        if "continuous" in mode
        else ("the default BirisInitRecord (report mode)")
    )
    common = (
        f"{record}, transport='vmusb' at the default modelled round trip "
        f"({USB_ROUND_TRIP_S * 1e6:g} us), {SAMPLES} samples, time_scale {TIME_SCALE:g}; one "
        f"single_scan({SCAN_DEG:g}). Counts are the simulated bridge's own "
        "(device.counters): immediate lists run, bulk OUT and IN transfers, IRQ stack runs, "
        "bytes both ways; usb_busy_percent = the timing model's busy hardware time over the "
        "hardware time elapsed."
    )
    return [
        Figure(
            key=f"transport_vmusb.lists_per_acq_{mode}",
            values={
                **mid.per(n),
                "max_lists_one_acq": float(max(one)) if one else math.nan,
                "acquisitions": float(n),
            },
            unit="per acq",
            target=Target("<=", MAX_LISTS_PER_ACQ, on="lists_per_acq"),
            method=common
            + f" Steady middle: counters read at each new REQUEST_POINT (polled every "
            f"{POLL_S * 1e3:g} ms; it reads no register), from the scan's acquisition "
            f"{a0} to {a1}; per acquisition = difference / {n}. max_lists_one_acq = the most "
            "lists between two consecutive acquisitions.",
        ),
        Figure(
            key=f"transport_vmusb.whole_scan_{mode}",
            values={
                **whole.per(max(whole.made, 1)),
                "lists": float(whole.lists),
                "transfers": float(whole.out + whole.inn),
                "acquisitions_made": float(whole.made),
                "acquisitions_in_scan": float(in_scan),
                "hw_s": whole.hw_s,
            },
            unit="per acq",
            method=common
            + " Whole scan: from just before single_scan to wait_idle's return (motion start, "
            "settling polls, the acquisition commands, the data path), per acquisition BIRIS "
            "made meanwhile. No target: context for the steady figure.",
        ),
    ]


# -- the sustained rate and its ceiling ----------------------------------------------------------


@dataclass
class _Step:
    """Continuous scanning at one modelled round trip: what was made, read, lost, and why not."""

    round_trip_s: float
    delta: _Snap | None = None
    read: int = 0
    in_scans: int = 0
    lost: int = 0
    losses: dict[str, float] = field(default_factory=dict)
    client_dropped: int = 0
    sweeps: int = 0
    acq_in_sweeps: int = 0
    failure: str = ""

    @property
    def passed(self) -> bool:
        return not self.failure and self.lost == 0 and self.client_dropped == 0

    @property
    def ms(self) -> float:
        return self.round_trip_s * 1e3

    def why(self) -> str:
        if self.failure:
            return self.failure
        parts = [f"{k} {v:g}" for k, v in self.losses.items() if v]
        if self.client_dropped:
            parts.append(f"client dropped {self.client_dropped} scan(s)")
        return ", ".join(parts)


def _sustained(
    mode: str,
    rig: SimulatedBiris,
    server: BirisServer,
    device: SimulatedVmUsb,
    round_trips: tuple[float, ...],
    bisections: int,
    sweeps: int,
    ctx: BenchContext,
) -> list[Figure]:
    """Step the modelled round trip up until a step fails, then bisect (geometrically)."""
    default_latency = device.transfer_latency_s
    steps: list[_Step] = []
    with (
        server.open() as conn,
        server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64) as data,
    ):
        good: float | None = None
        bad: float | None = None
        todo = list(round_trips)
        while todo:
            rt = todo.pop(0)
            ctx.log(f"bench: transport_vmusb.{mode} at a {rt * 1e3:g} ms round trip")
            step = _step(rig, server, device, conn, data, rt, sweeps)
            steps.append(step)
            device.transfer_latency_s = default_latency
            if step.passed:
                good = rt if good is None else max(good, rt)
            else:
                bad = rt if bad is None else min(bad, rt)
                if not _recover(server, conn, ctx, mode):
                    break
                todo = []  # ascending: the rest would fail too; bisect instead
            if not todo and good is not None and bad is not None and bisections > 0:
                bisections -= 1
                todo = [math.sqrt(good * bad)]
    return [_step_figure(mode, s, sweeps) for s in steps] + [_ceiling_figure(mode, steps)]


def _step(
    rig: SimulatedBiris,
    server: BirisServer,
    device: SimulatedVmUsb,
    conn: Connection[Any],
    data: Connection[Any],
    round_trip_s: float,
    sweeps: int,
) -> _Step:
    step = _Step(round_trip_s)
    _drain(data)
    violations = len(rig.audit.violations), len(device.violations)
    counters0 = dict(server.status().counters)
    dropped0 = data.dropped
    device.transfer_latency_s = round_trip_s / 2.0  # the rig's model: half a round trip each way
    start = _Snap.take(rig, device)
    try:
        conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
        for _ in range(sweeps):
            scan = data.ready_for_data(timeout=WAIT_S)
            step.sweeps += 1
            step.acq_in_sweeps += int(getattr(scan, "n_acq", 0))
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT_S)
    except (BirisError, TimeoutError) as exc:
        step.failure = f"{type(exc).__name__}: {exc}"
    step.delta = _Snap.take(rig, device).minus(start)
    counters = server.status().counters
    diff = {k: int(counters.get(k, 0)) - int(counters0.get(k, 0)) for k in counters}
    step.read = diff.get("acquisitions_read", 0)
    step.in_scans = diff.get("acquisitions_in_scans", 0)
    step.losses = {k: float(diff.get(k, 0)) for k in _LOSS_COUNTERS}
    step.lost = int(sum(step.losses.values()))
    step.client_dropped = data.dropped - dropped0
    if not step.failure and int(diff.get("faults", 0)):
        step.failure = f"{diff['faults']} fault(s)"
    audit = rig.audit.violations[violations[0] :]
    usb = device.violations[violations[1] :]
    if not step.failure and (audit or usb):
        step.failure = f"audit: {(audit or usb)[0]}"
    return step


def _drain(data: Connection[Any]) -> None:
    """Scans of the last step's final sweep are that step's, not the next one's."""
    while True:
        try:
            data.ready_for_data(timeout=0)
        except (TimeoutError, BirisError):
            return


def _recover(server: BirisServer, conn: Connection[Any], ctx: BenchContext, mode: str) -> bool:
    """After a failed step: stop scanning, or reset out of a fault (at the default latency)."""
    try:
        if server.status().fault is not None:
            conn.reset()
        else:
            conn.stop_scan()
        conn.wait_idle(timeout=WAIT_S)
    except (BirisError, TimeoutError) as exc:
        ctx.log(f"bench: transport_vmusb.{mode}: no recovery ({exc}); search ends")
        return False
    return True


def _step_values(step: _Step) -> dict[str, float]:
    d = step.delta
    assert d is not None
    hw = d.hw_s if d.hw_s > 0 else math.nan
    return {
        "acq_per_hw_s": step.read / hw,
        "made_per_hw_s": d.made / hw,
        "in_scans_per_hw_s": step.in_scans / hw,
        "nominal_per_s": 1.0 / acquisition_period_s(SAMPLES),
        "lost_total": float(step.lost + step.client_dropped),
        **step.losses,
        "client_dropped_scans": float(step.client_dropped),
        "round_trip_ms": step.ms,
        "usb_busy_percent": 100.0 * d.busy_s / hw,
        "lists_per_acq": d.lists / step.read if step.read else math.nan,
        "sweeps": float(step.sweeps),
        "acq_per_sweep": step.acq_in_sweeps / step.sweeps if step.sweeps else 0.0,
        "made": float(d.made),
        "read": float(step.read),
        "hw_s": d.hw_s,
        "wall_s": d.wall_s,
    }


def _step_figure(mode: str, step: _Step, sweeps: int) -> Figure:
    failed = f" FAILED: {step.why()}." if not step.passed else ""
    return Figure(
        key=f"transport_vmusb.sustained_{mode}_rt_{round(step.round_trip_s * 1e6)}us",
        values=_step_values(step),
        unit="acq/hw s",
        target=Target("==", 0.0, on="lost_total"),
        method=f"Continuous scanning +-{SWEEP_DEG:g} degrees, {SAMPLES} samples, time_scale "
        f"{TIME_SCALE:g}, until {sweeps} buffers reached an EVERY_BUFFER DATA connection, then "
        f"stop_scan + wait_idle, with a modelled USB round trip of {step.ms:g} ms. acq_per_hw_s "
        "= acquisitions the server read off BIRIS per hardware second of the step; "
        "made_per_hw_s = those BIRIS made; in_scans_per_hw_s = those that reached a scan "
        "(turn-arounds, where the head stands, excluded); lost_total = the server's "
        f"{', '.join(_LOSS_COUNTERS)} and scans the client was not given.{failed}",
    )


def _ceiling_figure(mode: str, steps: list[_Step]) -> Figure:
    passed = [s for s in steps if s.passed]
    failed = [s for s in steps if not s.passed]
    best = max(passed, key=lambda s: s.round_trip_s, default=None)
    first_bad = min(failed, key=lambda s: s.round_trip_s, default=None)
    values: dict[str, float] = {
        "ceiling_ms": best.ms if best is not None else 0.0,
        "default_ms": USB_ROUND_TRIP_S * 1e3,
        "steps": float(len(steps)),
        "acq_per_hw_s_at_default": _step_values(steps[0])["acq_per_hw_s"],
    }
    if best is not None:
        at = _step_values(best)
        values["acq_per_hw_s_at_ceiling"] = at["acq_per_hw_s"]
        values["usb_busy_percent_at_ceiling"] = at["usb_busy_percent"]
    if first_bad is not None:
        values["first_failure_ms"] = first_bad.ms
        limit = f"{first_bad.ms:.3g} ms: {first_bad.why()}"
    else:
        limit = "none (every step passed: the ceiling is above the largest round trip tried)"
    tried = ", ".join(f"{s.ms:.3g}{'' if s.passed else '*'}" for s in steps)
    if best is None:
        note = f"{mode}: acquisitions lost even at the default round trip: {limit}."
    else:
        rate = (
            f"{values['acq_per_hw_s_at_ceiling']:.1f} acq per hardware s there, "
            f"{values['acq_per_hw_s_at_default']:.1f} at the default "
            f"{USB_ROUND_TRIP_S * 1e3:g} ms; USB {values['usb_busy_percent_at_ceiling']:.0f} % busy"
        )
        beyond = (
            f"first failure at {limit}"
            if first_bad is not None
            else "no larger round trip was tried"
        )
        note = (
            f"{mode}: nothing lost up to a {best.ms:.3g} ms modelled USB round trip ({rate}); "
            f"{beyond}."
        )
    return Figure(
        key=f"transport_vmusb.ceiling_{mode}",
        values=values,
        unit="ms",
        method=f"One rig and server for the mode, time_scale {TIME_SCALE:g}: the modelled "
        "round trip (SimulatedVmUsb.transfer_latency_s = half of it, as the rig sets it) raised "
        "between the sustained_* steps, doubling, then bisected geometrically between the "
        f"largest pass and the smallest failure (tried, ms: {tried}; * = failed). A step "
        "passes when nothing is lost (lost_total 0), the server did not fault and neither "
        "audit (hardware rules, USB protocol) caught anything; after a failure the server is "
        f"reset at the default latency. First failure: {limit}. ceiling_ms = the largest "
        "round trip that passed; no target (the issue sets none).",
        note=note,
    )


# -- one register access ---------------------------------------------------------------------------

_SIZE = 0x10000
_READ8_AT = 0x101
_READ16_AT = 0x100
_FRAME_AT = 0x1000
_FRAME_BYTES = 2 * 129
"""The closest sample and 128 samples along the laser line, as the data path reads them."""
_BASE, _AM, _BITS = VME_MAP["biris"]
_MODEL_CALLS = 20
"""Calls on the modelled-latency crate: its cost per call is fixed, 20 shows any spread."""


@dataclass
class _Crate:
    """A simulated VM-USB with one memory slave, and the driver's window on it."""

    device: SimulatedVmUsb
    backend: VmUsbBackend
    window: VmUsbWindow
    line: VmUsbLine | None = None

    def close(self) -> None:
        if self.line is not None:
            self.line.close()
        self.window.close()
        self.device.close()


def _crate(serial: str, memory: MemoryWindow, latency_s: float, *, free: bool = False) -> _Crate:
    """``free``: no bandwidth cost either, so the device never waits (host cost only);
    otherwise the device's default bandwidth, as the rig's."""
    if free:
        device = SimulatedVmUsb(
            serial=serial, transfer_latency_s=latency_s, bandwidth_bytes_per_s=math.inf
        )
    else:
        device = SimulatedVmUsb(serial=serial, transfer_latency_s=latency_s)
    try:
        device.map("biris", memory, _BASE, _BITS)
        backend = VmUsbBackend(device)
        window = VmUsbWindow(_SIZE, base=_BASE, am=_AM, serial=serial, backend=backend)
    except BaseException:
        device.close()
        raise
    return _Crate(device, backend, window)


def register_costs(*, rounds: int, batch_ms: int) -> list[Figure]:
    """read8, read16 and a frame through VmUsbWindow against MemoryWindow, IRQ unarmed/armed.

    Two crates on the same memory: one with no modelled cost (what the host spends: driver,
    pyusb and the simulated bridge's Python), timed against the memory window in interleaved
    rounds; one with the rig's default timing model at x1, whose modelled_busy_s gives the
    hardware cost and whose real time per call shows what waiting it out costs here.
    """
    memory = MemoryWindow(_SIZE)
    memory.write(0, random.Random(13).randbytes(_SIZE))
    host = _crate("VMBENCH1", memory, 0.0, free=True)
    try:
        modelled = _crate("VMBENCH2", memory, USB_ROUND_TRIP_S / 2.0)
    except BaseException:
        host.close()
        raise
    figures: list[Figure] = []
    try:
        ops: list[tuple[str, Callable[[VmUsbWindow | MemoryWindow], Callable[[], object]]]] = [
            ("read8", lambda w: lambda: w.read8(_READ8_AT)),
            ("read16", lambda w: lambda: w.read16(_READ16_AT)),
            ("frame129", lambda w: lambda: w.read(_FRAME_AT, _FRAME_BYTES)),
        ]
        for name, op in ops:
            if op(host.window)() != op(memory)() or op(modelled.window)() != op(memory)():
                raise RuntimeError(f"{name}: the VM-USB window and the memory disagree")
        for armed in (False, True):
            if armed:  # an armed IRQ: data taking runs, so every list is stopped around
                host.line = VmUsbLine(level=3, vector=0x40, backend=host.backend)
                modelled.line = VmUsbLine(level=3, vector=0x40, backend=modelled.backend)
            for name, op in ops:
                figures.append(
                    _register_figure(
                        name, armed, op(host.window), op(memory), host.device,
                        op(modelled.window), modelled.device, rounds, batch_ms,
                    )
                )  # fmt: skip
    finally:
        host.close()
        modelled.close()
    return figures


def _register_figure(
    name: str,
    armed: bool,
    usb_op: Callable[[], object],
    mem_op: Callable[[], object],
    host: SimulatedVmUsb,
    model_op: Callable[[], object],
    model: SimulatedVmUsb,
    rounds: int,
    batch_ms: int,
) -> Figure:
    batch_ns = batch_ms * 1_000_000
    loops = {"vmusb": call_loop(usb_op), "memory": call_loop(mem_op)}
    sizes = {k: _batch_size(run, batch_ns) for k, run in loops.items()}
    c = host.counters
    out0, in0 = c.out_transfers, c.in_transfers
    ns = interleaved_rounds({k: _per_call(loops[k], sizes[k]) for k in loops}, rounds)
    calls = sizes["vmusb"] * rounds
    out_per, in_per = (c.out_transfers - out0) / calls, (c.in_transfers - in0) / calls
    busy0 = model.modelled_busy_s
    real = []
    for _ in range(_MODEL_CALLS):
        t0 = perf_counter_ns()
        model_op()
        real.append(perf_counter_ns() - t0)
    modelled_us = (model.modelled_busy_s - busy0) / _MODEL_CALLS * 1e6
    usb_ns, mem_ns = percentile(ns["vmusb"], 50), percentile(ns["memory"], 50)
    paired = [u / m for u, m in zip(ns["vmusb"], ns["memory"], strict=True)]
    expected = 5.0 if armed else 2.0
    what = (
        "one IRQ line armed (VmUsbLine level 3): data taking runs, so each access is stop "
        "(OUT), last buffer (IN, the reader thread), list (OUT), answer (IN), start (OUT)"
        if armed
        else "no IRQ armed: each access is one list (OUT) and its answer (IN)"
    )
    return Figure(
        key=f"transport_vmusb.register_{name}{'_irq_armed' if armed else ''}",
        values={
            "vmusb_us": usb_ns / 1e3,
            "memory_us": mem_ns / 1e3,
            "ratio_vs_memory": usb_ns / mem_ns,
            "ratio_p10": percentile(paired, 10),
            "ratio_p90": percentile(paired, 90),
            "transfers_per_call": out_per + in_per,
            "out_per_call": out_per,
            "in_per_call": in_per,
            "modelled_hw_us": modelled_us,
            "real_us_at_x1": statistics.median(real) / 1e3,
            "rounds": float(rounds),
        },
        unit="per call",
        target=Target("==", expected, on="transfers_per_call"),
        method=f"VmUsbWindow.{'read' if name == 'frame129' else name} (A32 at the rig's BIRIS "
        f"base; frame129 = read of {_FRAME_BYTES} bytes, D32 block transfer) on a simulated "
        f"VM-USB whose memory slave is a MemoryWindow, {what}. vmusb_us / memory_us = real "
        "microseconds per call on this host (median over interleaved rounds of tight loops "
        f"of ~{batch_ms} ms, GC off), the VM-USB crate with no modelled cost (driver + pyusb + "
        "the simulated bridge's Python; libusb and the kernel would replace the last on a real "
        "bridge) against MemoryWindow on the same bytes; ratio_vs_memory = vmusb_us / "
        "memory_us. transfers_per_call counted by the device. modelled_hw_us = what the "
        f"timing model charges (default {USB_ROUND_TRIP_S * 1e6:g} us per OUT+IN pair plus "
        f"bytes at its bandwidth), from a second crate at x1 ({_MODEL_CALLS} calls); "
        "real_us_at_x1 = their median real time (the model's waits plus the host's own "
        "cost and timer overshoot).",
    )


def _per_call(run: Callable[[int], int], n: int) -> Callable[[], float]:
    return lambda: run(n) / n


def _batch_size(run: Callable[[int], int], batch_ns: int) -> int:
    """Calls per batch so one lasts about ``batch_ns``; warms the contender up as well."""
    n = 4
    while True:
        took = max(run(n), 1)
        if took >= batch_ns // 10 or n >= 1 << 26:
            return max(1, math.ceil(n * batch_ns / took))
        n *= 4

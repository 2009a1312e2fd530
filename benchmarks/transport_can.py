"""The axes over CAN: frames per move and per acquisition, move start latency, sustained rate.

With ``SimulatedBiris(axes="canopen")`` pan and tilt are CiA 402 drives on a python-can
``virtual`` channel; the driver reaches them through canopen only. What a CAN axis costs is bus
traffic and round trips in *real* time (CAN does not run on the simulator's clock), so:

* **frames per move**: every frame on the channel, by kind (SDO, PDO, heartbeat, NMT/EMCY),
  counted by a listener of its own on the channel from just before a 90 degree single scan to
  ``wait_idle``'s return; the same during the steady middle of a long scan, per acquisition
  (the data path never touches the CAN bus: what remains is heartbeats and nothing else).
* **move start latency**: ``start_trapezoid`` from call to return -- on CAN an RPDO, the
  drive's set-point acknowledge in its event TPDO, and the RPDO clearing the new-set-point bit
  -- against the HCTL-1000's ``start_trapezoid`` on the in-memory Model 7600, interleaved.
* **sustained rate**: continuous scanning with a DATA connection taking every buffer, in
  acquisitions per hardware second against the sensor's nominal rate, and any loss.
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can

from benchmarks.common import HOME_NEAR_COUNTS
from benchmarks.harness import BenchContext, Figure, Target, benchmark, percentile
from biris_hw import BirisServer, ConnectionKind, DeliveryPolicy
from biris_hw.records import MotorParams
from regs.layout import acquisition_period_s
from regs.tech80 import DEFAULT_IRQ_VECTOR, Axis
from sim import Scene, SimulatedBiris

__all__ = ["transport_can"]

TIME_SCALE = 10.0
SAMPLES = 64
WAIT_S = 60.0
SCAN_DEG = 90.0
LONG_SCAN_DEG = -360.0
STEADY_FROM = 8
SWEEP_DEG = 45.0


def _kind(can_id: int) -> str:
    """A CANopen frame's kind by its COB-ID (CiA 301's predefined connection set)."""
    function = can_id & 0x780
    if function in (0x580, 0x600):
        return "sdo"
    if 0x180 <= function <= 0x500:
        return "pdo"
    if function == 0x700:
        return "heartbeat"
    return "nmt_emcy_sync"


class _FrameCounter(can.Listener):
    """Counts every frame seen on a virtual channel, by kind."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self._counts[_kind(int(msg.arbitration_id))] += 1

    def snapshot(self) -> Counter[str]:
        with self._lock:
            return Counter(self._counts)


@contextmanager
def _counting(channel: str) -> Iterator[_FrameCounter]:
    """A listener on ``channel`` (a bus of its own: it hears every other bus on the channel)."""
    bus = can.Bus(interface="virtual", channel=channel)
    counter = _FrameCounter()
    notifier = can.Notifier(bus, [counter], timeout=0.02)
    try:
        yield counter
    finally:
        notifier.stop()
        bus.shutdown()


def _diff(after: Counter[str], before: Counter[str]) -> dict[str, float]:
    kinds = ("sdo", "pdo", "heartbeat", "nmt_emcy_sync")
    out = {k: float(after[k] - before[k]) for k in kinds}
    out["total"] = sum(out.values())
    return out


@benchmark("transport_can")
def transport_can(ctx: BenchContext) -> list[Figure]:
    """CiA 402 axes on a virtual CAN bus: frames, move start latency, sustained rate."""
    figures: list[Figure] = []
    with SimulatedBiris(
        scene=Scene.circle(2.0),
        samples=SAMPLES,
        time_scale=TIME_SCALE,
        seed=1,
        initial_azimuth_counts=HOME_NEAR_COUNTS,
        axes="canopen",
    ) as rig:
        assert rig.can_channel is not None
        with _counting(rig.can_channel) as counter, BirisServer(rig.hardware) as server:
            ctx.log("bench: transport_can frames per move and per acquisition")
            figures += _frames(rig, server, counter, ctx.pick(full=5, quick=2))
            ctx.log("bench: transport_can sustained rate")
            can_rate = _sustained(rig, server, ctx.pick(full=8, quick=3))
        assert not rig.audit.violations and not rig.drive_violations, "the run broke a rule"
    with (
        SimulatedBiris(
            scene=Scene.circle(2.0),
            samples=SAMPLES,
            time_scale=TIME_SCALE,
            seed=1,
            initial_azimuth_counts=HOME_NEAR_COUNTS,
        ) as rig,
        BirisServer(rig.hardware) as server,
    ):
        ctx.log("bench: transport_can sustained rate, in-memory board for comparison")
        memory_rate = _sustained(rig, server, ctx.pick(full=8, quick=3))
    figures.append(_rate_figure(can_rate, memory_rate, ctx.pick(full=8, quick=3)))
    ctx.log("bench: transport_can move start latency")
    figures.append(_start_latency(ctx.pick(full=40, quick=10)))
    return figures


def _frames(
    rig: SimulatedBiris, server: BirisServer, counter: _FrameCounter, moves: int
) -> list[Figure]:
    per_move: list[dict[str, float]] = []
    with server.open() as conn:
        for i in range(moves):
            before, t0 = counter.snapshot(), time.perf_counter()
            conn.single_scan(SCAN_DEG if i % 2 == 0 else 0.0)
            conn.wait_idle(timeout=WAIT_S)
            counts = _diff(counter.snapshot(), before)
            counts["wall_s"] = time.perf_counter() - t0
            per_move.append(counts)
        # the steady middle of a long scan: what the bus carries per acquisition
        first = conn.request_point()
        t_first = first.t if first is not None else -1.0
        conn.single_scan(LONG_SCAN_DEG)
        marks: list[tuple[int, Counter[str], float]] = []
        deadline = time.monotonic() + WAIT_S
        while len(marks) < 2:
            point = conn.request_point()
            if point is not None and point.t > t_first:
                due = STEADY_FROM if not marks else marks[0][0] + 40
                if point.acq >= due:
                    marks.append((point.acq, counter.snapshot(), time.perf_counter()))
            if time.monotonic() > deadline:
                raise TimeoutError("transport_can: the long scan did not progress")
            time.sleep(0.002)
        conn.wait_idle(timeout=WAIT_S)
    (a0, c0, w0), (a1, c1, w1) = marks
    n = a1 - a0
    mid = _diff(c1, c0)
    mean = {k: sum(m[k] for m in per_move) / len(per_move) for k in per_move[0]}
    common = (
        f"SimulatedBiris(axes='canopen', samples={SAMPLES}, time_scale={TIME_SCALE:g}): two "
        "simulated CiA 402 drives on a python-can virtual channel, the driver's Cia402Axes on "
        "the same channel; frames counted by a third virtual bus on the channel (it hears "
        "every frame), by COB-ID: SDO 0x580/0x600, PDO 0x180-0x57F, heartbeat 0x700, the "
        f"rest NMT/EMCY/SYNC. The rig's heartbeat period is "
        f"{0.05 * 1e3:g} ms real for the host and each drive (60 frames/s whatever happens)."
    )
    return [
        Figure(
            key="transport_can.frames_per_move",
            values={**mean, "moves": float(len(per_move))},
            unit="frames",
            method=common
            + f" One move = single_scan alternately to {SCAN_DEG:g} and 0 degrees, from "
            "the request to wait_idle's return (set-point handshake, the end-of-motion TPDO, "
            "the settling polls by SDO, the acquisition sequence); mean over the moves.",
            note="A move costs a handful of PDOs; the settling polls (two SDO reads per poll) "
            "are most of its frames.",
        ),
        Figure(
            key="transport_can.frames_per_acq",
            values={
                **{k: v / n for k, v in mid.items()},
                "acquisitions": float(n),
                "wall_s": w1 - w0,
            },
            unit="frames per acq",
            target=Target("<=", 0.0, on="pdo"),
            method=common + f" Steady middle of a single_scan({LONG_SCAN_DEG:g}): counters at the "
            f"REQUEST_POINT of acquisition {a0} and of {a1}; per acquisition = difference / "
            f"{n}. No PDO may cross during a sweep: the move was started before it.",
        ),
    ]


def _sustained(rig: SimulatedBiris, server: BirisServer, sweeps: int) -> dict[str, float]:
    """Continuous scanning with a DATA connection taking every buffer: the rate BIRIS made
    acquisitions at (per hardware second), those that reached scans, and any loss."""
    with (
        server.open() as conn,
        server.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_BUFFER, depth=64) as data,
    ):
        conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
        data.ready_for_data(timeout=WAIT_S)  # the first sweep may start off-centre
        made0, hw0 = rig.supervisor.acquisitions_made, rig.clock.now()
        counters0 = dict(server.status().counters)
        acqs = dropped = 0
        for _ in range(sweeps):
            scan = data.ready_for_data(timeout=WAIT_S)
            acqs += len(scan.azimuth)
            dropped += scan.dropped
        made, hw_s = rig.supervisor.acquisitions_made - made0, rig.clock.now() - hw0
        counters = dict(server.status().counters)
        conn.stop_scan()
        conn.wait_idle(timeout=WAIT_S)
    lost = sum(
        float(counters.get(k, 0)) - float(counters0.get(k, 0))
        for k in ("lost_acquisitions", "dropped_acquisitions", "stale_acquisitions")
    )
    return {
        "made_per_hw_s": made / hw_s,
        "in_scans_per_hw_s": acqs / hw_s,
        "lost": lost + dropped,
    }


def _rate_figure(can_rate: dict[str, float], memory: dict[str, float], sweeps: int) -> Figure:
    nominal = 1.0 / acquisition_period_s(SAMPLES)
    return Figure(
        key="transport_can.sustained",
        values={
            **{f"can_{k}": v for k, v in can_rate.items()},
            **{f"memory_{k}": v for k, v in memory.items()},
            "nominal_per_hw_s": nominal,
            "ratio": can_rate["in_scans_per_hw_s"] / memory["in_scans_per_hw_s"],
        },
        unit="acq/s",
        target=Target(">=", 0.95, on="ratio"),
        method=f"continuous_scan(+-{SWEEP_DEG:g}), report mode, with a DATA connection "
        f"(EVERY_BUFFER, depth 64) taking {sweeps} sweeps after the first, on the CAN rig and "
        f"then on the in-memory Model 7600 rig (same seed, {SAMPLES} samples, time_scale "
        f"{TIME_SCALE:g}): acquisitions BIRIS made and acquisitions delivered in scans, per "
        "hardware second, and losses (the server's lost/dropped/stale counters plus the "
        "client's dropped). ratio = CAN's delivered rate over the board's. Report mode "
        "acquires only while the head sweeps, so neither reaches the nominal rate: every "
        "turn-round costs a move and BIRIS's start-up.",
    )


def _start_latency(moves: int) -> Figure:
    """start_trapezoid's call-to-return, CAN against the in-memory HCTL-1000, interleaved."""
    samples: dict[str, list[float]] = {"can": [], "memory": []}
    with (
        SimulatedBiris(time_scale=TIME_SCALE, seed=2, initial_azimuth_counts=0.0) as mem,
        SimulatedBiris(
            time_scale=TIME_SCALE, seed=2, initial_azimuth_counts=0.0, axes="canopen"
        ) as canrig,
    ):
        movers = {"memory": _mover(mem), "can": _mover(canrig)}
        for i in range(moves):
            dest = 200 if i % 2 == 0 else 0
            order = ("can", "memory") if i % 2 == 0 else ("memory", "can")
            for name in order:
                samples[name].append(movers[name](dest))
        bad = mem.audit.violations + canrig.audit.violations
        assert not bad and not canrig.drive_violations, "the latency run broke a rule"
    values: dict[str, float] = {}
    for name, xs in samples.items():
        values[f"{name}_p50_us"] = percentile(xs, 50) * 1e6
        values[f"{name}_p99_us"] = percentile(xs, 99) * 1e6
    values["ratio_p50"] = values["can_p50_us"] / values["memory_p50_us"]
    return Figure(
        key="transport_can.move_start_latency",
        values=values,
        unit="us",
        method=f"{moves} moves of 200 counts each way, per transport, interleaved (alternating "
        "who goes first); the time of start_trapezoid's call alone, on the devices the "
        "hardware bundle builds (no server): on CAN an RPDO with the target and the "
        "new-set-point bit, the wait for set-point acknowledge in the drive's event TPDO, and "
        "the RPDO that clears the bit; on the in-memory Model 7600 the HCTL-1000's register "
        "writes. Each move is waited out (end of motion, settled) before the next.",
        note="CAN's handshake is a frame round trip through the receive threads of both ends.",
    )


def _mover(rig: SimulatedBiris) -> Callable[[int], float]:
    """Configure and hold a rig's pan through its devices; return a timed move function."""
    devices = rig.hardware.devices
    pan, board = devices.azimuth, devices.board
    board.reset_chip(Axis.AZIMUTH)
    pan.configure(MotorParams())
    pan.wait_still(threading.Event())
    pan.hold_here()
    board.acknowledge(Axis.AZIMUTH)
    board.enable_end_of_scan(Axis.AZIMUTH, DEFAULT_IRQ_VECTOR)
    line = rig.hardware.level3
    stop = threading.Event()

    def move(dest: int) -> float:
        t0 = time.perf_counter()
        pan.start_trapezoid(dest)
        took = time.perf_counter() - t0
        if not line.wait(WAIT_S):
            raise TimeoutError("no end of motion")
        board.acknowledge(Axis.AZIMUTH)
        if not pan.wait_settled(stop):
            raise RuntimeError(f"the pan did not settle at {dest}")
        return took

    return move

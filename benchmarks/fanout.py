"""Fan-out: how long the last of 1, 10 or 100 DATA clients waits for a completed scan buffer.

Every DATA connection is handed each completed buffer (the administrator replies to every
parked READY_FOR_DATA in turn), so the delivery to the last client grows with the number of
clients; this measures by how much. One client thread per connection, each blocked in
ready_for_data, continuous 90 degree sweeps.

**Latency** = the client's ready_for_data return minus the moment the buffer was complete, both
perf_counter_ns. A buffer is complete when BIRIS has finished its acquisition sequence (the
command-completion interrupt, timestamped as the simulator raises it) *and* the motor has ended
its move (the end-of-profile interrupt); whichever came later, usually the former because the
240 ms start-up puts the last acquisition after the motor's arrival. So the figure holds the
whole server path: demultiplexer, command notifier, final drain, administrator building the
Scan, one reply per client, and each client thread waking up (100 threads on one GIL).

time_scale 5: buffers complete five times as often as on the sensor (one every ~0.22 s instead
of ~1.1 s), which gives more samples per second of run; latencies are wall-clock, which is what
they would be at time_scale 1 since the server's work per buffer does not depend on the scale
(the simulator runs five times as fast beside it, so if anything the figures are pessimistic).
"""

from __future__ import annotations

import bisect
import threading
import time
from dataclasses import dataclass

from benchmarks.common import Bench, IrqRecorder, running_server
from benchmarks.harness import BenchContext, Figure, Target, benchmark, summarise
from biris_hw import ConnectionKind
from biris_hw.client import Connection

__all__ = ["fanout"]

SAMPLES = 64
SWEEP_DEG = 45.0
TIME_SCALE = 5.0
CLIENTS = (1, 10, 100)
TARGET_100 = Target("<=", 5.0, on="p99")
MATCH_LIMIT_NS = 1_000_000_000
"""A delivery later than this after its buffer's completion is not matched (counted)."""


@dataclass(frozen=True)
class _Received:
    t_call_ns: int
    """When the client entered ready_for_data: a buffer complete before that was not waited
    for, and its delay is the client's, not the server's."""
    t_ns: int
    t_first: float
    """Hardware time of the scan's first acquisition (identifies its sequence)."""


@benchmark("fanout")
def fanout(ctx: BenchContext) -> list[Figure]:
    """Buffer completion to READY_FOR_DATA return for 1, 10 and 100 DATA clients."""
    buffers = {1: ctx.pick(full=40, quick=6), 10: ctx.pick(full=30, quick=5)}
    buffers[100] = ctx.pick(full=20, quick=4)
    figures: list[Figure] = []
    with (
        running_server(samples=SAMPLES, time_scale=TIME_SCALE) as bench,
        IrqRecorder(bench.rig) as irq,
    ):
        conn = bench.server.open()
        try:
            for n in CLIENTS:
                ctx.log(f"bench: fanout with {n} client(s)")
                figures.append(_phase(bench, irq, conn, n, buffers[n]))
        finally:
            conn.close()
    return figures


def _phase(bench: Bench, irq: IrqRecorder, conn: Connection, n: int, wanted: int) -> Figure:
    """n clients, each until it has received ``wanted`` buffers; then stop and wait for idle."""
    ready = threading.Barrier(n + 1)
    # No client closes its connection before every client has its last buffer: n CLOSE_REQUESTs
    # sent while the last buffer is still being handed round would compete with its deliveries,
    # and the phase's final round (which holds the slowest of its deliveries, that is, much of
    # its p99) would measure the tear-down instead of the fan-out.
    finished = threading.Barrier(n)
    received: list[list[_Received]] = [[] for _ in range(n)]
    dropped = [0] * n
    cpu_s = [0.0] * n
    errors: list[BaseException] = []
    stop = threading.Event()

    def client(i: int) -> None:
        data: Connection | None = None
        try:
            data = bench.server.open(ConnectionKind.DATA)
            ready.wait()
            cpu0 = time.thread_time()
            while len(received[i]) < wanted and not stop.is_set():
                called = time.perf_counter_ns()
                try:
                    scan = data.ready_for_data(timeout=1.0)
                except TimeoutError:
                    continue
                now = time.perf_counter_ns()
                if scan.n_acq:
                    received[i].append(_Received(called, now, float(scan.t[0])))
            dropped[i] = data.dropped
            cpu_s[i] = time.thread_time() - cpu0
            try:
                finished.wait(timeout=60.0 + wanted * 2.0)
            except threading.BrokenBarrierError:
                pass  # another client failed (its error is reported) or the phase timed out
        except BaseException as exc:
            errors.append(exc)
            ready.abort()
            finished.abort()
        finally:
            if data is not None:
                data.close()

    threads = [
        threading.Thread(target=client, args=(i,), name=f"bench-fanout-{i}") for i in range(n)
    ]
    for thread in threads:
        thread.start()
    try:
        ready.wait(timeout=30.0)
        irq.clear()
        with bench.cpu() as cpu:
            conn.continuous_scan(-SWEEP_DEG, SWEEP_DEG)
            deadline = time.perf_counter() + 60.0 + wanted * 2.0
            for thread in threads:
                thread.join(timeout=max(0.0, deadline - time.perf_counter()))
    finally:
        stop.set()
        for thread in threads:
            thread.join()
        conn.stop_scan()
        conn.wait_idle(timeout=30.0)
    if errors:
        raise errors[0]
    latencies, motor_last, unmatched, not_waiting = _latencies(irq, received)
    if not latencies:
        raise RuntimeError(f"no delivery to {n} client(s) could be matched to its buffer")
    values = {"clients": float(n), **summarise(latencies)}
    values["p99_ms"] = values["p99"]
    values.update({k: v for k, v in cpu.values.items() if k.endswith("_percent")})
    values["client_cpu_percent"] = 100.0 * sum(cpu_s) / cpu.values["wall_s"]
    values["client_dropped"] = float(sum(dropped))
    values["unmatched"] = float(unmatched)
    values["not_waiting"] = float(not_waiting)
    method = (
        f"{n} client thread(s), each with its own DATA connection blocked in ready_for_data, "
        f"{wanted} buffers each; continuous scanning +-{SWEEP_DEG:g} degrees, {SAMPLES} "
        f"samples, time_scale {TIME_SCALE:g} (buffers 5x as often as on the sensor); ms of wall "
        "time. Latency = return of ready_for_data minus the buffer's completion: the later of "
        "the simulator raising BIRIS's command-completion interrupt for that sequence and the "
        f"motor's end-of-profile interrupt (motor later {motor_last} time(s)), both "
        "perf_counter_ns. p99 pools every client's deliveries. cpu_percent = process CPU / wall "
        "while scanning (simulator included; 100 = one core); server_, sim_, client_ = their "
        "threads' share (clients: their own thread_time). client_dropped = buffers replaced "
        "before a client asked again; not_waiting = deliveries of a buffer completed before "
        "the client was back in ready_for_data (the client's delay, left out). No connection "
        "is closed before every client has its last buffer, so the tear-down is not measured."
    )
    return Figure(
        key=f"fanout.clients_{n}",
        values=values,
        unit="ms",
        target=TARGET_100 if n == 100 else None,
        method=method,
    )


def _latencies(
    irq: IrqRecorder, received: list[list[_Received]]
) -> tuple[list[float], int, int, int]:
    """Latency (ms) of every delivery; how many buffers the motor completed; how many
    deliveries were unmatched, and how many the client was not yet waiting for.

    A sequence's completion interrupt is the first command interrupt after its first
    acquisition (nothing but BI_ACQUIRE runs while scanning); its move ends with the first
    end-of-profile interrupt after that acquisition (the move started with the sequence, and
    the next one starts only after this buffer is complete).
    """
    cmd_hw = [hw for _, hw in irq.cmd]
    motor_hw = [hw for _, hw in irq.motor]
    latencies: list[float] = []
    motor_last: set[float] = set()
    unmatched = not_waiting = 0
    for per_client in received:
        for got in per_client:
            i = bisect.bisect_right(cmd_hw, got.t_first)
            if i >= len(irq.cmd):
                unmatched += 1
                continue
            done_ns = irq.cmd[i][0]
            j = bisect.bisect_right(motor_hw, got.t_first)
            if j < len(irq.motor) and done_ns < irq.motor[j][0] <= got.t_ns:
                done_ns = irq.motor[j][0]
                motor_last.add(got.t_first)
            if done_ns < got.t_call_ns:
                not_waiting += 1
                continue
            latency = got.t_ns - done_ns
            if not 0 < latency <= MATCH_LIMIT_NS:
                unmatched += 1
                continue
            latencies.append(latency / 1e6)
    return latencies, len(motor_last), unmatched, not_waiting

"""Recording, replay and live view: throughput, file size, and the latency they add.

* **throughput** -- the simulator at 128 samples (20 acquisitions per hardware second) runs
  faster than real time while a :class:`~biris_hw.io.record.Recorder` records continuous sweeps;
  the figure is the highest time scale of a ladder (x20, x40, ... until a rung fails) at which
  the recorder wrote every acquisition (its connections dropped none) while the simulator kept
  its rate: the recording rate as a multiple of the sensor's real one. When the simulator is
  what fails, the figure is a floor and the method says so.
* **replay** -- a :class:`~biris_hw.io.record.ReplayServer` at ``speed=None`` read by an
  EVERY_ACQUISITION client: acquisitions per second, as a multiple of the real rate.
* **size** -- the file's bytes per minute of hardware-time scanning (128 samples, profiles on).
* **latency** -- the every-acquisition path of :mod:`benchmarks.latency` (interrupt raise to a
  client holding the Point, time_scale 1, 64 samples) without, with a recorder and with a live
  view (a WebSocket client subscribed to every channel), in interleaved rounds of one run; the
  ratio of p50s.
"""

from __future__ import annotations

import json
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

from benchmarks.common import IrqRecorder, acquisition_period_s, running_server
from benchmarks.harness import BenchContext, Figure, Target, benchmark, percentile
from benchmarks.latency import _every_acquisition
from biris_hw import ConnectionKind, DeliveryPolicy
from biris_hw.errors import BirisError
from biris_hw.io.record import Recorder
from biris_hw.io.record.replay import EndOfRecording, ReplayServer

__all__ = ["record"]

REAL_RATE_128 = 59.94 / 3  # acquisitions per hardware second at 128 samples


LADDER = (20.0, 40.0, 80.0, 160.0, 320.0, 640.0)
"""Time scales tried in turn (128 samples: 20 acquisitions per hardware second at x1) until
one fails."""
BISECT_WITHIN = 1.3
"""After the first failing rung, rungs between it and the last pass are tried (geometric
middle) until they are within this factor..."""
BISECTIONS = 3
"""... or this many have been tried."""
KEEP_UP = 0.1
"""As benchmarks.throughput: the simulator kept up when its in-sequence rate was within this
share of nominal and no data interrupt came later than this share of the window."""


@benchmark("record")
def record(ctx: BenchContext) -> list[Figure]:
    """Recording throughput, replay throughput, file size, added latency of recorder/live view."""
    figures: list[Figure] = []
    seconds = float(ctx.pick(full=6, quick=3))
    ladder = list(LADDER[:3] if ctx.quick else LADDER)
    ctx.log("bench: record.throughput")
    best, runs, file, why = _throughput(ctx.work_dir, ladder, seconds)
    figures.append(
        Figure(
            key="record.throughput",
            values={"ratio": best, **runs},
            unit="x real rate",
            target=Target(">=", 20.0, on="ratio"),
            method=(
                f"128 samples, continuous sweeps -45..+45 deg, Recorder with profiles on, "
                f"{seconds:g} real s per rung of the time-scale ladder {ladder}, climbed until a "
                "rung fails; ratio = the highest time scale at which (a) the recorder's two "
                "DATA connections dropped no acquisition and no scan (server-counted) and "
                "wrote every acquisition the server delivered (points_xN == "
                "server_acquisitions_xN), and (b) the simulator kept up (in-sequence "
                f"interrupt rate >= {1 - KEEP_UP:g} x nominal and no data interrupt later than "
                f"{KEEP_UP:g} x the window, as throughput.ceiling checks), i.e. acquisitions "
                "written per second as a multiple of BIRIS's real 20 Hz. Per rung: acquisitions "
                "written per real second of scanning (rate_xN), the in-sequence rate over "
                "nominal (keep_up_xN), drops (dropped_xN). What stopped the ladder: " + why
            ),
        )
    )
    ctx.log("bench: record.replay")
    figures.append(_replay(file))
    ctx.log("bench: record.size")
    figures.append(_size(file))
    ctx.log("bench: record.latency")
    figures += _latency(ctx, float(ctx.pick(full=4, quick=2)), int(ctx.pick(full=5, quick=1)))
    return figures


def _rung(path: Path, scale: float, seconds: float) -> dict[str, float]:
    """One time scale: what the recorder wrote, what it dropped, whether the simulator kept up."""
    period = acquisition_period_s(128)
    with (
        running_server(samples=128, time_scale=scale) as bench,
        IrqRecorder(bench.rig) as irq,
    ):
        conn = bench.server.open()
        made0 = bench.rig.supervisor.acquisitions_made
        with Recorder(bench.server, path) as recorder:
            t0 = time.perf_counter_ns()
            conn.continuous_scan(-45.0, 45.0)
            recorder.failed.wait(seconds)
            t1 = time.perf_counter_ns()
            conn.stop_scan()
            conn.wait_idle(timeout=60.0)
            t2 = time.perf_counter_ns()
        conn.close()
        counters = bench.server.status()["counters"]
        spans = irq.sequence_spans()
        wall_ns = sum(ns for _, ns in spans)
        in_sequence = sum(n for n, _ in spans) * 1e9 / wall_ns if wall_ns else 0.0
        made_times = bench.rig.supervisor.acquisition_times_since(made0)
        lags = irq.lags_hw(made_times, period)
        max_lag = max(lags) / scale if lags else math.inf
    summary = recorder.summary
    assert summary is not None
    announced = sum(1 for e in irq.data if e.announces >= 0 and t0 <= e.t_ns <= t1)
    return {
        "points": float(summary.points),
        "server_acquisitions": float(counters["acquisitions"]),
        "dropped": float(summary.dropped),
        "rate": summary.points * 1e9 / (t2 - t0),
        "sensor_rate": announced * 1e9 / (t1 - t0),
        "keep_up": in_sequence / (scale / period),
        "max_lag_ms": max_lag * 1e3,
        "hw_seconds": (t1 - t0) / 1e9 * scale,
    }


def _throughput(
    work: Path, ladder: list[float], seconds: float
) -> tuple[float, dict[str, float], Path, str]:
    """Climb the ladder to the first failing rung, then bisect (geometrically, at most
    ``BISECTIONS`` rungs) between the fastest pass and the slowest failure."""
    best = 0.0
    bad: float | None = None
    why = f"none: every rung up to x{ladder[-1]:g} passed."
    values: dict[str, float] = {}
    file = work / f"x{ladder[0]:g}.mcap"
    tried = list(ladder)
    bisections = 0
    while tried:
        scale = tried.pop(0)
        name = f"x{scale:g}"
        try:
            rung = _rung(work / f"{name}.mcap", scale, seconds)
        except BirisError as exc:  # a fault at this rate (the process fell behind) fails it
            bad, tried = scale, []
            why = f"at {name} the run failed: {type(exc).__name__}: {exc}."
            rung = {}
        for key, value in rung.items():
            values[f"{key}_{name}"] = value
        kept_up = bool(rung) and (
            rung["keep_up"] >= 1 - KEEP_UP and rung["max_lag_ms"] <= KEEP_UP * seconds * 1e3
        )
        lossless = (
            bool(rung) and rung["dropped"] == 0 and rung["points"] >= rung["server_acquisitions"]
        )
        if kept_up and lossless:
            best = scale
        elif rung:
            bad, tried = scale, []
            if not lossless:
                why = (
                    f"at {name} the recorder missed acquisitions ({rung['dropped']:g} dropped, "
                    f"{rung['points']:g} of {rung['server_acquisitions']:g} written)."
                )
            else:
                why = (
                    f"at {name} the process (simulator, server and recorder on one GIL) could "
                    f"not keep the sensor's rate (in-sequence rate {rung['keep_up']:.2f} x "
                    f"nominal, latest interrupt {rung['max_lag_ms']:.0f} ms late) while the "
                    "recorder lost nothing: the ceiling is at least the last passing rung."
                )
        if bad is not None and best and bad / best > BISECT_WITHIN and bisections < BISECTIONS:
            tried = [float(round(math.sqrt(best * bad)))]
            bisections += 1
    return best, values, file, why


def _replay(path: Path) -> Figure:
    with ReplayServer(path, speed=None, autostart=False) as replay:
        data = replay.open(ConnectionKind.DATA, policy=DeliveryPolicy.EVERY_ACQUISITION)
        begun = time.perf_counter()
        replay.start()
        n = 0
        try:
            while True:
                data.ready_for_data(timeout=10.0)
                n += 1
        except EndOfRecording:
            pass
        took = time.perf_counter() - begun
    rate = n / took
    return Figure(
        key="record.replay",
        values={"ratio": rate / REAL_RATE_128, "acq_per_s": rate, "n": float(n)},
        unit="x real rate",
        method=(
            "The x20 recording of record.throughput replayed with speed=None (as fast as the "
            "reader takes it) to one EVERY_ACQUISITION client that counts Points; also served: "
            "scans and statuses. ratio = acquisitions per real second / 20 Hz. No target."
        ),
    )


def _size(path: Path) -> Figure:
    meta: dict[str, str] = {}
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        for m in reader.iter_metadata():
            if m.name == "biris.recording":
                meta = dict(m.metadata)
    assert summary is not None and summary.statistics is not None
    span_s = (summary.statistics.message_end_time - summary.statistics.message_start_time) / 1e9
    size = os.path.getsize(path)
    per_min = size / span_s * 60.0 / 1e6 if span_s > 0 else float("nan")
    return Figure(
        key="record.size",
        values={
            "mb_per_min": per_min,
            "bytes": float(size),
            "hw_seconds": span_s,
            "points": float(json.loads(meta.get("points", "0"))),
        },
        unit="MB/min",
        method=(
            "Size of the x20 recording (128 samples, zstd chunks, profiles, transforms, "
            "lossless channels, diagnostics) divided by its span of hardware time, per minute "
            "of continuous -45..+45 deg scanning. No target."
        ),
    )


def _subscriber(port: int, stop: threading.Event) -> threading.Thread:
    """A Foxglove WebSocket client subscribed to every channel, reading until ``stop``."""
    from websockets.sync.client import connect
    from websockets.typing import Subprotocol

    ready = threading.Event()

    def run() -> None:
        with connect(f"ws://127.0.0.1:{port}", subprotocols=[Subprotocol("foxglove.sdk.v1")]) as ws:
            ws.recv(timeout=10)
            channels: list[dict[str, Any]] = []
            while len(channels) < 6:
                channels += json.loads(ws.recv(timeout=10)).get("channels", [])
            subs = [{"id": i, "channelId": c["id"]} for i, c in enumerate(channels)]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
            ready.set()
            while not stop.is_set():
                try:
                    ws.recv(timeout=0.2)
                except TimeoutError:
                    continue

    thread = threading.Thread(target=run, name="bench-foxglove-client", daemon=True)
    thread.start()
    ready.wait(10)
    return thread


def _latency(ctx: BenchContext, seconds: float, rounds: int) -> list[Figure]:
    from biris_hw.io.liveview import LiveView

    samples: dict[str, list[float]] = {"without": [], "recorder": [], "liveview": []}
    published: list[float] = []
    with running_server(samples=64, time_scale=1.0) as bench, IrqRecorder(bench.rig) as irq:
        conn = bench.server.open()
        conn.continuous_scan(-45.0, 45.0)
        try:
            for r in range(rounds):
                order = ["without", "recorder", "liveview"]
                order = order[r % 3 :] + order[: r % 3]
                for name in order:
                    if name == "without":
                        figs = _every_acquisition(bench, irq, seconds)
                    elif name == "recorder":
                        with Recorder(bench.server, ctx.work_dir / f"lat{r}.mcap"):
                            figs = _every_acquisition(bench, irq, seconds)
                    else:
                        stop = threading.Event()
                        with LiveView(bench.server, port=0) as view:
                            client = _subscriber(view.port, stop)
                            figs = _every_acquisition(bench, irq, seconds)
                            stop.set()
                            client.join()
                        published.append(float(sum(view.published.values())))
                    samples[name].append(figs[0].values["p50"])
        finally:
            conn.stop_scan()
            conn.wait_idle(timeout=30.0)
            conn.close()
    base = percentile(samples["without"], 50)
    out = []
    for name in ("recorder", "liveview"):
        p50 = percentile(samples[name], 50)
        out.append(
            Figure(
                key=f"record.latency_{name}",
                values={
                    "ratio": p50 / base,
                    "p50_us": p50,
                    "without_p50_us": base,
                    "rounds": float(rounds),
                    **(
                        {"messages_published_per_phase": percentile(published, 50)}
                        if name == "liveview"
                        else {}
                    ),
                },
                unit="x",
                target=Target("<=", 1.2, on="ratio"),
                method=(
                    f"latency_us.every_acquisition's measurement (time_scale 1, 64 samples, "
                    f"continuous -45..+45 deg), {seconds:g} s per phase, {rounds} round(s) "
                    "rotating the order without / with a Recorder (profiles on) / with a "
                    "LiveView whose every channel a websockets client subscribes to; ratio = "
                    f"median of the phases' p50 with the {name} / median without, same run."
                ),
            )
        )
    return out

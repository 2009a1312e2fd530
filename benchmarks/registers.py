"""Register access: our ``mmap`` window against python-periphery's ``MMIO`` on the same memory.

periphery is what a Python programmer would reach for to poke a memory-mapped board, so it is
the yardstick: a single register through our window must be at least as fast (the range and
alignment checks and the big-endian swap must not cost more than periphery's own checks), and a
frame must be much faster than reading it a register at a time, because that is what the bulk
``read`` is for. Both sides map the same temporary file in the same process and are timed in the
same rounds, so the ratios compare like with like.
"""

from __future__ import annotations

import math
import random
import sys
from collections.abc import Callable, Mapping
from itertools import repeat
from time import perf_counter_ns
from typing import Any

import numpy as np
import numpy.typing as npt

from benchmarks.harness import (
    BenchContext,
    BenchSkipped,
    Figure,
    Target,
    benchmark,
    interleaved_rounds,
    percentile,
)
from biris_hw.bus import BusWindow, open_window

__all__ = ["call_loop", "registers"]

SIZE = 0x10000
"""Bytes mapped: a few pages, like a board's register span plus one frame area."""

READ8_AT = 0x101  # odd on purpose: an 8-bit register at a byte address
READ16_AT = 0x100
WRITE16_AT = 0x200
WRITE16_VALUE = 0x1234
FRAME_AT = 0x1000
FRAME_ELEMENTS = 129  # the closest sample and 128 samples along the laser line
FRAME_BYTES = 2 * FRAME_ELEMENTS

_BIG_ENDIAN_I16 = np.dtype(">i2")
_SWAP = sys.byteorder == "little"

Loop = Callable[[int], int]
"""Runs an operation ``n`` times and returns the nanoseconds that took."""


@benchmark("registers")
def registers(ctx: BenchContext) -> list[Figure]:
    """read8, read16, write16 and a 129-element frame: our mmap window against periphery.MMIO."""
    try:
        from periphery import MMIO
    except ImportError as exc:
        raise BenchSkipped(
            f"python-periphery is not installed ({exc}); install the 'bench' extra"
        ) from exc

    rounds = ctx.pick(full=21, quick=5)
    batch_ns = ctx.pick(full=50, quick=5) * 1_000_000
    path = ctx.work_dir / "registers.bin"
    path.write_bytes(random.Random(7).randbytes(SIZE))

    with open_window("mmap", path=str(path), size=SIZE) as ours:
        theirs = MMIO(0, SIZE, path=str(path))
        try:
            _check_same_memory(ours, theirs)
            common = (
                f"Tight loops of calls timed with perf_counter_ns (batches of about "
                f"{batch_ns // 1_000_000} ms), {rounds} rounds interleaving ours "
                "(open_window('mmap')) with periphery.MMIO on the same temporary file in the "
                "same process, GC off; medians of the rates, ratio = ours/theirs, "
                "ratio_p10/p90 = spread of the per-round ratios."
            )
            native = (
                " Ours checks range and alignment and converts from big-endian; periphery "
                "reads native-endian (no byte swap)."
            )
            single: list[tuple[str, Loop, Loop]] = [
                ("read8", _loop1(ours.read8, READ8_AT), _loop1(theirs.read8, READ8_AT)),
                ("read16", _loop1(ours.read16, READ16_AT), _loop1(theirs.read16, READ16_AT)),
                (
                    "write16",
                    _loop2(ours.write16, WRITE16_AT, WRITE16_VALUE),
                    _loop2(theirs.write16, WRITE16_AT, WRITE16_VALUE),
                ),
            ]
            figures = []
            for name, our_op, their_op in single:
                ctx.log(f"bench: registers.{name}")
                ns = _measure({"ours": our_op, "theirs": their_op}, rounds, batch_ns)
                figures.append(
                    Figure(
                        key=f"registers.{name}",
                        values=_compare(ns, "ours", "theirs", rounds),
                        unit="ops/s",
                        target=Target(">=", 1.0, on="ratio"),
                        method=common + native,
                    )
                )
            ctx.log("bench: registers.frame129")
            figures.append(_frame_figure(ours, theirs, rounds, batch_ns, common))
        finally:
            theirs.close()
    return figures


def _frame_figure(ours: BusWindow, theirs: Any, rounds: int, batch_ns: int, common: str) -> Figure:
    """The frame read, three ways; the target is the one that says what the bulk read buys."""
    contenders = {
        "ours": call_loop(_our_frame(ours)),
        "theirs_read16": call_loop(_their_frame_by_registers(theirs)),
        "theirs_bulk": call_loop(_their_frame_bulk(theirs)),
    }
    ns = _measure(contenders, rounds, batch_ns)
    values = _compare(ns, "ours", "theirs_read16", rounds)
    bulk = _compare(ns, "ours", "theirs_bulk", rounds)
    values["theirs_bulk_ops_per_s"] = bulk["theirs_bulk_ops_per_s"]
    values["ratio_vs_bulk"] = bulk["ratio"]
    method = (
        f"One op = {FRAME_ELEMENTS} big-endian int16 elements ({FRAME_BYTES} bytes) into a numpy "
        "int16 array. The target's ratio is ours (one window.read + "
        "frombuffer('>i2').astype(int16)) over 129 periphery read16 calls plus one numpy "
        "byte swap, which is what a register-at-a-time driver does; ratio_vs_bulk is ours over "
        "periphery's bulk MMIO.read with the same conversion (no target). " + common
    )
    return Figure(
        key="registers.frame129",
        values=values,
        unit="ops/s",
        target=Target(">=", 10.0, on="ratio"),
        method=method,
    )


# -- the contenders ------------------------------------------------------------------------------


def _our_frame(win: BusWindow) -> Callable[[], npt.NDArray[np.int16]]:
    read = win.read

    def frame() -> npt.NDArray[np.int16]:
        return np.frombuffer(read(FRAME_AT, FRAME_BYTES), dtype=_BIG_ENDIAN_I16).astype(np.int16)

    return frame


def _their_frame_bulk(mmio: Any) -> Callable[[], npt.NDArray[np.int16]]:
    read = mmio.read

    def frame() -> npt.NDArray[np.int16]:
        return np.frombuffer(read(FRAME_AT, FRAME_BYTES), dtype=_BIG_ENDIAN_I16).astype(np.int16)

    return frame


def _their_frame_by_registers(mmio: Any) -> Callable[[], npt.NDArray[np.int16]]:
    """129 native-endian register reads, then one vectorised swap: the best a per-register
    driver can do (a list comprehension measured faster than numpy.fromiter here)."""
    read16 = mmio.read16
    offsets = [FRAME_AT + 2 * i for i in range(FRAME_ELEMENTS)]

    def frame() -> npt.NDArray[np.int16]:
        raw = np.array([read16(o) for o in offsets], dtype=np.uint16)
        if _SWAP:
            raw.byteswap(inplace=True)
        return raw.view(np.int16)

    return frame


def _check_same_memory(ours: BusWindow, theirs: Any) -> None:
    """Refuse to time two things that do not see the same bytes: the ratios would be fiction."""

    def swapped(v: int) -> int:
        return ((v & 0xFF) << 8) | (v >> 8) if _SWAP else v

    problems = []
    if ours.read8(READ8_AT) != theirs.read8(READ8_AT):
        problems.append("read8")
    if ours.read16(READ16_AT) != swapped(theirs.read16(READ16_AT)):
        problems.append("read16")
    ours.write16(WRITE16_AT, WRITE16_VALUE)
    if swapped(theirs.read16(WRITE16_AT)) != WRITE16_VALUE:
        problems.append("write16")
    frames = [_our_frame(ours)(), _their_frame_bulk(theirs)(), _their_frame_by_registers(theirs)()]
    if not all(np.array_equal(frames[0], f) for f in frames[1:]):
        problems.append("frame")
    if problems:
        raise RuntimeError(f"ours and periphery disagree on {', '.join(problems)}")


# -- timing --------------------------------------------------------------------------------------
# One loop factory per arity, shared by both sides, so the loop overhead (included in every
# figure) is the same for ours and theirs.


def call_loop(fn: Callable[[], object]) -> Loop:
    def run(n: int) -> int:
        f = fn
        it = repeat(None, n)
        t0 = perf_counter_ns()
        for _ in it:
            f()
        return perf_counter_ns() - t0

    return run


def _loop1(fn: Callable[[int], object], a: int) -> Loop:
    def run(n: int) -> int:
        f, x = fn, a
        it = repeat(None, n)
        t0 = perf_counter_ns()
        for _ in it:
            f(x)
        return perf_counter_ns() - t0

    return run


def _loop2(fn: Callable[[int, int], object], a: int, b: int) -> Loop:
    def run(n: int) -> int:
        f, x, y = fn, a, b
        it = repeat(None, n)
        t0 = perf_counter_ns()
        for _ in it:
            f(x, y)
        return perf_counter_ns() - t0

    return run


def _batch_size(run: Loop, batch_ns: int) -> int:
    """Calls per batch so one batch lasts about ``batch_ns``; warms the contender up as well."""
    n = 16
    while True:
        took = max(run(n), 1)
        if took >= batch_ns // 10 or n >= 1 << 30:
            return max(1, math.ceil(n * batch_ns / took))
        n *= 4


def _measure(loops: Mapping[str, Loop], rounds: int, batch_ns: int) -> dict[str, list[float]]:
    """Nanoseconds per operation, one sample per contender per round."""
    sizes = {name: _batch_size(run, batch_ns) for name, run in loops.items()}

    def per_op(name: str) -> Callable[[], float]:
        run, n = loops[name], sizes[name]
        return lambda: run(n) / n

    return interleaved_rounds({name: per_op(name) for name in loops}, rounds)


def _compare(ns: Mapping[str, list[float]], a: str, b: str, rounds: int) -> dict[str, float]:
    """Median rates of ``a`` and ``b``, their ratio, and the spread of per-round ratios."""
    rate_a = 1e9 / percentile(ns[a], 50)
    rate_b = 1e9 / percentile(ns[b], 50)
    paired = [tb / ta for ta, tb in zip(ns[a], ns[b], strict=True)]
    return {
        f"{a}_ops_per_s": rate_a,
        f"{b}_ops_per_s": rate_b,
        "ratio": rate_a / rate_b,
        "ratio_p10": percentile(paired, 10),
        "ratio_p90": percentile(paired, 90),
        f"{a}_ns_p90": percentile(ns[a], 90),
        f"{b}_ns_p90": percentile(ns[b], 90),
        "rounds": float(rounds),
    }

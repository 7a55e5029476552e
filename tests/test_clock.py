"""ManualClock: sleepers wake in time order, and only when time is advanced past them."""

from __future__ import annotations

import asyncio
import socket

from companion.clock import ManualClock, SystemClock


async def test_sleepers_wake_in_order() -> None:
    clock = ManualClock(start_s=10.0)
    woke: list[tuple[str, float]] = []

    async def sleeper(name: str, dt: float) -> None:
        await clock.sleep(dt)
        woke.append((name, clock.now()))

    tasks = [asyncio.create_task(sleeper("b", 2.0)), asyncio.create_task(sleeper("a", 1.0))]
    await clock.advance(0.5)
    assert woke == [] and clock.pending == 2
    await clock.advance(1.0)
    assert woke == [("a", 11.0)]
    await clock.advance(5.0)
    assert woke == [("a", 11.0), ("b", 12.0)]
    assert clock.now() == 16.5
    await asyncio.gather(*tasks)


async def test_periodic_task_ticks_per_period() -> None:
    clock = ManualClock()
    ticks: list[float] = []

    async def ticker() -> None:
        while True:
            ticks.append(clock.now())
            await clock.sleep(0.1)

    task = asyncio.create_task(ticker())
    await clock.advance(1.05)
    task.cancel()
    assert len(ticks) == 11


async def test_loopback_io_flows_between_steps() -> None:
    clock = ManualClock()
    loop = asyncio.get_running_loop()
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    got: list[bytes] = []
    loop.add_reader(rx.fileno(), lambda: got.append(rx.recv(100)))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        tx.sendto(b"ping", rx.getsockname())
        await clock.advance(0.01)
        assert got == [b"ping"]
    finally:
        loop.remove_reader(rx.fileno())
        rx.close()
        tx.close()


async def test_system_clock_is_monotonic() -> None:
    c = SystemClock()
    a = c.now()
    await c.sleep(0)
    assert c.now() >= a

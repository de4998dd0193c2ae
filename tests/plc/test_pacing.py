"""The front ends' work budgets (cellctl.plc.pacing): a front end busy past its burst waits, and the budget every
front end shares holds the others back too (pure asyncio, no server)."""

from __future__ import annotations

import asyncio

from cellctl.plc.pacing import Budget, Pacer


def test_a_busy_front_end_waits_and_the_shared_budget_holds_every_front_end() -> None:
    shared = Budget(share=0.5, burst_s=0.01)
    busy = Pacer(share=0.25, burst_s=0.01, shared=shared)
    other = Pacer(share=0.5, burst_s=0.01, shared=shared)
    alone = Pacer(share=0.5, burst_s=0.01, shared=None)

    async def run() -> None:
        t0 = await busy.wait()
        busy.done(t0 - 0.05)  # 50 ms of work, 40 ms past the bursts: 160 ms to refill its own, 80 ms the shared
        await other.wait()  # its own budget is full, the shared one is spent
        await alone.wait()  # outside the shared budget: goes at once
        await busy.wait()

    asyncio.run(run())
    assert busy.frames == 1 and busy.status() == {"frames": 1, "waited_s": busy.status()["waited_s"]}
    assert other.waited_s >= 0.05, other.waited_s
    assert alone.waited_s == 0.0
    assert busy.waited_s >= 0.03, busy.waited_s  # its own budget: what was left after the other's wait

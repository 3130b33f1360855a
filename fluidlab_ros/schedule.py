"""The command stream's clock: absolute deadlines that never bunch ticks (used by sim_node's stream thread).

Deadline of tick k: max(t0 + k T, previous tick + min_gap), min_gap = T / 2 when one command spans at least
two 1 ms ticks of the arm. Why: a late command is held by the arm; sending the following ones every T / 2
until the timeline is reached again gives back, to first order, the time the late one took (docs/ros.md).
At 1 kHz (one command per arm tick) nothing can be sent faster without losing commands, so a stall cannot be
given back: the timeline moves on by the stall instead (the stream's position feedback corrects the drift), and
the lateness of a tick is that of its own stall. Without this, the stalls of a long 1 kHz stream under load
added up until one passed late_tick_limit (bench_stream: 20.1 ms at tick 9,529 of 10,772, no stall above 7 ms).
"""
from __future__ import annotations

import time


class Schedule:
    """Absolute deadlines t0 + k T on a fixed timeline, with a minimum gap between ticks.

    wait() sleeps until the next deadline and returns (now, lateness against the timeline). After a stall,
    the following ticks come every `min_gap` (T / 2 when a command spans at least two 1 ms arm ticks) until
    the timeline is reached again. So commands are never bunched (at most two reach one 1 ms arm tick: the
    one-lost-command case the planner budgets for), and the time each command is held averages out: the arm
    held the stalled command too long, then holds the next ones shorter, and comes back onto the planned
    positions instead of drifting by (stall x velocity) per stall."""

    def __init__(self, period: float, t0: float, arm_tick: float = 1e-3):
        self.period, self.t0, self.k = period, t0, 0
        self.min_gap = period / 2 if period >= 2 * arm_tick - 1e-12 else period
        self.last: float | None = None
        self.late_ticks, self.max_late = 0, 0.0

    def wait(self) -> tuple[float, float]:
        on_time = self.t0 + self.k * self.period
        deadline = on_time if self.last is None else max(on_time, self.last + self.min_gap)
        sleep_until(deadline)
        now = time.monotonic()
        late = now - on_time
        if late > self.period / 2:
            self.late_ticks += 1
        self.max_late = max(self.max_late, late)
        self.k += 1
        self.last = now
        if self.min_gap >= self.period and late > self.period / 2:
            self.t0 += late  # no catch-up possible (see above): the timeline follows the stall
        return now, late


def sleep_until(deadline: float):
    """Sleep to within 0.3 ms of the deadline, then spin (time.sleep overshoots by up to a tick of the OS)."""
    while True:
        left = deadline - time.monotonic()
        if left <= 0:
            return
        if left > 0.0006:
            time.sleep(left - 0.0004)

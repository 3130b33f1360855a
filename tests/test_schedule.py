"""The command stream's clock (fluidlab_ros/schedule.py): after a stall, a 500 Hz stream catches up with its
timeline (commands every T / 2, never bunched), and a 1 kHz stream, which cannot send faster than the arm's
1 ms tick, moves its timeline on instead, so that the lateness of later ticks is their own and stalls do not add
up to a stop."""
import time

from fluidlab_ros.schedule import Schedule

STALL = 0.03  # s


def stalled(rate: float, after: int = 40):
    """Lateness of each tick (s) and the gaps between ticks, with one stall of STALL before tick 5."""
    clock = Schedule(1.0 / rate, time.monotonic() + 0.005)
    lates, times = [], []
    for k in range(5 + after):
        if k == 5:
            time.sleep(STALL)
        now, late = clock.wait()
        lates.append(late)
        times.append(now)
    return lates, [b - a for a, b in zip(times[:-1], times[1:])]


def test_500_hz_catches_up_with_its_timeline_without_bunching():
    lates, gaps = stalled(500.0)
    assert lates[5] > 0.8 * STALL
    # back on the timeline: the stall (30 ms) is given back at 1 ms per command within 30-odd commands
    assert min(lates[-5:]) < 0.005, lates
    assert min(gaps) >= 0.001 - 2e-4, min(gaps)  # never closer than T / 2 (less the clock's spin tolerance)


def test_1_khz_moves_its_timeline_on_so_stalls_do_not_add_up():
    lates, gaps = stalled(1000.0)
    assert lates[5] > 0.8 * STALL
    # the following ticks are late by their own delays only (without the shift: 30 ms each, to the end)
    assert min(lates[6:]) < 0.005, lates[6:]
    assert min(gaps) >= 0.001 - 2e-4, min(gaps)

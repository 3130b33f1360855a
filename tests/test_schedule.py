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
    """The stall (30 ms) is given back at T - T / 2 = 1 ms per command, so the stream is back within 5 ms of its
    timeline some 25 commands later, and no two commands come closer than T / 2. How many commands that takes
    is the machine's: a wake-up the OS delays is lateness of its own, given back at the same rate. With three
    test processes on the two cores (2026-12-07) 14.4 ms were left after 40 commands, falling by 1.00 ms a
    command (18.4, 17.4, 16.4, 15.4, 14.4 ms), where the test once stopped; it now runs 200 commands and asserts
    the return to the timeline, the rate being what the gaps' bound holds."""
    lates, gaps = stalled(500.0, after=200)
    assert lates[5] > 0.8 * STALL
    back = next((k for k in range(6, len(lates)) if lates[k] < 0.005), None)
    assert back is not None, lates
    assert min(gaps) >= 0.001 - 2e-4, min(gaps)  # never closer than T / 2 (less the clock's spin tolerance)


def test_1_khz_moves_its_timeline_on_so_stalls_do_not_add_up():
    lates, gaps = stalled(1000.0)
    assert lates[5] > 0.8 * STALL
    # the following ticks are late by their own delays only (without the shift: 30 ms each, to the end)
    assert min(lates[6:]) < 0.005, lates[6:]
    assert min(gaps) >= 0.001 - 2e-4, min(gaps)

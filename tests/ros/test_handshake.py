"""stream.handshake: a plan's first command goes out only once every subscriber can hear it.

A new stream process (at start-up, and after a take-over) has new DDS writers; a subscriber that has not
matched one yet drops what it sends, and CI once saw a stream begin at its third command, 0.028 rad/s from rest
(28 rad/s^2 against the FR3's 10). The real graph is exercised by tests/ros/test_stream_faults.py (a plan right
after a replacement process is ready, every stream opened by the handshake's zero); here the order of the steps
and the failures, with publishers whose matching and acknowledgements the test controls.
"""
from __future__ import annotations

import time

import pytest

pytest.importorskip("rclpy", reason="ROS 2 (ros-jazzy-rclpy, requirements-ros.txt) is not installed")

from fluidlab_ros.stream import handshake  # noqa: E402


class FakePublisher:
    """Matches one more subscription every `every` s up to `final`; acknowledges within `ack_after` s (None:
    never). Logs what happens to `log`."""

    def __init__(self, log: list, final: int, every: float = 0.02, ack_after: float | None = 0.01):
        self.log, self.final, self.every, self.ack_after = log, final, every, ack_after
        self.t0 = time.monotonic()

    def get_subscription_count(self) -> int:
        return min(self.final, int((time.monotonic() - self.t0) / self.every))

    def wait_for_all_acked(self, timeout) -> bool:
        limit = timeout.nanoseconds * 1e-9
        self.log.append(("wait_acked", self.get_subscription_count()))
        if self.ack_after is None or self.ack_after > limit:
            time.sleep(limit)
            return False
        time.sleep(self.ack_after)
        return True


def test_the_zero_goes_out_only_after_each_publisher_matched_the_nodes_count_and_then_is_acknowledged():
    log = []
    pubs = [FakePublisher(log, final=3), FakePublisher(log, final=1)]
    sent_at_counts = []
    problem = handshake([(pubs[0], "/sim_node/commands", 2), (pubs[1], "/controller/commands", 1)],
                        lambda: sent_at_counts.append([p.get_subscription_count() for p in pubs]), timeout=2.0)
    assert problem == ""
    assert len(sent_at_counts) == 1 and sent_at_counts[0][0] >= 2 and sent_at_counts[0][1] >= 1, sent_at_counts
    assert [e[0] for e in log] == ["wait_acked", "wait_acked"]  # both topics acknowledged, after the zero


def test_a_publisher_never_matched_sends_nothing_and_names_topic_and_counts():
    sent = []
    t = time.monotonic()
    problem = handshake([(FakePublisher([], final=1), "/sim_node/commands", 2)], lambda: sent.append(0), timeout=0.3)
    assert not sent, "nothing may be sent before the subscribers matched"
    assert "/sim_node/commands matched 1 of the 2 subscribers" in problem and "nothing was sent" in problem, problem
    assert 0.3 <= time.monotonic() - t < 1.0


def test_an_unacknowledged_zero_is_reported_and_is_all_that_was_sent():
    sent = []
    problem = handshake([(FakePublisher([], final=1, ack_after=None), "/sim_node/commands", 1)],
                        lambda: sent.append(0), timeout=0.3)
    assert sent == [0]
    assert "did not acknowledge the stream's opening zero command within 0.3 s" in problem, problem
    assert "the arm stays at rest" in problem


def test_a_stop_during_the_wait_ends_it_at_once_with_the_stop_reason():
    """A cancel (or ~/stop, a disarm) while the handshake waits ends it within a poll, with the stop's reason as
    the plan's outcome (sim_node then cancels the goal): nothing sent while matching, the zero alone after it."""
    asked = {"at": None}

    def stopped():
        return "cancelled" if asked["at"] is not None and time.monotonic() >= asked["at"] else ""

    sent = []
    asked["at"] = time.monotonic() + 0.1
    t = time.monotonic()
    problem = handshake([(FakePublisher([], final=0), "/sim_node/commands", 1)], lambda: sent.append(0), timeout=5.0,
                        stopped=stopped)
    assert problem == "cancelled" and not sent
    assert time.monotonic() - t < 0.5, "the stop must end the wait for subscribers within a poll"
    asked["at"] = time.monotonic() + 0.1
    t = time.monotonic()
    problem = handshake([(FakePublisher([], final=1, every=1e-6, ack_after=None), "/sim_node/commands", 1)],
                        lambda: sent.append(0), timeout=5.0, stopped=stopped)
    assert problem == "cancelled" and sent == [0]
    assert time.monotonic() - t < 0.5, "the stop must end the wait for acknowledgements within a poll"

"""The node's handle on a command stream (sim_node.Stream) stays usable from every thread after the stream ends.

The execute goal's thread reads the stop flag ten times a second while the follower thread follows the stream,
and the follower closes the shared RunBuffer when the stream ends. CI caught the goal reading the flag just after
a killed stream process's buffer was closed: the goal died with an AttributeError, and so did the node's
shutdown, instead of reporting the stop and ramping to rest.
"""
from __future__ import annotations

import threading

import pytest

pytest.importorskip("rclpy", reason="ROS 2 (ros-jazzy-rclpy, requirements-ros.txt) is not installed")
pytest.importorskip("fluidlab_msgs", reason="fluidlab_msgs is not built (pip install ./fluidlab_msgs_py)")

from fluidlab_ros.sim_node import Stream  # noqa: E402
from fluidlab_ros.stream import RunBuffer  # noqa: E402


def test_stop_reason_survives_the_buffer_being_closed():
    stream = Stream(plan=None, to_robot=False, buf=RunBuffer(8, 7))
    assert stream.stop_reason == ""
    stream.request_stop("cancelled")
    stream.request_stop("node shutting down")  # the first reason is kept
    stream.close_buffer()
    assert stream.buf is None
    assert stream.stop_reason == "cancelled"
    stream.request_stop("node shutting down")  # after the end: ignored, no error
    assert stream.stop_reason == "cancelled"
    stream.close_buffer()  # twice: harmless


def test_readers_on_other_threads_never_meet_a_half_closed_buffer():
    errors = []
    for _ in range(200):
        stream = Stream(plan=None, to_robot=False, buf=RunBuffer(4, 7))
        go = threading.Event()

        def reader():
            go.wait()
            try:
                for _ in range(200):
                    stream.stop_reason
                    stream.request_stop("cancelled")
            except Exception as err:  # noqa: BLE001 - collected and asserted below
                errors.append(repr(err))

        t = threading.Thread(target=reader)
        t.start()
        go.set()
        stream.close_buffer()
        t.join()
    assert not errors, errors[:3]

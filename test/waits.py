"""
Waits on events for the ROS tests: a match seen from both ends, a probe that came back.

A reliable, volatile writer delivers what it publishes after *it* matched a reader
(``pub.get_subscription_count()``); the reader's own match (``sub.get_publisher_count()``)
completes the pair. In one process both ends are visible, so tests wait for both. Across
processes only our end is: the proof that the other end matched too is a message that made
the whole trip (see :func:`round_trip`), never a sleep.
"""

import time
import warnings

import pytest

from conftest import TIMEOUT_SCALE


def until(ros, predicate, timeout: float):
    """Return ``predicate()`` once true, or None after ``timeout`` (unscaled) seconds."""
    return ros.until(predicate, timeout)


def _endpoints(publishers, subscriptions):
    for p in publishers:
        yield p, 'subscriptions', p.get_subscription_count
    for s in subscriptions:
        yield s, 'publishers', s.get_publisher_count


def wait_matched(ros, publishers=(), subscriptions=(), count: int = 1,
                 timeout: float = 20.0) -> None:
    """
    Wait until each publisher and each subscription has matched ``count`` peers.

    Give both ends of an in-process match (the publisher and the subscription): then
    messages flow both ways from the first one on, best effort included.
    """
    ends = list(_endpoints(publishers, subscriptions))

    def unmatched():
        return [f'{e.topic_name} ({n()} {kind} matched)' for e, kind, n in ends if n() < count]

    ros.wait_for(lambda: not unmatched(), timeout,
                 what=lambda: f'matches with {count} peer(s): ' + ', '.join(unmatched()))


def round_trip(ros, send, arrived, what: str, retry_s: float = 2.0,
               timeout: float = 60.0) -> int:
    """
    Send probes until one's answer ``arrived()``; return how many were sent.

    ``send(k)`` sends probe ``k`` (0, 1, ...). An answer that made the whole trip proves every
    endpoint pair on its way matched at both ends, including those in other processes that
    no graph query shows. A probe is sent again only after ``retry_s`` seconds without an
    answer: a writer in another process that had not matched our reader yet dropped its
    answer (volatile QoS), and nothing would ever bring it. More than one probe is reported
    as a warning in the test summary.
    """
    deadline = time.monotonic() + timeout * TIMEOUT_SCALE
    k = 0
    while True:
        send(k)
        k += 1
        if until(ros, arrived, retry_s):
            if k > 1:       # something was lost to an unfinished match: say so
                warnings.warn(f'round_trip: {k} probes for {what}')
            return k
        if time.monotonic() > deadline:
            pytest.fail(f'timed out after {timeout * TIMEOUT_SCALE:.1f} s and {k} probes '
                        f'waiting for {what}')


def call(ros, client, request, what: str, timeout: float = 30.0):
    """
    Call a service in another process; return the first answer.

    A request can go unanswered: the graph may still list the service of a process that is
    gone (``wait_for_service`` passes before the live server matched our client), and a
    server drops its response if our client's response reader has not matched it within
    100 ms (rmw_fastrtps; rclpy warns "failed to send response (timeout)" there), which a
    new client on a busy machine can take. So it is repeated (:func:`round_trip`). Answers
    come in request order: the first is that of the earliest request served. Only for
    requests that are harmless twice (a lifecycle transition already taken is refused).
    """
    calls = []
    round_trip(ros, lambda k: calls.append(client.call_async(request)),
               lambda: any(f.done() for f in calls), what, timeout=timeout)
    return next(f for f in calls if f.done()).result()

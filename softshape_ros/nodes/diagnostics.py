"""
Diagnostics the way ``diagnostic_updater`` does them: one Updater per node, named tasks.

On a ROS install the real ``diagnostic_updater`` package is used. Where it does not import
(the PyPI wheels here), a small stand-in with the same API takes its place: ``Updater``
(``add(name, fn)``, ``force_update()``, ``setHardwareID``, the ``diagnostic_updater.period``
parameter, status names ``<node name>: <task>``, a "Node starting up" status per new task),
``DiagnosticStatusWrapper`` (``summary``, ``mergeSummary``, ``add``), ``FrequencyStatus``
and ``HeaderlessTopicDiagnostic`` (``<topic> topic status``: ERROR without events, WARN
outside the frequency bounds). Aggregators (``diagnostic_aggregator``) match those names.
"""

from __future__ import annotations

import threading
import time

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

__all__ = ['Updater', 'DiagnosticStatusWrapper', 'FrequencyStatus', 'FrequencyStatusParam',
           'HeaderlessTopicDiagnostic', 'USING_DIAGNOSTIC_UPDATER', 'OK', 'WARN', 'ERROR',
           'STALE', 'topic_frequency', 'TriggeredRate', 'fill']

OK, WARN, ERROR, STALE = (DiagnosticStatus.OK, DiagnosticStatus.WARN,
                          DiagnosticStatus.ERROR, DiagnosticStatus.STALE)


def _level(level) -> bytes:
    return bytes([level]) if isinstance(level, int) else level


class _DiagnosticStatusWrapper(DiagnosticStatus):
    """A DiagnosticStatus with the updater's helpers (summary, mergeSummary, add)."""

    def summary(self, *args) -> None:
        """Set the level and the message (from two values or from another status)."""
        if len(args) == 1:
            self.level, self.message = args[0].level, args[0].message
        else:
            self.level, self.message = _level(args[0]), str(args[1])

    def clearSummary(self) -> None:  # noqa: N802 - diagnostic_updater's name
        """Reset to OK with an empty message."""
        self.summary(OK, '')

    def mergeSummary(self, *args) -> None:  # noqa: N802
        """Merge a level and message in: the worse level wins, non-OK messages join."""
        if len(args) == 1:
            lvl, msg = args[0].level, args[0].message
        else:
            lvl, msg = _level(args[0]), str(args[1])
        lvl, own = _level(lvl), _level(self.level)
        if (lvl > _level(OK)) == (own > _level(OK)):
            if self.message:
                self.message += '; '
            self.message += msg
        elif lvl > own:
            self.message = msg
        if lvl > own:
            self.level = lvl

    def add(self, key: str, val) -> None:
        """Append a key and its value (as text)."""
        self.values.append(KeyValue(key=str(key), value=str(val)))


class _Task:
    def __init__(self, name: str, fn):
        self.name, self.fn = name, fn


class _Updater:
    """Run named tasks every ``diagnostic_updater.period`` seconds; publish ``node: task``."""

    def __init__(self, node, period: float = 1.0):
        self.node = node
        self.tasks: list[_Task] = []
        self.lock = threading.Lock()
        self.hwid = ''
        self.publisher = node.create_publisher(DiagnosticArray, '/diagnostics', 1)
        self.period_parameter = 'diagnostic_updater.period'
        self._period = float(node.declare_parameter(self.period_parameter, float(period)).value)
        self.use_fqn_parameter = 'diagnostic_updater.use_fqn'
        use_fqn = (node.get_parameter(self.use_fqn_parameter).value
                   if node.has_parameter(self.use_fqn_parameter)
                   else node.declare_parameter(self.use_fqn_parameter, False).value)
        self.node_name = (node.get_fully_qualified_name() if use_fqn else node.get_name())
        self.timer = node.create_timer(self._period, self.update)

    @property
    def period(self) -> float:
        return self._period

    def add(self, *args) -> None:
        """Add a task, as (name, fn) or a task object; fn(stat) fills and returns the status."""
        task = _Task(args[0], args[1]) if len(args) == 2 else _Task(args[0].name, args[0].run)
        with self.lock:
            self.tasks.append(task)
        stat = DiagnosticStatusWrapper()
        stat.name = task.name
        stat.summary(OK, 'Node starting up')
        self.publish(stat)

    def removeByName(self, name: str) -> bool:  # noqa: N802
        """Remove the first task called ``name``; True if there was one."""
        with self.lock:
            for i, t in enumerate(self.tasks):
                if t.name == name:
                    del self.tasks[i]
                    return True
        return False

    def setHardwareID(self, hwid: str) -> None:  # noqa: N802
        """Set the hardware_id of every status."""
        self.hwid = hwid

    def update(self) -> None:
        """Run every task and publish their statuses in one DiagnosticArray."""
        out = []
        with self.lock:
            for task in self.tasks:
                stat = DiagnosticStatusWrapper()
                stat.level, stat.name = _level(ERROR), task.name
                stat.message, stat.hardware_id = 'No message was set', self.hwid
                out.append(task.fn(stat))
        self.publish(out)

    force_update = update

    def broadcast(self, lvl, msg: str) -> None:
        """Publish one level and message for every task (e.g. on shutdown)."""
        out = []
        for task in self.tasks:
            stat = DiagnosticStatusWrapper()
            stat.name = task.name
            stat.summary(lvl, msg)
            out.append(stat)
        self.publish(out)

    def publish(self, msg) -> None:
        """Publish one status or a list, each named ``<node>: <task>``."""
        statuses = msg if isinstance(msg, list) else [msg]
        arr = DiagnosticArray()
        arr.header.stamp = self.node.get_clock().now().to_msg()
        for stat in statuses:
            out = DiagnosticStatus(level=_level(stat.level), name=f'{self.node_name}: {stat.name}',
                                   message=stat.message, hardware_id=stat.hardware_id,
                                   values=list(stat.values))
            arr.status.append(out)
        self.publisher.publish(arr)


class _FrequencyStatusParam:
    """Frequency bounds {'min', 'max'} (Hz), a tolerance and the window (updates)."""

    def __init__(self, freq_bound: dict, tolerance: float = 0.1, window_size: int = 5):
        self.freq_bound, self.tolerance, self.window_size = freq_bound, tolerance, window_size


class _FrequencyStatus:
    """Events per second over the last ``window_size`` updates, against the bounds."""

    def __init__(self, params, name: str = 'FrequencyStatus'):
        self.name, self.params = name, params
        self.lock = threading.Lock()
        self.clear()

    def clear(self) -> None:
        with self.lock:
            self.count = 0
            now = time.monotonic()
            self.times = [now] * self.params.window_size
            self.seq_nums = [0] * self.params.window_size
            self.hist_indx = 0

    def tick(self) -> None:
        with self.lock:
            self.count += 1

    def run(self, stat):
        with self.lock:
            now = time.monotonic()
            events = self.count - self.seq_nums[self.hist_indx]
            window = max(now - self.times[self.hist_indx], 1e-9)
            freq = events / window
            self.seq_nums[self.hist_indx], self.times[self.hist_indx] = self.count, now
            self.hist_indx = (self.hist_indx + 1) % self.params.window_size
            bound, tol = self.params.freq_bound, self.params.tolerance
            if events == 0:
                stat.summary(ERROR, 'No events recorded.')
            elif freq < bound['min'] * (1 - tol):
                stat.summary(WARN, 'Frequency too low.')
            elif 'max' in bound and freq > bound['max'] * (1 + tol):
                stat.summary(WARN, 'Frequency too high.')
            else:
                stat.summary(OK, 'Desired frequency met')
            stat.add('Events in window', '%d' % events)
            stat.add('Events since startup', '%d' % self.count)
            stat.add('Duration of window (s)', '%f' % window)
            stat.add('Actual frequency (Hz)', '%f' % freq)
            if bound['min'] > 0:
                stat.add('Minimum acceptable frequency (Hz)', '%f' % (bound['min'] * (1 - tol)))
            if 'max' in bound:
                stat.add('Maximum acceptable frequency (Hz)', '%f' % (bound['max'] * (1 + tol)))
        return stat


class _HeaderlessTopicDiagnostic:
    """A ``<topic> topic status`` task with a FrequencyStatus, added to ``diag``."""

    def __init__(self, name: str, diag, freq):
        self.name = f'{name} topic status'
        self.freq = FrequencyStatus(freq)
        diag.add(self.name, self.run)

    def tick(self) -> None:
        self.freq.tick()

    def clear_window(self) -> None:
        self.freq.clear()

    def run(self, stat):
        return self.freq.run(stat)


try:  # a ROS install: the real package (same names, same behaviour)
    from diagnostic_updater import (DiagnosticStatusWrapper, FrequencyStatus,  # noqa: F401
                                    FrequencyStatusParam, HeaderlessTopicDiagnostic, Updater)
    USING_DIAGNOSTIC_UPDATER = True
except ImportError:
    DiagnosticStatusWrapper = _DiagnosticStatusWrapper
    FrequencyStatus = _FrequencyStatus
    FrequencyStatusParam = _FrequencyStatusParam
    HeaderlessTopicDiagnostic = _HeaderlessTopicDiagnostic
    Updater = _Updater
    USING_DIAGNOSTIC_UPDATER = False


def topic_frequency(updater, topic: str, rate_hz: float, tolerance: float = 0.3,
                    window_size: int = 5):
    """Watch ``topic`` at ``rate_hz`` (+-tolerance); call ``.tick()`` per message sent."""
    bound = {'min': rate_hz, 'max': rate_hz}
    return HeaderlessTopicDiagnostic(topic, updater,
                                     FrequencyStatusParam(bound, tolerance, window_size))


class TriggeredRate:
    """
    A ``<topic> topic status`` for a triggered stream: its rate is the trigger rate.

    A fixed frequency bound would call an idle rig an error; instead each trigger counts
    as answered (``tick``) or missed (``miss``), and a window with misses is a WARN.
    """

    def __init__(self, updater, topic: str):
        self.name = f'{topic} topic status'
        self.lock = threading.Lock()
        self.events = self.misses = self.total = 0
        self.last = time.monotonic()
        updater.add(self.name, self.run)

    def tick(self) -> None:
        """Count one message sent."""
        with self.lock:
            self.events += 1
            self.total += 1

    def miss(self) -> None:
        """Count one trigger that got no message."""
        with self.lock:
            self.misses += 1

    def run(self, stat):
        with self.lock:
            now = time.monotonic()
            window = max(now - self.last, 1e-9)
            events, misses = self.events, self.misses
            self.events = self.misses = 0
            self.last = now
        if misses:
            stat.summary(WARN, f'{misses} trigger(s) without a frame.')
        elif events == 0:
            stat.summary(OK, 'No triggers in window.')
        else:
            stat.summary(OK, 'Every trigger answered')
        stat.add('Events in window', '%d' % events)
        stat.add('Missed triggers in window', '%d' % misses)
        stat.add('Events since startup', '%d' % self.total)
        stat.add('Duration of window (s)', '%f' % window)
        stat.add('Actual frequency (Hz)', '%f' % (events / window))
        return stat


def received_key(topic: str) -> str:
    """Return the key of a recorder's count of one topic's messages queued for the bag."""
    return f'received {topic}'


def newest_key(topic: str) -> str:
    """Return the key of the newest queued message's source stamp (ns) on ``topic``."""
    return f'newest {topic}'


SUBSCRIBERS = 'subscribers '


def subscribers_key(topic: str) -> str:
    """Return the key of how many readers a node's writer on ``topic`` has matched."""
    return f'{SUBSCRIBERS}{topic}'


def subscribers_topic(key: str) -> str | None:
    """Return the topic of a :func:`subscribers_key`, or None for any other key."""
    return key[len(SUBSCRIBERS):] if key.startswith(SUBSCRIBERS) else None


def writers_matched(said: dict, topic: str) -> list[int]:
    """
    Return the readers each status in ``said`` says its writer on ``topic`` has matched.

    ``said``: status name -> key -> value, as :func:`matched_subscribers` fills them; a
    value that is not a count is left out, as if unsaid.
    """
    out = []
    for values in said.values():
        try:
            out.append(int(values[subscribers_key(topic)]))
        except (KeyError, ValueError):
            pass
    return out


def matched_subscribers(publishers) -> dict:
    """
    Return each writer's matched readers as ``subscribers <topic>`` diagnostic values.

    The graph shows a new reader before the writer has matched it, and a message published
    in between never reaches it: the collector's ``recorder`` wait reads these to know that
    a recorder gets the rig's first frames.
    """
    return {subscribers_key(pub.topic_name): pub.get_subscription_count() for pub in publishers}


def fill(stat, level, message: str, values: dict, hardware_id: str = ''):
    """Fill a task's status (level, message, key-values) and return it."""
    stat.summary(level, message)
    if hardware_id:
        stat.hardware_id = hardware_id
    for k, v in values.items():
        stat.add(str(k), str(v))
    return stat

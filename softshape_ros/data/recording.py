"""
The recorder's engine: a bounded queue in front of one writer thread that owns the bag.

Subscription callbacks only append raw CDR bytes to the queue (never block, never
deserialise); when the queue is full (by count or bytes) the message is dropped and
counted. The writer thread writes, flushes so that at most ``flush_interval_s`` of data
sits in memory, and splits files; a write error (full disk) stops writing but not the
process. No rclpy here, so the benchmark and tests drive it directly.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict, deque

from softshape_ros.data.bag_writer import BagWriter, TopicSpec

RECORDING, PAUSED, FAILED, STOPPED = 'recording', 'paused', 'failed', 'stopped'


class Recording:
    """Queue + writer thread around a :class:`BagWriter`; thread-safe ``offer``."""

    def __init__(self, writer: BagWriter, queue_messages: int = 2000,
                 queue_bytes: int = 512 * 2**20, flush_interval_s: float = 1.0):
        if flush_interval_s <= 0:
            raise ValueError(f'flush_interval_s must be > 0, got {flush_interval_s}')
        self.writer = writer
        self.queue_messages, self.queue_bytes = int(queue_messages), int(queue_bytes)
        self.flush_interval_s = float(flush_interval_s)
        self._q = deque()
        self._q_bytes = 0
        self._cv = threading.Condition()
        self._paused = False
        self._stop = False
        self.received = defaultdict(int)
        self.paused_skipped = defaultdict(int)  # arrived while paused: not recorded
        self.drops = defaultdict(int)          # queue full
        self.refused = 0                       # arrived after the bag failed
        self.max_queue_seen = 0
        self.error = ''
        self._thread = threading.Thread(target=self._run, name='bag-writer', daemon=True)
        self._thread.start()

    # -- called from callbacks / services (any thread) ------------------------------------
    def add_topic(self, spec: TopicSpec) -> None:
        self._control(('topic', spec))

    def offer(self, topic: str, stamp_ns: int, data) -> bool:
        """Queue one message; False (and counted) if paused, failed or the queue is full."""
        with self._cv:
            if self._stop:
                return False
            if self._paused:
                self.paused_skipped[topic] += 1
                return False
            if self.error:
                self.refused += 1
                return False
            n = len(data)
            if len(self._q) >= self.queue_messages or self._q_bytes + n > self.queue_bytes:
                self.drops[topic] += 1
                return False
            self._q.append(('msg', topic, stamp_ns, data, time.monotonic()))
            self._q_bytes += n
            self.received[topic] += 1
            if len(self._q) > self.max_queue_seen:
                self.max_queue_seen = len(self._q)
            self._cv.notify()
        return True

    def pause(self) -> None:
        with self._cv:
            self._paused = True

    def resume(self) -> None:
        with self._cv:
            self._paused = False

    @property
    def paused(self) -> bool:
        return self._paused

    def split(self) -> None:
        self._control(('split',))

    def _control(self, item) -> None:
        with self._cv:
            self._q.append(item)
            self._cv.notify()

    def stats(self) -> dict:
        with self._cv:
            state = FAILED if self.error else (PAUSED if self._paused else
                                               (STOPPED if self._stop else RECORDING))
            return {
                'state': state,
                'messages_written': self.writer.message_count,
                'bytes_written': self.writer.bytes_written,
                'received': sum(self.received.values()),
                'received_by_topic': dict(sorted(self.received.items())),
                'skipped_while_paused': sum(self.paused_skipped.values()),
                'dropped_queue_full': sum(self.drops.values()),
                'dropped_after_error': self.refused,
                'queue_length': len(self._q),
                'queue_bytes': self._q_bytes,
                'max_queue_length': self.max_queue_seen,
                'current_file': self.writer.current_file,
                'files': len(self.writer.files),
                'error': self.error,
            }

    def stop(self, timeout: float = 60.0) -> dict:
        """Write what is queued, finalise the bag, join the thread; returns the metadata."""
        with self._cv:
            self._stop = True
            self._cv.notify()
        self._thread.join(timeout)
        if self._thread.is_alive():     # never close the bag under the writer's feet
            self.error = self.error or f'writer thread still busy after {timeout:.0f} s'
            return self.writer.metadata()
        return self.writer.close()

    # -- the writer thread --------------------------------------------------------------
    def _handle(self, item, oldest_unflushed):
        """Write one queue item; return the receive time of the oldest unflushed message."""
        if item is None:
            pass
        elif item[0] == 'msg':
            _, topic, stamp, data, t_recv = item
            if self.writer.write(topic, stamp, data) and oldest_unflushed is None:
                oldest_unflushed = t_recv
        elif item[0] == 'topic':
            self.writer.add_topic(item[1])
        elif item[0] == 'split':
            self.writer.split()
            oldest_unflushed = None
        # Flush when the oldest unflushed message has waited half the interval: the
        # other half covers writing, so the loss bound holds from receive time.
        if oldest_unflushed is not None and \
                time.monotonic() >= oldest_unflushed + self.flush_interval_s / 2:
            self.writer.flush()
            oldest_unflushed = None
        return oldest_unflushed

    def _run(self) -> None:
        oldest_unflushed = None
        while True:
            with self._cv:
                while not self._q and not self._stop:
                    timeout = None
                    if oldest_unflushed is not None:
                        timeout = oldest_unflushed + self.flush_interval_s / 2 - time.monotonic()
                        if timeout <= 0:
                            break
                    self._cv.wait(timeout)
                if not self._q and self._stop:
                    break
                item = self._q.popleft() if self._q else None
                if item is not None and item[0] == 'msg':
                    self._q_bytes -= len(item[3])
            try:
                oldest_unflushed = self._handle(item, oldest_unflushed)
            except Exception as exc:  # never die silently: fail loudly, keep what is written
                with self._cv:
                    self.error = self.error or f'writer: {type(exc).__name__}: {exc}'
                    self._q.clear()
                    self._q_bytes = 0
            if self.writer.failed and not self.error:
                with self._cv:
                    self.error = self.writer.failed
                    self._q.clear()
                    self._q_bytes = 0

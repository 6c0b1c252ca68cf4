"""A bag written by its own thread from a bounded in-memory cache, as rosbag2 records.

Receiving must never wait for the disk: a 1080p camera at 60 Hz is 373 MB/s, more than
many disks take, and a recorder that stops taking samples makes keep-last publishers
overwrite what it has not received, which DDS (Cyclone) does not report. So the recorder
hands each message to :class:`CachedBagWriter`, which queues it and returns at once; a
thread writes the queue to the :class:`~tpsr_ros.io.bag.BagWriter` (compression, CRCs
and the file writes release the GIL, so it runs beside the receiving thread). When the
cache already holds ``max_bytes``, :meth:`CachedBagWriter.put` refuses the message and
the caller counts it: a loss that is always known, unlike one inside the middleware.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Sequence
from typing import Any

from rosbags.interfaces import Qos

from tpsr_ros.io.bag import BagWriter

__all__ = ["CachedBagWriter"]


class CachedBagWriter:
    """``BagWriter.write`` through a bounded queue and a writer thread; other calls locked."""

    def __init__(self, writer: BagWriter, max_bytes: int) -> None:
        self.writer = writer
        self.max_bytes = int(max_bytes)
        self.queued_bytes = 0
        self._items: deque[tuple[str, int, bytes]] = deque()
        self._ready = threading.Condition()
        self._bag = threading.Lock()  # BagWriter is not thread-safe
        self._closing = False
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="bag-writer", daemon=True)
        self._thread.start()

    @property
    def path(self) -> Any:
        """The bag's directory."""
        return self.writer.path

    def put(self, topic: str, stamp_ns: int, data: bytes) -> bool:
        """Queue one message; False (nothing queued) when the cache is full.

        An error the writer thread met (a full disk) is raised here, on the caller's thread.
        """
        if self._error is not None:
            raise self._error
        with self._ready:
            if self._items and self.queued_bytes + len(data) > self.max_bytes:
                return False
            self._items.append((topic, stamp_ns, data))
            self.queued_bytes += len(data)
            self._ready.notify()
        return True

    def add_topic(self, topic: str, msgtype: str, qos: Sequence[Qos] = ()) -> None:
        """``BagWriter.add_topic``, between the writer thread's writes."""
        with self._bag:
            self.writer.add_topic(topic, msgtype, qos)

    def set_custom_data(self, key: str, value: str) -> None:
        """``BagWriter.set_custom_data``, between the writer thread's writes."""
        with self._bag:
            self.writer.set_custom_data(key, value)

    def flush(self) -> None:
        """``BagWriter.flush`` (what is still queued is not waited for)."""
        with self._bag:
            self.writer.flush()

    def _run(self) -> None:
        while True:
            with self._ready:
                while not self._items and not self._closing:
                    self._ready.wait()
                if not self._items:
                    return
                topic, stamp_ns, data = self._items[0]
            try:
                with self._bag:
                    self.writer.write(topic, stamp_ns, data)
            except BaseException as exc:
                self._error = exc
                return
            finally:
                with self._ready:  # put() never waits: nobody to wake
                    self._items.popleft()
                    self.queued_bytes -= len(data)

    def close(self) -> None:
        """Write everything queued, stop the thread and close the bag (it stays readable)."""
        with self._ready:
            self._closing = True
            self._ready.notify_all()
        self._thread.join()
        with self._bag:
            self.writer.close()
        if self._error is not None:
            raise self._error

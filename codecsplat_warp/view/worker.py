"""A background thread that does the latest requested work per key: the viewer's frame streaming (one key per
browser, its newest camera) and its re-encoding (one key, the newest λ and preset)."""

from __future__ import annotations

import sys
import threading
import traceback
from collections import OrderedDict
from typing import Callable, Hashable


class LatestWork:
    """Runs ``work(key, value)`` on its own thread for each requested key, oldest key first, with the value of the
    key's latest request: requests that arrive while a key waits replace its value (a camera that moved twice
    before its frame was rendered is rendered once, where it is now).

    An exception of ``work`` is printed to stderr with its traceback and the thread goes on with the next key: one
    failed frame or encode never stops the viewer.
    """

    def __init__(self, name: str, work: Callable[[Hashable, object], None]):
        self._work = work
        self._pending: OrderedDict[Hashable, object] = OrderedDict()
        self._condition = threading.Condition()
        self._stopped = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def request(self, key: Hashable, value: object = None) -> None:
        """Ask for ``work(key, value)``, replacing the value of a request of ``key`` that has not started."""
        with self._condition:
            self._pending[key] = value
            self._condition.notify()

    def forget(self, key: Hashable) -> None:
        """Drop a waiting request of ``key`` (a browser that left)."""
        with self._condition:
            self._pending.pop(key, None)

    def stop(self, timeout: float) -> None:
        """Drop the waiting requests, and wait up to ``timeout`` seconds for the running one to end."""
        with self._condition:
            self._stopped = True
            self._pending.clear()
            self._condition.notify()
        self._thread.join(timeout)

    def _next(self) -> tuple[Hashable, object] | None:
        """The oldest waiting request (blocks until there is one), or None once stopped."""
        with self._condition:
            while not self._pending and not self._stopped:
                self._condition.wait()
            if self._stopped:
                return None
            return self._pending.popitem(last=False)

    def _run(self) -> None:
        while (item := self._next()) is not None:
            try:
                self._work(*item)
            except Exception:  # noqa: BLE001 - a bug in one request: report it, keep serving
                print(f"codecsplat view: {self._thread.name} failed:", file=sys.stderr)
                traceback.print_exc()

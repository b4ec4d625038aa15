"""The node's hand-over between threads: a one-slot mailbox and a turnstile.

The executor thread drops each new cloud into a :class:`LatestMailbox` (replacing one nobody has
taken: a dropped frame); worker threads take numbered items from it and publish through a
:class:`Turnstile`, which lets them out in the order they were taken. Both only use
:class:`threading.Condition`; every wait is bounded or ends on ``close``.
"""

from __future__ import annotations

import threading
from typing import Any


class LatestMailbox:
    """A one-slot mailbox: ``put`` replaces a waiting item (counted as dropped); ``take`` waits, bounded."""

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._item: Any = None
        self._closed = False
        self._taken = 0

    def put(self, item: Any) -> bool:
        """Leave ``item`` for the worker; True if it replaced an item nobody had taken (a dropped frame)."""
        with self._condition:
            replaced = self._item is not None
            self._item = item
            self._condition.notify()
            return replaced

    def take(self, timeout: float) -> Any:
        """The waiting item (emptying the slot), or None after ``timeout`` seconds or once closed."""
        taken = self.take_numbered(timeout)
        return None if taken is None else taken[1]

    def take_numbered(self, timeout: float) -> tuple[int, Any] | None:
        """(number, item) like :meth:`take`; items are numbered 0, 1, 2, ... in the order they are taken."""
        with self._condition:
            if self._item is None and not self._closed:
                self._condition.wait(timeout)
            item, self._item = self._item, None
            if item is None:
                return None
            self._taken += 1
            return self._taken - 1, item

    def pending(self) -> bool:
        """True while an item waits to be taken."""
        with self._condition:
            return self._item is not None

    def close(self) -> None:
        """Wake every waiting ``take``."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()


class Turnstile:
    """Lets numbered holders through in number order (0, 1, 2, ...): the workers' publishing order.

    A holder with nothing to publish (a skipped or failed frame) releases its number at once; the
    others wait for their turn, publish, then release theirs.
    """

    def __init__(self) -> None:
        self._condition = threading.Condition()
        self._next = 0
        self._released: set[int] = set()
        self._closed = False

    def wait_turn(self, number: int, timeout: float | None = None) -> bool:
        """Wait until every lower number is released; False on timeout or once closed."""
        with self._condition:
            self._condition.wait_for(lambda: self._next == number or self._closed, timeout)
            return self._next == number and not self._closed

    def release(self, number: int) -> None:
        """``number`` is done (published, skipped or failed); in any order."""
        with self._condition:
            self._released.add(number)
            while self._next in self._released:
                self._released.remove(self._next)
                self._next += 1
            self._condition.notify_all()

    def close(self) -> None:
        """Release every waiter (they get False)."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()

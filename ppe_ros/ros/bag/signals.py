"""SIGINT / SIGTERM during a run and around it."""

from __future__ import annotations

import signal
import threading
from typing import Any


class Interrupted(KeyboardInterrupt):
    """A signal that stopped the command at once (``signum``: SIGINT or SIGTERM)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


class _SignalHandlers:
    """Installs ``self._handle`` for SIGINT and SIGTERM (in the main thread only: signals reach no other;
    elsewhere the caller's handling applies) and restores the previous handlers."""

    def __init__(self) -> None:
        self._previous: dict[int, Any] = {}

    def install(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for signum in (signal.SIGINT, signal.SIGTERM):
                self._previous[signum] = signal.signal(signum, self._handle)

    def restore(self) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)
        self._previous.clear()

    def ignore(self) -> None:
        """Ignore the signals whose handlers install() set (SIG_IGN), for a process that is about to exit:
        the interpreter's shutdown puts SIG_DFL back for signals with a Python handler (a signal after
        that would kill the process and replace its exit code), but leaves ignored ones ignored."""
        for signum in self._previous:
            signal.signal(signum, signal.SIG_IGN)
        self._previous.clear()

    def _handle(self, signum: int, frame: Any) -> None:
        raise NotImplementedError


class StopRequests(_SignalHandlers):
    """SIGINT / SIGTERM during a run: the first stops reading, a second drops the frames in flight.

    The handlers only count (writing the output is never interrupted halfway); a second signal
    raises KeyboardInterrupt only while an inline frame is being processed (``abortable``). Outside
    the writing of an output (opening and scanning an input, between inputs) a signal raises
    KeyboardInterrupt at once (``interruptible``): nothing is being written that it could cut.
    """

    def __init__(self) -> None:
        super().__init__()
        self.count = 0
        self.first_signal: int | None = None
        self.abortable = False
        self.interruptible = False

    def _handle(self, signum: int, frame: Any) -> None:
        self.count += 1
        if self.first_signal is None:
            self.first_signal = signum
        if self.interruptible:
            raise Interrupted(signum)
        if self.count > 1 and self.abortable:
            raise KeyboardInterrupt

    @property
    def stop(self) -> bool:
        return self.count > 0

    @property
    def drop(self) -> bool:
        return self.count > 1


class CommandSignals(_SignalHandlers):
    """SIGINT / SIGTERM outside :func:`process_bag`'s own handling: before it (opening and scanning
    the input) they stop the command; after it (the bag is closed, the summary is printed) they
    are ignored, so that a repeated Ctrl-C never ends in a traceback."""

    def __init__(self) -> None:
        super().__init__()
        self.done = False
        self.signum: int | None = None

    def _handle(self, signum: int, frame: Any) -> None:
        if self.signum is None:
            self.signum = signum
        if not self.done:
            raise KeyboardInterrupt

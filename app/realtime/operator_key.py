"""The operator's stop key in the terminal: space or Enter stops a real-time race (race.operator).

:class:`TerminalStopKey` is armed with ``arm`` (or as a context manager). On a terminal that this
process owns in the foreground, it switches stdin to cbreak mode (keys arrive one at a time, not
echoed; Ctrl-C still interrupts) and ``poll()`` reads whatever was typed without blocking
(``select`` with a zero timeout). Otherwise (stdin a pipe or a file, or the race started in the
background, where changing the terminal mode would stop the process with SIGTTOU) it is a no-op
that never stops the race.

The terminal's mode is restored on every way out: ``close`` (or the end of the ``with`` block) in a
``finally`` (return, exception, Ctrl-C), interpreter exit (atexit) and SIGTERM (the handler
restores, then hands the signal on to the previous handler, so the serial link's neutral-on-SIGTERM
and the default exit still happen). Input typed before the race (type-ahead) is discarded when the
key is armed.
"""
from __future__ import annotations

import atexit
import os
import select
import signal
import sys
import termios
import threading

STOP_KEYS = frozenset(b" \r\n")


class TerminalStopKey:
    def __init__(self, stream=None) -> None:
        self._stream = sys.stdin if stream is None else stream
        self._fd: int | None = None
        self._saved = None              # termios attributes to restore
        self._previous_sigterm = None
        self.active = False             # the key works (a foreground terminal)

    # ---- OperatorInput
    def poll(self) -> bool:
        if not self.active:
            return False
        try:
            ready, _, _ = select.select([self._fd], [], [], 0)
            if not ready:
                return False
            typed = os.read(self._fd, 64)
        except OSError:  # the terminal went away: no stop key any more (Ctrl-C still works)
            self.active = False
            return False
        return any(byte in STOP_KEYS for byte in typed)

    # ---- arming and restoring (also as a context manager)
    def __enter__(self) -> "TerminalStopKey":
        return self.arm()

    def __exit__(self, *exc) -> None:
        self.close()

    def arm(self) -> "TerminalStopKey":
        """Switch the terminal to cbreak mode (when it is ours, module doc) and install the restore hooks."""
        fd = self._terminal_fd()
        if fd is None:
            return self
        try:
            saved = termios.tcgetattr(fd)
            mode = termios.tcgetattr(fd)
            mode[3] &= ~(termios.ICANON | termios.ECHO)  # lflags: key by key, no echo; ISIG kept (Ctrl-C)
            mode[6][termios.VMIN], mode[6][termios.VTIME] = 1, 0
            termios.tcsetattr(fd, termios.TCSANOW, mode)
            termios.tcflush(fd, termios.TCIFLUSH)  # type-ahead is not a stop
        except termios.error:
            return self
        self._fd, self._saved, self.active = fd, saved, True
        atexit.register(self.restore)
        if threading.current_thread() is threading.main_thread():
            self._previous_sigterm = signal.signal(signal.SIGTERM, self._on_sigterm)
        return self

    def close(self) -> None:
        """Restore the terminal and remove the hooks (idempotent)."""
        self.restore()
        atexit.unregister(self.restore)
        if self._previous_sigterm is not None and threading.current_thread() is threading.main_thread():
            if signal.getsignal(signal.SIGTERM) == self._on_sigterm:  # only undo our own handler
                signal.signal(signal.SIGTERM, self._previous_sigterm)
            self._previous_sigterm = None

    def restore(self) -> None:
        """Put the terminal back in the mode it had (idempotent)."""
        if self._saved is not None:
            try:
                termios.tcsetattr(self._fd, termios.TCSANOW, self._saved)
            except termios.error:
                pass
            self._saved = None
        self.active = False

    def _on_sigterm(self, signum, frame) -> None:
        self.restore()
        previous = self._previous_sigterm
        if callable(previous):
            previous(signum, frame)
        elif previous in (signal.SIG_DFL, None):
            signal.signal(signum, signal.SIG_DFL)  # re-deliver: the exit status still says "killed by SIGTERM"
            os.kill(os.getpid(), signum)

    def _terminal_fd(self) -> int | None:
        """stdin's descriptor if it is a terminal this process may change, else None."""
        try:
            fd = self._stream.fileno()
        except (AttributeError, OSError, ValueError):  # pytest's captured stdin has no descriptor
            return None
        if not os.isatty(fd):
            return None
        try:
            if os.tcgetpgrp(fd) != os.getpgrp():  # started in the background (`race --hil &`)
                return None
        except OSError:  # not our controlling terminal: changing its mode cannot stop us
            pass
        return fd

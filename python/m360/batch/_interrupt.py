"""Ctrl-C that reaches the main thread, whichever thread the kernel gave it to.

A signal sent to a process is handled by one of its threads, and on Linux that is not always
the main thread: rayon's, BLAS's and ONNX Runtime's threads and the process pool's manager
thread are candidates too. CPython runs Python signal handlers only in the main thread, at its
next bytecode. If the main thread is blocked in a system call at that moment (reading a pipe,
waiting for a future) and the signal went to another thread, nothing interrupts the call and
Ctrl-C is lost until it returns, which may be never: a batch run waiting for its workers hung.

:class:`MainThreadInterrupts` installs a handler and a wake-up pipe (``signal.set_wakeup_fd``,
written by CPython's C-level handler in whichever thread caught the signal). A watcher thread
reads the pipe and, if the main thread has not yet run the handler, sends SIGINT to the main
thread itself (``pthread_kill``), which interrupts its blocking call. It kicks at most once:
the kick's own echo on the pipe is then ignored, so the two can never ping-pong, and the
handler is idempotent, so a kick that races the real delivery does no harm.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Callable, Iterator
from types import FrameType, TracebackType
from typing import Any

Handler = Callable[[int, FrameType | None], Any]


class MainThreadInterrupts:
    """Context manager: run ``handler`` for SIGINT in the main thread, promptly.

    ``handler`` must be idempotent: it may run more than once for one Ctrl-C. Outside the
    main thread, or where POSIX thread signals are missing (Windows), or when the process
    already has a wake-up fd (an asyncio loop), it only installs ``handler`` if it can and
    otherwise does nothing.
    """

    def __init__(self, handler: Handler) -> None:
        self._handler = handler
        self._handled = False
        self._previous_handler: Any = None
        self._previous_fd = -1
        self._pipe: tuple[int, int] | None = None
        self._watcher: threading.Thread | None = None

    def __enter__(self) -> MainThreadInterrupts:
        if threading.current_thread() is not threading.main_thread():
            return self  # signals are delivered to the main thread's handler: not ours
        self._previous_handler = signal.signal(signal.SIGINT, self._on_sigint)
        if not hasattr(signal, "pthread_kill"):
            return self
        read_fd, write_fd = os.pipe()
        os.set_blocking(write_fd, False)
        previous = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
        if previous != -1:  # someone else's wake-up fd (an event loop): leave it theirs
            signal.set_wakeup_fd(previous)
            os.close(read_fd)
            os.close(write_fd)
            return self
        self._pipe = (read_fd, write_fd)
        self._watcher = threading.Thread(
            target=self._watch,
            args=(read_fd, threading.main_thread().ident),
            name="m360-ctrl-c",
            daemon=True,
        )
        self._watcher.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        if self._previous_handler is None:
            return
        if self._pipe is not None:
            signal.set_wakeup_fd(-1)
            os.close(self._pipe[1])  # the watcher reads end-of-file and returns
            if self._watcher is not None:
                self._watcher.join()
            os.close(self._pipe[0])
        signal.signal(signal.SIGINT, self._previous_handler)

    def _on_sigint(self, signum: int, frame: FrameType | None) -> None:
        self._handled = True
        self._handler(signum, frame)

    def _watch(self, read_fd: int, main_ident: int | None) -> None:
        kicked = False
        while True:
            data = os.read(read_fd, 64)
            if not data:
                return
            if signal.SIGINT in data and not self._handled and not kicked and main_ident:
                kicked = True
                with contextlib.suppress(ProcessLookupError, OSError):
                    signal.pthread_kill(main_ident, signal.SIGINT)


def install_for_process(handler: Handler) -> None:
    """Route SIGINT to ``handler`` in the main thread for the rest of this process's life."""
    MainThreadInterrupts(handler).__enter__()


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """Hold back Ctrl-C while the block runs; deliver it when the block ends.

    For the few steps that must not be cut in two, such as taking a claim (create the lock
    file, lock it, hand it to the code that removes it): a KeyboardInterrupt between two of
    them would leave the file behind. A SIGINT that arrives meanwhile is recorded, and the
    handler that was installed before runs as the block exits, so Ctrl-C is late by the
    length of the block, never lost. Blocks nest. Outside the main thread Python runs no
    signal handler, so there is nothing to hold back.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    arrived = False

    def record(signum: int, frame: FrameType | None) -> None:
        nonlocal arrived
        arrived = True

    previous = signal.signal(signal.SIGINT, record)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if arrived:
            if callable(previous):
                previous(signal.SIGINT, None)
            elif previous == signal.SIG_DFL:
                signal.raise_signal(signal.SIGINT)

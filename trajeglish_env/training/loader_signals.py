"""DataLoader workers that leave Ctrl-C and SIGTERM to the training process.

A signal sent to the whole process group (Ctrl-C at a terminal, ``timeout``, a job scheduler's ``kill``)
reaches the loader's workers too. torch's worker handler ends a worker on any SIGTERM its parent did not
send, and the training process then raised "DataLoader worker (pid N) is killed by signal: Terminated"
over its own interrupt (a traceback and exit code 1, or an "Exception ignored" message). Here the workers
start with both signals held (:func:`loader_batches`) and keep them held, so only the training process
unwinds, and it shuts the loader down. A SIGTERM from the parent itself (torch's shutdown of a worker that
does not stop) still ends a worker, as torch's rule has it.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import traceback
from collections.abc import Iterable, Iterator
from typing import Any

INTERRUPTS = {signal.SIGINT, signal.SIGTERM}
_MASKS = hasattr(signal, "pthread_sigmask")  # POSIX; elsewhere signals are left as they are


@contextlib.contextmanager
def held_interrupts() -> Iterator[None]:
    """Ctrl-C and SIGTERM wait (pending, not lost) while the block runs; processes it starts inherit them
    held. They arrive when it ends."""
    old = signal.pthread_sigmask(signal.SIG_BLOCK, INTERRUPTS) if _MASKS else None
    try:
        yield
    finally:
        if old is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _batch_transfer_cut(kind: type[BaseException], value: BaseException, tb: Any) -> bool:
    """Whether an uncaught error is a batch's file descriptor transfer cut off: multiprocessing's
    ``resource_sharer`` thread reports it through ``sys.excepthook`` (a traceback on stderr) when the other
    end of a worker's connection goes away, as the training process does when it is interrupted."""
    if not issubclass(kind, (OSError, EOFError)):
        return False
    return any(frame.filename.endswith("resource_sharer.py") for frame in traceback.extract_tb(tb))


def quiet_transfer_errors() -> None:
    """Drop the tracebacks of batch transfers cut off by an interrupt (:func:`_batch_transfer_cut`);
    every other uncaught error is reported as before. Idempotent."""
    hook = sys.excepthook
    if getattr(hook, "drops_cut_transfers", False):
        return

    def excepthook(kind: type[BaseException], value: BaseException, tb: Any) -> None:
        if not _batch_transfer_cut(kind, value, tb):
            hook(kind, value, tb)

    excepthook.drops_cut_transfers = True  # type: ignore[attr-defined]
    sys.excepthook = excepthook


def quiet_worker(worker_id: int) -> None:
    """A loader worker's ``worker_init_fn``: Ctrl-C ignored, SIGTERM held, a thread that ends the worker
    on a SIGTERM from its parent and drops any other, and no traceback for a batch transfer the interrupted
    trainer cut off."""
    quiet_transfer_errors()
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    if not _MASKS:
        return
    signal.pthread_sigmask(signal.SIG_BLOCK, INTERRUPTS)  # threads started from here on inherit it
    if hasattr(signal, "sigwaitinfo"):
        threading.Thread(target=_end_on_parents_sigterm, args=(os.getppid(),), daemon=True).start()


def _end_on_parents_sigterm(parent: int) -> None:
    """Waits for SIGTERMs; the parent's ends the process at once (torch's worker handler does the same)."""
    while True:
        if signal.sigwaitinfo({signal.SIGTERM}).si_pid == parent:
            os._exit(0)


@contextlib.contextmanager
def loader_batches(loader: Iterable[Any]) -> Iterator[Iterator[Any]]:
    """The loader's batches, its workers started with interrupts held and shut down when the block ends,
    however it ends (an interrupt included), not whenever the iterator is freed."""
    quiet_transfer_errors()  # the trainer's side of a batch transfer an interrupt cuts off
    with held_interrupts():
        batches = iter(loader)
    try:
        yield batches
    finally:
        shutdown = getattr(batches, "_shutdown_workers", None)  # what torch's __del__ calls; idempotent
        if shutdown is not None:
            shutdown()

"""The ``busy`` section of ``trajeglish bench``: the batched env at the default thread setting, idle and
then with one other busy process on the machine (issue 16: multi-threaded decoding collapsed beside one
busy process; the target is >= 0.8x the idle speed at B = 1, 8 and 128).

The busy process is a child spinning one core in a pure-Python loop. It is started before the timed run
and killed (and reaped) after it, errors included; should this process die first, the child notices
that its parent changed and ends itself, so it is never left behind."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

BUSY_BATCHES = (1, 8, 128)  # the batch sizes of the target
# spins one core; every million iterations it checks that its parent is still the one that started it
SPIN = """import os
parent = os.getppid()
while os.getppid() == parent:
    for _ in range(1_000_000):
        pass
"""

EnvRun = Callable[[int], dict[str, Any]]  # batch size -> one env_speed result (measured in its process)


class Spinner:
    """A running busy child process: its ``pid``, and the CPU it has used so far."""

    def __init__(self, process: subprocess.Popen[bytes]):
        self.process = process
        self.pid = process.pid
        self.started = time.perf_counter()

    def cpu_seconds(self) -> float | None:
        """CPU seconds the child has used (user + system; None where /proc is not readable)."""
        try:
            with open(f"/proc/{self.pid}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:
            return None
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime

    def cpu_share(self) -> float | None:
        """The share of one core the child has used since it started (about 1 when it got a core)."""
        cpu = self.cpu_seconds()
        wall = time.perf_counter() - self.started
        return None if cpu is None or wall <= 0 else round(cpu / wall, 3)


@contextmanager
def busy_process() -> Iterator[Spinner]:
    """One child process spinning one core for the duration of the ``with`` block; killed and reaped on
    exit, whether the block ends normally or with an error."""
    process = subprocess.Popen([sys.executable, "-c", SPIN], stdin=subprocess.DEVNULL)
    try:
        yield Spinner(process)
    finally:
        process.kill()
        process.wait()


def busy_batches(batches: tuple[int, ...], quick: bool) -> tuple[int, ...]:
    """The configured batch sizes the section measures: those among :data:`BUSY_BATCHES` (quick: B = 1
    only)."""
    wanted = (1,) if quick else BUSY_BATCHES
    return tuple(b for b in wanted if b in batches)


def busy_section(batches: tuple[int, ...], run: EnvRun) -> dict[str, Any]:
    """Per batch size, ``run`` idle and then beside one busy process: ``idle`` and ``busy`` (the two env
    runs), their ``agent_steps_per_s``, ``busy_to_idle`` (busy / idle) and ``spinner_cpu_share`` (the
    share of a core the busy process got during the busy run)."""
    if not batches:
        sizes = ", ".join(str(b) for b in BUSY_BATCHES)
        return {"skipped": f"none of the batch sizes {sizes} is configured (--batches)"}
    out: dict[str, Any] = {}
    for b in batches:
        idle = run(b)
        with busy_process() as spinner:
            busy = run(b)
            share = spinner.cpu_share()
        idle_rate, busy_rate = idle["agent_steps_per_s"], busy["agent_steps_per_s"]
        out[str(b)] = {
            "idle_agent_steps_per_s": idle_rate,
            "busy_agent_steps_per_s": busy_rate,
            "busy_to_idle": round(busy_rate / idle_rate, 3),
            "spinner_cpu_share": share,
            "idle": idle,
            "busy": busy,
        }
    return out

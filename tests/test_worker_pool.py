"""Process pools that stop with their caller: an interrupt cancels the queued jobs and ends the workers at
once (ProcessPoolExecutor's own exit ran every queued job first; a second Ctrl-C could deadlock it), and
the CLI turns SIGTERM and Ctrl-C into one line and exit code 130."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from trajeglish_env.worker_pool import worker_pool


def _slow(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


def test_an_interrupt_cancels_the_queue_and_ends_the_workers() -> None:
    start = time.perf_counter()
    with pytest.raises(KeyboardInterrupt), worker_pool(2) as pool:
        pool.submit(_slow, 0.0).result(timeout=120)  # the workers are up
        futures = [pool.submit(_slow, 5.0) for _ in range(8)]
        time.sleep(0.5)
        processes = list(pool._processes.values())
        raise KeyboardInterrupt  # as Ctrl-C in the caller
    assert time.perf_counter() - start < 4.5  # not 8 x 5 s of queued jobs over 2 workers, nor one of them
    assert len(processes) == 2 and all(p.exitcode is not None for p in processes)
    assert sum(f.cancelled() for f in futures) >= 3  # those not handed to the workers' queue yet


def test_the_pool_finishes_its_jobs_when_nothing_goes_wrong() -> None:
    with worker_pool(2) as pool:
        results = list(pool.map(_slow, [0.0] * 4))
    assert len(results) == 4 and os.getpid() not in results


@pytest.mark.skipif(sys.platform != "linux", reason="process groups and /proc")
def test_sigterm_stops_generate_with_workers_in_one_line(tmp_path: Path) -> None:
    """`kill` of a `generate --workers 2` job: exit 130 within seconds, its workers gone (they ran on,
    orphaned, before), the shards written so far whole and resumable."""
    command = [sys.executable, "-m", "trajeglish_env.cli", "generate", "--scenes", "40", "--scenes-per-shard"]
    command += ["1", "--workers", "2", "--seed", "3", "--out", str(tmp_path / "g"), "--quiet"]
    job = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not list((tmp_path / "g").glob("*.scn.npz")):
        time.sleep(0.2)  # the workers are running once a shard is written
    children = [int(p) for p in Path(f"/proc/{job.pid}/task/{job.pid}/children").read_text().split()]
    assert children, "no worker processes"
    job.send_signal(signal.SIGTERM)
    _, err = job.communicate(timeout=60)
    assert job.returncode == 130, err
    assert err.strip().splitlines()[-1].startswith("trajeglish generate: interrupted;")
    deadline = time.monotonic() + 15  # the workers end at once; multiprocessing's resource tracker soon
    while time.monotonic() < deadline and [c for c in children if Path(f"/proc/{c}").exists()]:
        time.sleep(0.2)
    assert not [c for c in children if Path(f"/proc/{c}").exists()], "orphaned workers"

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


def _holding(folder: str) -> int:
    """A job that holds a temporary folder and a child process (as a SUMO run does) until it is ended."""
    import tempfile

    with tempfile.TemporaryDirectory(dir=folder):
        subprocess.run(["sleep", "30"], check=False)
    return 0


@pytest.mark.skipif(sys.platform != "linux", reason="/proc")
def test_ended_workers_remove_their_temporary_folders_and_tools(tmp_path: Path) -> None:
    """SIGTERM unwinds a worker: its temporary folder is removed and the tool it runs is killed (they
    were left behind, the tool running on)."""
    with pytest.raises(KeyboardInterrupt), worker_pool(1) as pool:
        job = pool.submit(_holding, str(tmp_path))
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and not list(tmp_path.iterdir()):
            time.sleep(0.1)
        time.sleep(0.5)  # the sleep tool has started
        (worker,) = pool._processes.values()
        tools = [int(p) for p in Path(f"/proc/{worker.pid}/task/{worker.pid}/children").read_text().split()]
        raise KeyboardInterrupt
    assert job.cancelled() or job.done()
    assert list(tmp_path.iterdir()) == [] and tools
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(Path(f"/proc/{t}").exists() for t in tools):
        time.sleep(0.1)
    assert not any(Path(f"/proc/{t}").exists() for t in tools), "the tool outlived its worker"


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


def _ctrl_c_as_at_a_terminal() -> None:
    """The job's Ctrl-C as a terminal's: a test run started in the background (``cmd &``, nohup) ignores
    SIGINT, and its children inherit that (the job then ran on through the test's Ctrl-C)."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


def _workers_of(pid: int) -> list[int]:
    """The spawned pool workers among ``pid``'s children (not multiprocessing's resource tracker)."""
    children = Path(f"/proc/{pid}/task/{pid}/children").read_text().split()
    found = []
    for child in children:
        try:
            line = Path(f"/proc/{child}/cmdline").read_bytes()
        except OSError:
            continue
        if b"spawn_main" in line and b"resource_tracker" not in line:
            found.append(int(child))
    return found


@pytest.mark.skipif(sys.platform != "linux", reason="process groups and /proc")
def test_ctrl_c_while_the_workers_start_prints_only_the_callers_line(tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the process group) while `generate --workers 2`'s spawned workers still import:
    each printed a KeyboardInterrupt traceback before the caller's one line; they start with it held now."""
    # scenes enough that the job is still running when Ctrl-C comes, however fast the machine
    command = [sys.executable, "-m", "trajeglish_env.cli", "generate", "--scenes", "5000"]
    command += ["--scenes-per-shard", "1", "--workers", "2", "--out", str(tmp_path / "g"), "--quiet"]
    job = subprocess.Popen(
        command,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_ctrl_c_as_at_a_terminal,
    )
    deadline = time.monotonic() + 60
    while job.poll() is None and time.monotonic() < deadline and len(_workers_of(job.pid)) < 2:
        time.sleep(0.02)
    time.sleep(0.3)  # the workers' Python is up (it handles Ctrl-C) and imports (for seconds)
    for worker in _workers_of(job.pid):  # Ctrl-C reaches them first (it raced the caller's teardown)
        os.kill(worker, signal.SIGINT)
    time.sleep(1.0)
    assert job.poll() is None, "the job ended before Ctrl-C"
    os.killpg(job.pid, signal.SIGINT)
    _, err = job.communicate(timeout=60)
    assert job.returncode == 130, err
    assert "Traceback" not in err, err
    assert err.strip().splitlines()[-1].startswith("trajeglish generate: interrupted;")

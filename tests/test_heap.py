"""The decoding engines' heap policy: freed activations are reused instead of fresh kernel pages (which cost
a page fault per 4 kB), it is turned off by TRAJEGLISH_KEEP_HEAP=0, and it changes no sampled number."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# allocates 24 activations of 4 MB and frees them, 10 times (as a decoding step does), and prints the minor
# page faults that took, with the policy applied or not. Without it glibc gives the 96 MB freed at the
# heap's top back to the kernel whatever its history: its own trim threshold is twice its mmap threshold,
# which never rises above 32 MB
PROBE = """
import json, resource, sys, torch
from trajeglish_env.heap import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "policy" else False
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def step():
    xs = [torch.ones(1024 * 1024) for _ in range(24)]
    return sum(float(x.sum()) for x in xs)
for _ in range(3):
    step()
before = faults()
for _ in range(10):
    step()
print(json.dumps({"applied": applied, "faults": faults() - before}))
"""


def probe(mode: str, **env: str) -> dict:
    """The probe in a fresh process whose environment is the shell's basics only: variables other tests of
    the same worker leave behind must not change how the C heap behaves there."""
    basics = {k: os.environ[k] for k in ("PATH", "HOME", "LANG", "TMPDIR") if k in os.environ}
    done = subprocess.run(
        [sys.executable, "-c", PROBE, mode],
        capture_output=True,
        text=True,
        check=True,
        env={**basics, **env},
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


def huge_pages_always() -> bool:
    """Transparent huge pages for every allocation: faults are then counted per 2 MB, not per 4 kB."""
    try:
        return "[always]" in Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and /proc page faults")
@pytest.mark.skipif(huge_pages_always(), reason="page faults are counted per huge page")
def test_freed_memory_is_reused_instead_of_fresh_pages() -> None:
    default, policy = probe("default"), probe("policy")
    assert policy["applied"] is True
    # without the policy every step faults its 24,576 pages back in; with it the heap's pages are reused
    # (the heap may still grow once)
    assert default["faults"] > 8 * 24_576
    assert policy["faults"] <= 24_576 + 2_048
    assert probe("policy", TRAJEGLISH_KEEP_HEAP="0")["applied"] is False


ENGINE = """
from trajeglish_env import heap
from trajeglish_env.benchmark.workloads import model_checkpoint
from trajeglish_env.sampler.engine import BatchEngine
before = heap._done
BatchEngine(model_checkpoint()[0], 1)
print(before, heap._done)
"""


def test_engines_apply_the_policy() -> None:
    done = subprocess.run([sys.executable, "-c", ENGINE], capture_output=True, text=True, check=True)
    before, after = done.stdout.split()
    wanted = sys.platform.startswith("linux") and os.environ.get("TRAJEGLISH_KEEP_HEAP") != "0"
    assert before == "None" and after == str(wanted)  # a fresh process: the engine applied it

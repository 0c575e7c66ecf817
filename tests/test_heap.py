"""The decoding engines' heap policy: freed activations are reused instead of fresh kernel pages (which cost
a page fault per 4 kB), it is turned off by TRAJEGLISH_KEEP_HEAP=0, and it changes no sampled number."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from trajeglish_env.heap import keep_freed_memory

# allocates and frees activations 10 times (as a decoding step does), and prints the minor page faults
# that took, with the policy applied or not. They are 40 MB: above the 32 MB that glibc's own threshold
# ever rises to, so that without the policy every one is fresh kernel pages, whatever the heap's history
# (the engine's 3-10 MB activations fault only some of the time without it)
PROBE = """
import json, resource, sys, torch
from trajeglish_env.heap import keep_freed_memory
applied = keep_freed_memory() if sys.argv[1] == "policy" else False
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def step():
    a = torch.ones(10 * 1024, 1024)
    return float((a * 2).sum())
for _ in range(3):
    step()
before = faults()
for _ in range(10):
    step()
print(json.dumps({"applied": applied, "faults": faults() - before}))
"""


def probe(mode: str, **env: str) -> dict:
    done = subprocess.run(
        [sys.executable, "-c", PROBE, mode],
        capture_output=True,
        text=True,
        check=True,
        env={**os.environ, **env},
    )
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt and /proc page faults")
def test_freed_memory_is_reused_instead_of_fresh_pages() -> None:
    default, policy = probe("default"), probe("policy")
    assert policy["applied"] is True
    # without the policy each of the 20 tensors of 40 MB is 10,240 fresh pages; with it the heap's pages
    # are reused (the heap may still grow once or twice)
    assert default["faults"] > 20 * 10_000
    assert policy["faults"] <= 3 * 10_240
    assert probe("policy", TRAJEGLISH_KEEP_HEAP="0")["applied"] is False


def test_engines_apply_the_policy() -> None:
    from helpers import tiny

    from trajeglish_env.sampler.engine import BatchEngine

    BatchEngine(tiny(), 1)
    assert keep_freed_memory() is (
        sys.platform.startswith("linux") and os.environ.get("TRAJEGLISH_KEEP_HEAP") != "0"
    )

"""Issue 17, bug 8: ``import trajeglish_env`` alone registers the Gymnasium and the PettingZoo ids.

Each check runs in a fresh interpreter: the test session itself has imported ``trajeglish_env.env``.
"""

from __future__ import annotations

import os
import subprocess
import sys

from helpers import REPO

_SCRIPT = """
import sys
import gymnasium
import pettingzoo
import trajeglish_env

light = sorted(m for m in ("torch", "trajeglish_env.env") if m in sys.modules)
assert not light, f"import trajeglish_env loaded {light}"
assert "trajeglish_env/Ego-v0" in gymnasium.envs.registry
aec = pettingzoo.make("aec", "trajeglish_env/Traffic-v0", npc="replay")
par = pettingzoo.make("parallel", "trajeglish_env/Traffic-v0", npc="replay")
aec.reset(seed=0)
observations, _ = par.reset(seed=0)
assert isinstance(aec, pettingzoo.AECEnv) and isinstance(par, pettingzoo.ParallelEnv)
assert aec.agents and set(observations) == set(par.agents)
import trajeglish_env.env  # importing the env package afterwards registers nothing twice
print("ok", type(aec.unwrapped).__name__)
"""


def test_plain_import_registers_pettingzoo_and_gymnasium_ids() -> None:
    env = {
        **os.environ,
        "PYTHONPATH": str(REPO),
        "OMP_NUM_THREADS": "1",
        "PYTHONWARNINGS": "error::UserWarning",
    }
    done = subprocess.run(
        [sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, cwd=REPO, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["ok", "raw_env"]

"""Fixtures (the shared builders live in ``helpers.py``) and one torch thread per test worker."""

from __future__ import annotations

import pytest
import torch
from helpers import straight_road_scene

from trajeglish_env.scenario import Scenario


@pytest.fixture
def straight_scene() -> Scenario:
    return straight_road_scene()


# Tests run in parallel workers (pytest -n 2) on small tensors: one intra-op thread each avoids
# oversubscribing the cores (thread spin-waits made small decodes ~20x slower).
torch.set_num_threads(1)

"""Helpers shared by the benchmark scripts: scene data for benchmarks and JSON output."""

from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path
from typing import Any


def scene_dir(data: str | None, scenes: int = 32, source: str = "highway", seed: int = 12345) -> Path:
    """``data`` if given, else a cached directory of freshly generated scenes (created on first use)."""
    if data:
        return Path(data)
    from trajeglish_env.sources.generation import GenerationConfig, generate

    out = Path(tempfile.gettempdir()) / f"trajeglish_bench_{source}_{scenes}_{seed}"
    generate(GenerationConfig(source, scenes, seed), out, workers=1, progress=True)
    return out


def report(result: dict[str, Any], as_json: bool) -> None:
    """Print a result as JSON (stdout) or as aligned lines."""
    if as_json:
        print(json.dumps(result, indent=2))
    else:
        for k, v in result.items():
            print(f"{k:>32}: {v}", file=sys.stdout)

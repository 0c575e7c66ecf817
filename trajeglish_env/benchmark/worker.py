"""One batched-env measurement in its own process (``python -m trajeglish_env.benchmark.worker SPEC``,
SPEC a JSON object of :func:`trajeglish_env.benchmark.measure.env_speed` arguments); prints one JSON line."""

from __future__ import annotations

import json
import os
import sys


def main() -> None:
    from trajeglish_env.benchmark.measure import env_speed
    from trajeglish_env.worker_pool import die_with_parent

    die_with_parent(
        os.getppid()
    )  # a bench killed by SIGKILL takes its run along (it ran on, up to 32 rounds)

    spec = json.loads(sys.argv[1])
    print(json.dumps(env_speed(**spec)))


if __name__ == "__main__":
    main()

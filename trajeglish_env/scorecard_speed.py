"""The scorecard's ``speed`` part (issue 16's "nothing else gets slower"): a candidate's env speed against
the shipped model's, timed in interleaved pairs."""

from __future__ import annotations

from typing import Any


def speed_part(card: Any, key: str, ckpt: Any) -> dict[str, Any]:
    """Agent-steps/s of the batched env (24 agents a scene, guarded NPCs of this checkpoint, one torch
    thread) against the shipped model's, in interleaved pairs (the order alternates), per batch size, each
    run timed over at least ``speed_min_seconds``; the ratio of the medians. The shipped model itself is
    the reference."""
    import statistics

    from trajeglish_env.benchmark.measure import env_speed
    from trajeglish_env.checkpoint import load_pretrained, pretrained_path
    from trajeglish_env.file_digest import file_sha256

    if not pretrained_path().is_file():
        return {"skipped": f"no shipped model to time against ({pretrained_path()} is missing)"}
    if file_sha256(ckpt.path) == file_sha256(pretrained_path()):
        return {"reference": True}
    shipped = load_pretrained()
    rates: dict[str, dict[int, list[float]]] = {"model": {}, "shipped": {}}
    for rep in range(card.config.speed_repeats):
        for batch in card.config.speed_batches:
            pair = (("shipped", shipped), ("model", ckpt))
            for who, model in pair if rep % 2 == 0 else pair[::-1]:
                run = env_speed(
                    batch,
                    "trajeglish_guard",
                    torch_threads=1,
                    checkpoint=model,
                    min_seconds=card.config.speed_min_seconds,
                )
                rates[who].setdefault(batch, []).append(run["agent_steps_per_s"])
    return {
        str(batch): {
            "model": statistics.median(rates["model"][batch]),
            "shipped": statistics.median(rates["shipped"][batch]),
            "ratio": round(
                statistics.median(rates["model"][batch]) / statistics.median(rates["shipped"][batch]), 3
            ),
            "runs": {who: rates[who][batch] for who in rates},
        }
        for batch in card.config.speed_batches
    }

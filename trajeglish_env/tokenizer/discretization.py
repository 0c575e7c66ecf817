"""Discretization-error and collision metrics of a tokenizer on held-out trajectories, and their plots.

Errors are the mean corner distance between each logged state and its tokenized state, over every valid
step that is not an anchor (anchors are copies of the log, see :mod:`.tokenize`), reported in cm.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from trajeglish_env.scenario import AgentKind
from trajeglish_env.tokenizer.collisions import collision_flags
from trajeglish_env.tokenizer.coverage import DRIFT_TOLERANCE_M, drift_report, envelope_error
from trajeglish_env.tokenizer.data import TrajectorySet
from trajeglish_env.tokenizer.tokenize import TokenizedTrajectories, tokenize
from trajeglish_env.tokenizer.vocabulary import MotionVocabulary

THRESHOLDS_CM = (2.0, 5.0, 10.0)


def _rounded(x: float) -> float | None:
    return None if not np.isfinite(x) else round(float(x), 5)


def error_summary(tok: TokenizedTrajectories, kind: np.ndarray) -> dict[str, Any]:
    """Mean error (cm), fraction of steps worse than 2/5/10 cm, step counts; overall and per class."""
    measured = tok.valid & ~tok.anchored

    def summarize(mask: np.ndarray) -> dict[str, Any]:
        err = tok.error[mask] * 100.0
        out: dict[str, Any] = {"steps": int(err.size), "mean_cm": _rounded(err.mean()) if err.size else None}
        out["frac_above_cm"] = {
            f"{c:g}": (_rounded((err > c).mean()) if err.size else None) for c in THRESHOLDS_CM
        }
        out["max_cm"] = _rounded(err.max()) if err.size else None
        return out

    result = summarize(measured)
    result["by_kind"] = {k.name.lower(): summarize(measured & (kind == int(k))[:, None]) for k in AgentKind}
    return result


def error_vs_length(tok: TokenizedTrajectories, max_steps: int | None = None) -> dict[str, list]:
    """Mean error (cm) and fraction above 2/5/10 cm as a function of steps since the anchor (1, 2, ...)."""
    measured = tok.valid & ~tok.anchored
    length = tok.steps_since_anchor[measured]
    err = tok.error[measured] * 100.0
    top = int(length.max()) if length.size else 0
    top = top if max_steps is None else min(top, max_steps)
    keep = length <= top
    length, err = length[keep], err[keep]
    count = np.bincount(length, minlength=top + 1)[1:]
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = np.bincount(length, weights=err, minlength=top + 1)[1:] / count
        above = {
            f"{c:g}": (np.bincount(length, weights=(err > c).astype(float), minlength=top + 1)[1:] / count)
            for c in THRESHOLDS_CM
        }
    return {
        "steps": list(range(1, top + 1)),
        "count": count.tolist(),
        "mean_cm": [_rounded(v) for v in mean],
        "frac_above_cm": {c: [_rounded(v) for v in a] for c, a in above.items()},
    }


def collision_rates(data: TrajectorySet, xyh: np.ndarray, valid: np.ndarray) -> dict[str, Any]:
    """Fraction of valid agent-steps whose box overlaps another agent of the scene (overall and per step)."""
    hit = collision_flags(xyh, valid, data.size, data.scene)
    per_step_count = valid.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_step = hit.sum(0) / per_step_count
    return {
        "rate": _rounded(hit[valid].mean()) if valid.any() else None,
        "per_step": [_rounded(v) for v in per_step],
    }


def evaluate_vocabulary(
    vocab: MotionVocabulary,
    data: TrajectorySet,
    *,
    collisions: bool = True,
    max_steps: int | None = None,
    raw_collisions: dict[str, Any] | None = None,
    drift_tolerance: float = DRIFT_TOLERANCE_M,
    warn_drift: bool = True,
) -> dict[str, Any]:
    """Tokenize ``data`` with ``vocab``; report errors, error vs length and (optionally) collision rates.

    ``raw_collisions`` (:func:`collision_rates` of the logged states) saves recomputing them per vocabulary.
    ``drift`` reports per class the max error and the share of tracks whose tokenized state drifts beyond
    ``drift_tolerance`` m (a warning names the worst of them, by scene and agent index, unless
    ``warn_drift`` is False); ``envelope_max_cm`` the max one-step error on each class's motion envelope.
    """
    tok = tokenize(vocab, data.xyh, data.valid, data.size, data.kind)
    result: dict[str, Any] = {"method": vocab.method, "templates": vocab.size, "dt": data.dt}
    result.update(error_summary(tok, data.kind))
    first = np.searchsorted(data.scene, data.scene)  # rows are grouped by scene
    names = [f"scene {s} agent {i - f}" for i, (s, f) in enumerate(zip(data.scene, first, strict=True))]
    result["drift"] = drift_report(
        tok.error, tok.valid & ~tok.anchored, data.kind, names, drift_tolerance, warn=warn_drift
    )
    result["envelope_max_cm"] = {
        k.name.lower(): round(envelope_error(vocab.for_kind(k), k, data.dt) * 100, 3) for k in AgentKind
    }
    result["error_vs_length"] = error_vs_length(tok, max_steps)
    if collisions:
        raw = raw_collisions if raw_collisions is not None else collision_rates(data, data.xyh, data.valid)
        tokenized = collision_rates(data, np.nan_to_num(tok.xyh), data.valid)
        result["collision_rate"] = {"raw": raw["rate"], "tokenized": tokenized["rate"]}
        result["collision_per_step"] = {"raw": raw["per_step"], "tokenized": tokenized["per_step"]}
    return result


def plot_error_vs_length(
    results: list[dict[str, Any]], path: str | os.PathLike[str], title: str = ""
) -> Path:
    """Plot error vs trajectory length (methods at V=384; k-disks at every V) and collision rates."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from trajeglish_env.scenario_io import atomic_path

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.5))
    for res in results:
        curve = res["error_vs_length"]
        t = np.asarray(curve["steps"]) * res.get("dt", 0.1)
        mean = np.asarray([np.nan if v is None else v for v in curve["mean_cm"]])
        if res["vocab_size"] == 384:
            axes[0].plot(t, mean, label=f"{res['method']} ({res['templates']})")
        if res["method"] == "k-disks":
            axes[1].plot(t, mean, label=f"|V|={res['vocab_size']}")
            if "collision_per_step" in res:
                axes[2].plot(
                    np.asarray(res["collision_per_step"]["tokenized"], dtype=float),
                    label=f"k-disks {res['vocab_size']}",
                )
    raw = next((r["collision_per_step"]["raw"] for r in results if "collision_per_step" in r), None)
    if raw is not None:
        axes[2].plot(np.asarray(raw, dtype=float), color="black", lw=2, label="raw")
    axes[0].set(
        title="methods, |V|=384", xlabel="trajectory length (s)", ylabel="E[d(s, s_hat)] (cm)", yscale="log"
    )
    axes[1].set(title="k-disks", xlabel="trajectory length (s)", ylabel="E[d(s, s_hat)] (cm)")
    axes[2].set(title="collision rate", xlabel="step", ylabel="fraction of agents overlapping")
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
    return path

"""Plots of ``trajeglish evaluate``: collision curves (overall, per scene kind), speed and acceleration
histograms, and every method's per-feature realism score."""

from __future__ import annotations

import textwrap
from pathlib import Path
from typing import Any

import numpy as np

from trajeglish_env.metrics.config import FEATURE_NAMES, get_config
from trajeglish_env.scenario_io import atomic_path


def plot_evaluation(raw: dict[str, Any], dt: float, out: Path) -> list[str]:
    """The collision curves (overall and per scene kind) and the speed/acceleration histograms of every
    method of an evaluation's raw results; returns the files written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, r in raw.items():
        curve = np.asarray(r["collision_rate_over_time"])
        ax.plot((np.arange(len(curve)) + 1) * dt, curve, label=name, lw=2 if name == "log" else 1)
    ax.set_xlabel("time after the current step (s)")
    ax.set_ylabel("fraction of agents in collision")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(_save(fig, out / "collision_rate_over_time.png"))
    paths.append(_plot_by_kind(raw, dt, out))
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for name, r in raw.items():
        axes[0].hist(r["_speed"], bins=60, range=(0, 35), histtype="step", density=True, label=name)
        axes[1].hist(r["_accel"], bins=60, range=(-10, 10), histtype="step", density=True, label=name)
    axes[0].set_xlabel("speed (m/s), every simulated agent of every class")
    axes[1].set_xlabel("acceleration (m/s², those within ±10)")
    for ax in axes:
        ax.set_ylabel("density")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    paths.append(_save(fig, out / "kinematics_histograms.png"))
    plt.close("all")
    return paths


def _plot_by_kind(raw: dict[str, Any], dt: float, out: Path) -> str:
    """The collision curves, one panel per scene kind: in which kind of scene and when agents collide."""
    import matplotlib.pyplot as plt

    kinds = sorted({kind for r in raw.values() for kind in r["collision_rate_over_time_by_kind"]})
    cols = min(4, len(kinds))
    rows = -(-len(kinds) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False, sharex=True)
    for ax, kind in zip(axes.flat, kinds, strict=False):
        for name, r in raw.items():
            curve = np.asarray(r["collision_rate_over_time_by_kind"].get(kind, []))
            ax.plot((np.arange(len(curve)) + 1) * dt, curve, label=name, lw=2 if name == "log" else 1)
        ax.set_title(kind, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(kinds) :]:
        ax.axis("off")
    for ax in axes[-1]:
        ax.set_xlabel("time after the current step (s)", fontsize=8)
    axes[0][0].set_ylabel("fraction in collision", fontsize=8)
    axes[0][0].legend(fontsize=6)
    fig.tight_layout()
    return _save(fig, out / "collision_rate_over_time_by_kind.png")


def plot_feature_scores(methods: dict[str, Any], path: Path, metrics: str = "2025", title: str = "") -> str:
    """Grouped bars of every method's per-feature likelihood score (``methods``: the ``methods`` of an
    evaluation's JSON), each feature labelled with its meta-metric weight: where a model loses realism."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cfg = get_config(metrics)
    names = [f for f in FEATURE_NAMES if cfg.feature(f).weight > 0]
    x = np.arange(len(names))
    width = 0.8 / max(1, len(methods))
    fig, ax = plt.subplots(figsize=(max(8.0, 1.1 * len(names)), 4.2))
    for k, (method, r) in enumerate(methods.items()):
        scores = [r["scores"][f] for f in names]
        meta = r["scores"]["metametric"]
        ax.bar(x + (k - (len(methods) - 1) / 2) * width, scores, width, label=f"{method} ({meta:.3f})")
    labels = [f"{textwrap.fill(f.replace('_', ' '), 14)}\n(w {cfg.feature(f).weight:g})" for f in names]
    ax.set_xticks(x, labels, fontsize=7)
    ax.set_ylabel("likelihood score")
    ax.set_ylim(0, 1.05)
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=7, ncol=2, title="method (meta-metric)", title_fontsize=7)
    if title:
        ax.set_title(title, fontsize=9)
    fig.tight_layout()
    saved = _save(fig, path)
    plt.close(fig)
    return saved


def _save(fig: Any, path: Path) -> str:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    return str(path)

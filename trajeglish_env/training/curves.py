"""A training run's metrics file (``metrics.csv``) and curves: its own curve and several runs compared."""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

from trajeglish_env.scenario_io import atomic_path

__all__ = ["plot_curve", "plot_runs", "read_metrics", "write_metrics"]


def write_metrics(path: Path, history: list[dict]) -> None:
    """Write the rows logged so far as ``metrics.csv`` (atomically: a crash keeps the previous file)."""
    fields = ["step", "loss", "val_nll", "lr", "grad_norm", "tokens_per_s", "data_wait"]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=fields)
        writer.writeheader()
        for row in history:
            writer.writerow({k: row.get(k, "") for k in fields})


def read_metrics(run: str | os.PathLike[str]) -> list[dict[str, float]]:
    """The rows of a run's ``metrics.csv`` (empty fields left out), for comparing runs."""
    path = Path(run) / "metrics.csv" if Path(run).is_dir() else Path(run)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no metrics.csv (expected a run directory of `trajeglish train`)")
    try:
        with open(path, newline="") as fh:
            reader = csv.DictReader(fh)
            if not reader.fieldnames or "step" not in reader.fieldnames or "val_nll" not in reader.fieldnames:
                raise ValueError(f"{path}: not a training metrics file (columns {reader.fieldnames})")
            try:
                return [{k: float(v) for k, v in row.items() if v not in ("", None)} for row in reader]
            except ValueError as exc:
                raise ValueError(f"{path}: a non-numeric value ({exc})") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text metrics file (binary or corrupt: {exc.reason})") from None


def plot_runs(runs: dict[str, str | os.PathLike[str]], out: str | os.PathLike[str]) -> dict[str, Any]:
    """Validation NLL against step for several runs in one picture (e.g. the variants of the ablation);
    returns each run's last validation NLL and the picture's path (a .png, .pdf or .svg file, in the format
    its suffix names; another suffix is refused before any plotting: a .txt got a PNG)."""
    if Path(out).suffix.lower() not in (".png", ".pdf", ".svg"):
        raise ValueError(f"--out {out}: expected a .png, .pdf or .svg picture (the suffix sets the format)")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    last: dict[str, float | None] = {}
    for name, run in runs.items():
        val = [(r["step"], r["val_nll"]) for r in read_metrics(run) if "val_nll" in r]
        last[name] = val[-1][1] if val else None
        if val:
            ax.plot(*zip(*val, strict=True), "o-", ms=3, label=name)
    ax.set_xlabel("optimisation step")
    ax.set_ylabel("validation NLL (nats / token)")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(Path(out)) as tmp:
        fig.savefig(tmp, format=Path(out).suffix.lower()[1:], dpi=110)
    plt.close(fig)
    return {"plot": str(out), "last_val_nll": last}


def plot_curve(history: list[dict], path: Path) -> None:
    """The run's training loss and validation NLL against step, as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    tr = [(h["step"], h["loss"]) for h in history if "loss" in h]
    va = [(h["step"], h["val_nll"]) for h in history if "val_nll" in h]
    if tr:
        ax.plot(*zip(*tr, strict=True), label="train loss (noisy inputs)")
    if va:
        ax.plot(*zip(*va, strict=True), "o-", label="validation NLL")
    ax.set_xlabel("optimisation step")
    ax.set_ylabel("nats / token")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)

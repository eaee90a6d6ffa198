"""The experiment report's figures (matplotlib, Agg backend, PNG), mirroring the paper's §4 figures.

* :func:`plot_evolution`: per task, held-out reward and success per iteration for every method:
  each seed a thin line, the mean over seeds a thick one (paper Figure ``fig:evolution-curve``).
* :func:`plot_sample_efficiency`: per task, held-out success against cumulative training env
  steps, each seed a line.
* :func:`plot_seed_bars`: a bar per group (mean, ± std whiskers with two or more values) with a
  dot per value, and the paper's figures as hatched bars beside them (paper Figures
  ``fig:t6-flagship`` and ``fig:identity-drift``).
* :func:`plot_governance`: per task, the blocking rate, and the unsafe-episode rate with
  governance off and on with their Wilson intervals; the paper's values as hollow markers
  (paper Figure ``fig:safety`` (a) and (b)).

The functions take plain numbers, not the report's records, so this module imports nothing from
:mod:`capevo.experiment.report`. They reuse evolve's matplotlib set-up and resolution.

Invariants:
1. Every function writes one PNG at the given path and returns the path; none opens a window.
2. Every function accepts empty input and still writes a readable figure saying so.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from capevo.evolve.plots import DPI, _pyplot

_COLORS = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22")


def _color(i: int) -> str:
    return _COLORS[i % len(_COLORS)]


def _save(fig: Any, plt: Any, path: str | os.PathLike[str]) -> Path:
    out = Path(path)
    fig.savefig(out, dpi=DPI)
    plt.close(fig)
    return out


def _mean_curve(curves: Sequence[Sequence[tuple[float, float]]]) -> list[tuple[float, float]]:
    """Mean over the curves at each x some curve has (over the curves that have it)."""
    at: dict[float, list[float]] = {}
    for c in curves:
        for x, y in c:
            at.setdefault(x, []).append(y)
    return [(x, sum(v) / len(v)) for x, v in sorted(at.items())]


def plot_evolution(
    series: Mapping[str, Mapping[str, Sequence[Sequence[tuple[int, float, float]]]]],
    path: str | os.PathLike[str],
    *,
    titles: Mapping[str, str] | None = None,
) -> Path:
    """Reward (left) and success (right) per iteration, one row per task.

    Args:
        series: ``task → method label → per seed [(iteration, reward_mean, success_rate), ...]``.
        path: The PNG to write.
        titles: Row titles per task (default the task key).

    Returns:
        ``path``.
    """
    from matplotlib.ticker import MaxNLocator

    plt = _pyplot()
    tasks = list(series)
    n = max(len(tasks), 1)
    fig, axes = plt.subplots(n, 2, figsize=(11, 2.8 * n + 1.0), squeeze=False)
    labels = sorted({label for t in tasks for label in series[t]})
    color = {label: _color(i) for i, label in enumerate(labels)}
    seen: set[str] = set()
    for row, task in enumerate(tasks):
        ax_r, ax_s = axes[row, 0], axes[row, 1]
        for label, seeds in series[task].items():
            for k, (ax, j) in enumerate(((ax_r, 1), (ax_s, 2))):
                curves = [[(float(p[0]), float(p[j]) * (100.0 if j == 2 else 1.0)) for p in s] for s in seeds]
                for c in curves:
                    if c:
                        ax.plot(*zip(*c, strict=True), color=color[label], lw=0.8, alpha=0.35)
                mean = _mean_curve(curves)
                if mean:
                    ax.plot(
                        *zip(*mean, strict=True),
                        "o-",
                        color=color[label],
                        lw=2,
                        ms=3,
                        label=label if k == 0 and label not in seen else None,
                    )
                    if k == 0:
                        seen.add(label)
        title = (titles or {}).get(task, task)
        ax_r.set_title(f"{title}: held-out reward", fontsize=9)
        ax_s.set_title(f"{title}: held-out success", fontsize=9)
        ax_r.set_ylabel("mean episode reward")
        ax_s.set_ylabel("success (%)")
        ax_s.set_ylim(-5, 105)
        for ax in (ax_r, ax_s):
            ax.set_xlabel("iteration")
            ax.xaxis.set_major_locator(MaxNLocator(integer=True))
            ax.grid(alpha=0.3)
    if not tasks:
        axes[0, 0].text(0.5, 0.5, "no finished cell", ha="center", va="center", transform=axes[0, 0].transAxes)
    handles, names = [], []
    for ax in axes[:, 0]:
        h, lab = ax.get_legend_handles_labels()
        handles += h
        names += lab
    if handles:
        fig.suptitle("thick: mean over seeds; thin: each seed", fontsize=9)
        fig.legend(handles, names, loc="lower center", ncol=min(len(names), 4), fontsize=8)
        fig.tight_layout(rect=(0, 0.06 if n < 3 else 0.03, 1, 1))
    else:
        fig.tight_layout()
    return _save(fig, plt, path)


def plot_sample_efficiency(
    series: Mapping[str, Mapping[str, Sequence[Sequence[tuple[int, float]]]]],
    path: str | os.PathLike[str],
    *,
    titles: Mapping[str, str] | None = None,
) -> Path:
    """Held-out success against cumulative training env steps, one panel per task.

    Args:
        series: ``task → method label → per seed [(cumulative env steps, success_rate), ...]``.
        path: The PNG to write.
        titles: Panel titles per task.

    Returns:
        ``path``.
    """
    plt = _pyplot()
    tasks = list(series)
    n = max(len(tasks), 1)
    fig, axes = plt.subplots(n, 1, figsize=(8, 2.8 * n + 1.0), squeeze=False)
    labels = sorted({label for t in tasks for label in series[t]})
    color = {label: _color(i) for i, label in enumerate(labels)}
    for row, task in enumerate(tasks):
        ax = axes[row, 0]
        right = max((float(p[0]) for seeds in series[task].values() for s in seeds for p in s), default=0.0)
        ax.set_xlim(0, max(right * 1.05, 1.0))
        for label, seeds in series[task].items():
            for i, s in enumerate(seeds):
                if not s:
                    continue
                xs = [float(p[0]) for p in s]
                ys = [100.0 * float(p[1]) for p in s]
                ax.plot(xs, ys, "o-", color=color[label], lw=1.2, ms=3, alpha=0.8, label=label if i == 0 else None)
        for th in (50, 80):
            ax.axhline(th, color="gray", ls=":", lw=0.8)
        ax.set_title((titles or {}).get(task, task), fontsize=9)
        ax.set_ylabel("held-out success (%)")
        ax.set_xlabel("training env steps (cumulative)")
        ax.set_ylim(-5, 105)
        ax.grid(alpha=0.3)
        if series[task]:
            ax.legend(fontsize=7, loc="upper left")
    if not tasks:
        axes[0, 0].text(0.5, 0.5, "no finished cell", ha="center", va="center", transform=axes[0, 0].transAxes)
    fig.tight_layout()
    return _save(fig, plt, path)


def plot_seed_bars(
    values: Mapping[str, Sequence[float | None]],
    path: str | os.PathLike[str],
    *,
    title: str,
    ylabel: str,
    paper: Mapping[str, Sequence[float]] | None = None,
) -> Path:
    """A bar per group: the mean, whiskers ± std (ddof = 1) with two or more values, a dot per value.

    Args:
        values: Group label → its values (None entries are left out).
        path: The PNG to write.
        title: Figure title.
        ylabel: Axis label.
        paper: The paper's values per label, drawn hatched after the run's bars.

    Returns:
        ``path``.
    """
    import numpy as np

    plt = _pyplot()
    groups = [(label, [float(v) for v in vs if v is not None], False) for label, vs in values.items()]
    groups += [(label, [float(v) for v in vs], True) for label, vs in (paper or {}).items()]
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(groups) + 2.0), 4.6))
    for i, (_, vs, quoted) in enumerate(groups):
        if not vs:
            continue
        mean = float(np.mean(vs))
        std = float(np.std(vs, ddof=1)) if len(vs) > 1 else 0.0
        ax.bar(
            i,
            mean,
            yerr=std if len(vs) > 1 else None,
            capsize=5,
            color="white" if quoted else _color(i),
            edgecolor="#555555" if quoted else _color(i),
            hatch="//" if quoted else None,
            alpha=0.9,
        )
        ax.scatter([i] * len(vs), vs, color="white", edgecolors="black", s=22, zorder=5)
    ax.set_xticks(range(len(groups)))
    ax.set_xticklabels([_wrapped(g[0]) for g in groups], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel(ylabel)
    ax.set_title(title + ("\nhatched: the paper's published figures" if paper else ""), fontsize=9)
    ax.grid(alpha=0.3, axis="y")
    if not groups:
        ax.text(0.5, 0.5, "no values", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout()
    return _save(fig, plt, path)


def _wrapped(label: str, width: int = 28) -> str:
    """A tick label on several lines: a group's option list would otherwise push the axes aside."""
    import textwrap

    return "\n".join(textwrap.wrap(label, width=width, break_long_words=False, break_on_hyphens=False)) or label


def plot_governance(rows: Sequence[Mapping[str, Any]], path: str | os.PathLike[str]) -> Path:
    """Blocking rate and unsafe-episode rates per task (see the module docstring).

    Args:
        rows: Per task ``{"task", "blocking", "on": {"rate", "low", "high"}, "off": {...}, "paper":
            (blocking %, unsafe off %, unsafe on %, overhead ms) or None}``; rates are fractions,
            None where the run has no such cell.
        path: The PNG to write.

    Returns:
        ``path``.
    """
    plt = _pyplot()
    fig, (ax_b, ax_u) = plt.subplots(1, 2, figsize=(11, 4.2))
    xs = list(range(len(rows)))
    names = [str(r["task"]) for r in rows]
    for x, r in zip(xs, rows, strict=True):
        if r.get("blocking") is not None:
            ax_b.bar(x, 100 * r["blocking"], width=0.5, color="#1f77b4", label="run")
        paper = r.get("paper")
        if paper:
            ax_b.scatter([x], [paper[0]], marker="D", facecolors="none", edgecolors="black", zorder=5)
        for dx, side, color in ((-0.18, "off", "#d62728"), (0.18, "on", "#2ca02c")):
            s = r.get(side) or {}
            rate = s.get("rate")
            if rate is None:
                continue
            lo, hi = s.get("low"), s.get("high")
            err = (
                [[100 * max(rate - lo, 0.0)], [100 * max(hi - rate, 0.0)]]
                if lo is not None and hi is not None and math.isfinite(lo) and math.isfinite(hi)
                else None
            )
            ax_u.bar(x + dx, 100 * rate, width=0.34, color=color, yerr=err, capsize=4, label=f"governance {side}")
            if paper:
                ax_u.scatter(
                    [x + dx], [paper[1] if side == "off" else paper[2]], marker="D", facecolors="none",
                    edgecolors="black", zorder=5,
                )  # fmt: skip
    for ax, title, label in (
        (ax_b, "(a) blocking rate: interventions per step, governance on", "blocking (%)"),
        (ax_u, "(b) unsafe episodes (95 % Wilson)", "unsafe episodes (%)"),
    ):
        ax.set_xticks(xs)
        ax.set_xticklabels(names)
        ax.set_xlim(-0.7, max(len(rows), 1) - 0.3)
        ax.set_ylim(0, max(105.0, 1.05 * max((b.get_height() for b in ax.patches), default=0.0)))
        ax.set_ylabel(label)
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    if any(r.get("paper") for r in rows):
        ax_b.scatter([], [], marker="D", facecolors="none", edgecolors="black", label="paper (Table 7)")
    for ax in (ax_b, ax_u):
        handles, labels = ax.get_legend_handles_labels()
        uniq = dict(zip(labels, handles, strict=True))
        if uniq:
            ax.legend(uniq.values(), uniq.keys(), fontsize=7)
    if not rows:
        ax_b.text(0.5, 0.5, "no explorer cell", ha="center", va="center", transform=ax_b.transAxes)
    fig.tight_layout()
    return _save(fig, plt, path)


__all__ = ["plot_evolution", "plot_governance", "plot_sample_efficiency", "plot_seed_bars"]

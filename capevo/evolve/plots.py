"""The report's figures (matplotlib, Agg backend, PNG).

* :func:`plot_progress`: success rate (95% Wilson intervals) and mean episode reward (95% t
  intervals) of the live episodes per iteration, with each iteration's gate decision marked,
  and the final capability set on iteration 0's seeds as a last point.
* :func:`plot_timeline`: per ECM, its active version over the run (a step line read from the
  registry's audit history) with every publish, gate, promotion, rejection and rollback.

Invariants:
1. Both functions write a PNG at the given path and return it; they never open a window (Agg).
2. They accept an empty run (no rows, no events) and still write a readable figure.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from capevo.evolve.metrics import IterationMetrics, OutcomeStats
from capevo.records import Action, AuditEvent

DPI = 120
_DECISION_STYLE = {
    "promote": ("^", "#2ca02c", "promoted"),
    "reject": ("x", "#d62728", "rejected"),
}
_EVENT_STYLE: Mapping[Action, tuple[str, str, str]] = {
    Action.PUBLISH: ("o", "#7f7f7f", "published"),
    Action.GATE: ("s", "#1f77b4", "gated"),
    Action.PROMOTE: ("^", "#2ca02c", "promoted"),
    Action.REJECT: ("x", "#d62728", "rejected"),
    Action.ROLLBACK: ("v", "#ff7f0e", "rolled back"),
    Action.DEPRECATE: ("D", "#9467bd", "deprecated"),
}


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def _err(value: float, low: float | None, high: float | None) -> tuple[float, float]:
    if low is None or high is None or not (math.isfinite(low) and math.isfinite(high)):
        return 0.0, 0.0
    return max(value - low, 0.0), max(high - value, 0.0)


def plot_progress(
    rows: Sequence[IterationMetrics],
    path: str | os.PathLike[str],
    *,
    title: str = "",
    final: OutcomeStats | None = None,
) -> Path:
    """Success and reward per iteration (see the module docstring).

    Args:
        rows: The finished iterations.
        path: The PNG to write.
        title: Figure title.
        final: Stats of the final evaluation (iteration 0's seeds), drawn after the last iteration.

    Returns:
        ``path``.
    """
    plt = _pyplot()
    fig, (ax_s, ax_r) = plt.subplots(2, 1, figsize=(8, 7.2), sharex=True)
    xs = [r.iteration for r in rows]
    stats = [r.live for r in rows]
    if rows:
        s_err = list(zip(*[_err(s.success_rate, s.success_low, s.success_high) for s in stats], strict=True))
        ax_s.errorbar(
            xs,
            [s.success_rate for s in stats],
            yerr=s_err,
            fmt="o-",
            capsize=4,
            color="#1f77b4",
            label="live episodes (95% Wilson CI)",
        )
        r_err = list(zip(*[_err(s.reward_mean, s.reward_low, s.reward_high) for s in stats], strict=True))
        ax_r.errorbar(
            xs,
            [s.reward_mean for s in stats],
            yerr=r_err,
            fmt="o-",
            capsize=4,
            color="#1f77b4",
            label="mean episode reward (95% t CI)",
        )
        seen: set[str] = set()
        for r in rows:
            if r.gate is None:
                continue
            # a chain's decisions share one marker: promoted if any of them was
            decisions = [g.decision for g in r.gates]
            decision = "promote" if "promote" in decisions else r.gate.decision
            marker, color, label = _DECISION_STYLE.get(decision, ("o", "gray", decision))
            ax_s.scatter(
                [r.iteration],
                [1.07],
                marker=marker,
                color=color,
                s=60,
                clip_on=False,
                zorder=5,
                label=None if label in seen else f"gate: {label} (at end of iteration)",
            )
            seen.add(label)
            ax_s.annotate(
                f"{r.gate.ecm.split('.', 1)[-1]} v{r.gate.candidate_version}"
                + (f" +{len(r.further)}" if r.further else ""),
                (r.iteration, 1.07),
                textcoords="offset points",
                xytext=(0, 7),
                ha="center",
                fontsize=7,
                annotation_clip=False,
            )
    if final is not None and rows:
        fx = rows[-1].iteration + 1
        lo, hi = _err(final.success_rate, final.success_low, final.success_high)
        ax_s.errorbar(
            [fx],
            [final.success_rate],
            yerr=[[lo], [hi]],
            fmt="D",
            capsize=4,
            color="#2ca02c",
            label="final set on iteration 0's seeds",
        )
        lo, hi = _err(final.reward_mean, final.reward_low, final.reward_high)
        ax_r.errorbar(
            [fx],
            [final.reward_mean],
            yerr=[[lo], [hi]],
            fmt="D",
            capsize=4,
            color="#2ca02c",
            label="final set on iteration 0's seeds",
        )
    ax_s.set_ylim(-0.05, 1.15)
    ax_s.set_ylabel("success rate")
    ax_s.grid(alpha=0.3)
    ax_r.set_ylabel("episode reward")
    ax_r.set_xlabel("iteration")
    ax_r.grid(alpha=0.3)
    handles, labels = ax_s.get_legend_handles_labels()
    h2, l2 = ax_r.get_legend_handles_labels()
    for h, lab in zip(h2, l2, strict=True):
        if lab not in labels:
            handles.append(h)
            labels.append(lab)
    if rows:
        ticks = [*xs, *([rows[-1].iteration + 1] if final is not None else [])]
        ax_r.set_xticks(ticks)
        ax_r.set_xticklabels([str(t) for t in xs] + (["final"] if final is not None else []))
    else:
        ax_s.text(0.5, 0.5, "no finished iteration yet", ha="center", va="center", transform=ax_s.transAxes)
    fig.suptitle(title or "live episodes per iteration")
    if handles:
        fig.legend(handles, labels, loc="lower center", ncol=2, fontsize=8, bbox_to_anchor=(0.5, 0.0))
        fig.tight_layout(rect=(0, 0.1, 1, 1))
    else:
        fig.tight_layout()
    out = Path(path)
    fig.savefig(out, dpi=DPI)
    plt.close(fig)
    return out


def active_steps(events: Sequence[AuditEvent]) -> list[tuple[float, int]]:
    """``(time, active version)`` after every pointer move in ``events`` (promote, rollback)."""
    out: list[tuple[float, int]] = []
    for e in sorted(events, key=lambda e: e.seq):
        if e.action in (Action.PROMOTE, Action.ROLLBACK):
            v = e.to_version if e.to_version is not None else e.version
            if v is not None:
                out.append((e.at, int(v)))
    return out


def plot_timeline(
    history: Mapping[str, Sequence[AuditEvent]],
    path: str | os.PathLike[str],
    *,
    t0: float | None = None,
    iteration_starts: Sequence[tuple[int, float]] = (),
    end: float | None = None,
    title: str = "",
) -> Path:
    """Per ECM: active version over time with its lifecycle events (see the module docstring).

    Args:
        history: Audit events per ECM name (``registry.history(name)``).
        path: The PNG to write.
        t0: Time origin (seconds since the epoch); default the earliest event. Earlier events
            are drawn at the left edge.
        iteration_starts: ``(iteration, time)`` pairs drawn as dotted lines.
        end: Right end of the time axis; default the latest event.
        title: Figure title.

    Returns:
        ``path``.
    """
    plt = _pyplot()
    names = list(history)
    n = max(len(names), 1)
    fig, axes = plt.subplots(n, 1, figsize=(9, 1.9 * n + 1.2), sharex=True, squeeze=False)
    all_times = [e.at for evs in history.values() for e in evs]
    origin = t0 if t0 is not None else (min(all_times) if all_times else 0.0)
    stop = end if end is not None else (max(all_times) if all_times else origin + 60.0)
    stop = max(stop, origin + 1.0)

    # Minutes for real runs; seconds when the whole run took under two minutes.
    unit, scale = ("minutes", 60.0) if stop - origin >= 120.0 else ("seconds", 1.0)

    def x(t: float) -> float:
        return (max(t, origin) - origin) / scale

    legend_done: set[str] = set()
    for ax, name in zip(axes[:, 0], names or ["(no ECM)"], strict=False):
        events = sorted(history.get(name, ()), key=lambda e: e.seq)
        steps = active_steps(events)
        if steps:
            xs = [x(t) for t, _ in steps] + [x(stop)]
            ys = [v for _, v in steps] + [steps[-1][1]]
            ax.step(
                xs,
                ys,
                where="post",
                color="#1f77b4",
                lw=2,
                alpha=0.6,
                label=None if "active" in legend_done else "active version",
            )
            legend_done.add("active")
        max_v = 0
        for e in events:
            if e.version is None:
                continue
            max_v = max(max_v, int(e.version))
            marker, color, label = _EVENT_STYLE.get(e.action, ("o", "gray", e.action.value))
            y = e.to_version if e.action is Action.ROLLBACK and e.to_version is not None else e.version
            hollow = e.action is Action.GATE  # drawn under the promote/reject mark of the same moment
            style: dict[str, Any] = (
                {"facecolors": "none", "edgecolors": color, "s": 130, "linewidths": 1.5, "zorder": 4}
                if hollow
                else {"color": color, "s": 45, "zorder": 5}
            )
            ax.scatter([x(e.at)], [y], marker=marker, label=None if label in legend_done else label, **style)
            legend_done.add(label)
        for it, t in iteration_starts:
            ax.axvline(x(t), color="gray", ls=":", lw=0.8)
            if ax is axes[0, 0]:
                ax.annotate(
                    f"it {it}",
                    (x(t), 1.0),
                    xycoords=("data", "axes fraction"),
                    fontsize=7,
                    xytext=(2, -10),
                    textcoords="offset points",
                    color="gray",
                )
        ax.set_ylabel(f"{name}\nversion", fontsize=8)
        ax.set_ylim(-0.5, max_v + 0.5)
        step = max(1, (max_v + 1) // 8)
        ax.set_yticks(list(range(0, max_v + 1, step)))
        ax.grid(alpha=0.25)
        if not events:
            ax.text(0.5, 0.5, "no events", ha="center", va="center", transform=ax.transAxes)
    axes[-1, 0].set_xlabel(f"{unit} since the run started")
    handles, labels = [], []
    for ax in axes[:, 0]:
        h, lab = ax.get_legend_handles_labels()
        handles += h
        labels += lab
    if handles:
        fig.legend(
            handles, labels, loc="upper center", ncol=min(len(labels), 6), fontsize=8, bbox_to_anchor=(0.5, 0.995)
        )
    fig.suptitle(title or "version timeline", y=0.93 if handles else 0.99, fontsize=10)
    fig.tight_layout(rect=(0, 0, 1, 0.9 if handles else 0.97))
    out = Path(path)
    fig.savefig(out, dpi=DPI)
    plt.close(fig)
    return out


__all__ = ["active_steps", "plot_progress", "plot_timeline"]

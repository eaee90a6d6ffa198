"""heldout.png: held-out success of the code set and the distilled set per seed block, with 95 % Wilson intervals.

Usage: python plot.py RUN_DIR [RUN_DIR ...] (directories written by commands.sh, with the extra
270000 block); writes heldout.png next to this file.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from capevo.runtime.gate_stats import wilson_interval

BLOCKS = ("250000-250029", "260000-260029", "270000-270029")
SETS = (("code", "code set (evolved by CEM)"), ("distilled", "distilled set (5 of 8 ECMs neural)"))


def main(run: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.38
    for k, (key, label) in enumerate(SETS):
        xs, rates, lows, highs = [], [], [], []
        for i, block in enumerate((*BLOCKS, "all")):
            names = BLOCKS if block == "all" else (block,)
            outcomes = [o for b in names for o in json.loads((run / f"heldout-{key}-{b}.json").read_text())]
            n, s = len(outcomes), sum(o["success"] for o in outcomes)
            ci = wilson_interval(s, n, alpha=0.025)
            xs.append(i + (k - 0.5) * width)
            rates.append(s / n)
            lows.append(s / n - ci.low)
            highs.append(ci.high - s / n)
            ax.text(xs[-1], 0.02, f"{s}/{n}", ha="center", va="bottom", fontsize=8, color="white")
        ax.bar(xs, rates, width, yerr=[lows, highs], capsize=3, label=label)
    ax.axhline(0.9, color="grey", linestyle="--", linewidth=1)
    ax.text(-0.45, 0.92, "issue 19's target, 90 %", fontsize=8, color="grey", ha="left")
    ax.set_xticks(range(4), [*(f"seeds {b}" for b in BLOCKS), "all 90"], fontsize=8)
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("held-out success")
    ax.set_title("T6 peg_in_hole: code ECMs vs their behaviour-cloned copies (95 % Wilson)", fontsize=9)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=2, frameon=False)
    fig.tight_layout()
    fig.savefig(Path(__file__).with_name("heldout.png"), dpi=120)


if __name__ == "__main__":
    main(Path(sys.argv[1]))

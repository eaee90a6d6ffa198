"""The report directory of a run: ``report.md``, ``metrics.csv`` (kept by the loop), and PNG plots.

``report.md`` states the task, preset and modality; says plainly what version 0 is; compares
success at the start (iteration 0's live episodes) with the final capability set on the
same seeds; lists, for the final set's code ECMs past version 0, the parameters search changed
(v0 → final); tabulates every iteration (success with 95% intervals, reward and σ², Δπ,
interventions, unsafe steps, the ECM updated, the gate decision, wall time) and every gate
decision (N, intervals, p-values, failed checks); lists rollbacks; and gives the agent's
identity hash. Plots: ``progress.png`` (:func:`~capevo.evolve.plots.plot_progress`) and
``timeline.png`` (:func:`~capevo.evolve.plots.plot_timeline`, from the registry's history).

Invariants:
1. :func:`write_report` rewrites ``report.md`` and the plots from what is on disk and in the
   registry; running it twice gives the same Markdown (apart from the "written at" line).
2. It needs no simulator: it reads metrics, the journal and the registry only.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from capevo.errors import CapevoError, NotFound
from capevo.evolve.metrics import (
    IterationMetrics,
    OutcomeStats,
    outcome_stats,
    read_metrics,
    split_monitor_actions,
    write_atomically,
)
from capevo.evolve.state import RunManifest, load_manifest
from capevo.records import AuditEvent, EcmVersion, Kind
from capevo.registry.api import Registry
from capevo.runtime.evaluation import EpisodeOutcome
from capevo.runtime.tasks import task_spec

REPORT = "report.md"
PROGRESS_PNG = "progress.png"
TIMELINE_PNG = "timeline.png"


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100 * x:.0f}%"


def _p(x: float | None) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "-"
    return f"{x:.3g}"


def _num(x: Any) -> str:
    return f"{x:.4g}" if isinstance(x, (int, float)) else "-"


def _ci(low: float | None, high: float | None) -> str:
    return "-" if low is None or high is None else f"[{100 * low:.0f}, {100 * high:.0f}]%"


def _versions(v: Mapping[str, int]) -> str:
    return ", ".join(f"{k.split('.', 1)[-1]}@{n}" for k, n in sorted(v.items(), key=lambda kv: kv[0]))


def _rate(s: OutcomeStats) -> str:
    return f"{s.successes}/{s.episodes} = {_pct(s.success_rate)} {_ci(s.success_low, s.success_high)}"


def envelope_text(choice: str, spec: Any, *, connect: bool = False) -> str:
    """One line naming the envelope a run's episodes ran under, with its hash."""
    from capevo.runtime.envelope import PHI_PAPER, PHI_TASK, resolve_phi

    what = {
        PHI_TASK: "the paper's box, 20 N force limit and velocity cap plus the task's scene (braking before contacts)",
        PHI_PAPER: "the paper's Φ alone (box, 20 N force limit, velocity cap)",
    }.get(choice, f"from `{choice}`")
    text = f"`{choice}`: {what}; hash `{resolve_phi(choice, spec).hash[:12]}`"
    if connect:
        text += " (learner episodes; live and gate episodes ran under the runtime workers' own Φ)"
    return text + "; unsafe graded by the independent safety monitor"


def describe_v0(registry: Registry, task: str) -> list[dict[str, Any]]:
    """Version 0 of each ECM of ``task`` as the registry has it (kind, origin, who, what).

    ECMs without a version 0 are skipped.
    """
    out = []
    for name in task_spec(task).ecm_names:
        try:
            v0 = registry.get_version(name, 0)
        except NotFound:
            continue
        row: dict[str, Any] = {
            "name": name,
            "kind": v0.kind.value,
            "origin": v0.origin.value,
            "created_by": v0.created_by,
            "description": v0.descriptor.description,
            "params": None,
        }
        if v0.kind is Kind.CODE:
            try:
                from capevo.runtime.ecm.code import read_params

                row["params"] = read_params(registry.get_artifact(name, 0).decode("utf-8"))
            except (CapevoError, UnicodeDecodeError):
                row["params"] = None
        out.append(row)
    return out


def describe_changes(registry: Registry, versions: Mapping[str, int]) -> list[dict[str, Any]]:
    """What search changed: each code ECM of ``versions`` past version 0, with the parameters whose
    value differs from its version 0 (``{name: (v0, now)}``).

    ECMs at version 0, neural ones and any whose source cannot be read are skipped: the report
    only states what it can show.
    """
    from capevo.runtime.ecm.code import read_params

    out = []
    for name, version in sorted(versions.items()):
        if version <= 0:
            continue
        try:
            if registry.get_version(name, version).kind is not Kind.CODE:
                continue
            before = read_params(registry.get_artifact(name, 0).decode("utf-8"))
            after = read_params(registry.get_artifact(name, version).decode("utf-8"))
        except (CapevoError, UnicodeDecodeError):
            continue
        changed = {k: (before.get(k), v) for k, v in after.items() if before.get(k) != v}
        out.append({"name": name, "version": version, "changed": changed})
    return out


def v0_statement(rows: Sequence[Mapping[str, Any]]) -> str:
    """One paragraph saying plainly what version 0 is."""
    kinds = {r["kind"] for r in rows}
    origins = {r["origin"] for r in rows}
    if not rows:
        return "The registry holds no version 0 of this task's ECMs."
    parts = []
    if "code" in kinds:
        parts.append(
            "**code ECMs**: the built-in parametric skills shipped with capevo (`capevo.learner.skills`). Their "
            "structure (phases, tolerances, noise handling) is written by hand; their parameters are plausible "
            "guesses made without running the simulator and deliberately left untuned"
        )
    if "neural" in kinds:
        parts.append("**neural ECMs**: randomly initialised SAC policies (`capevo.learner.neural_seed`), untrained")
    how = (
        "published with origin `manual` and promoted without a gate"
        if origins == {"manual"}
        else (f"published with origin(s) {', '.join(sorted(origins))}")
    )
    return (
        "Version 0 is **manual creation** in the paper's sense, not learned: "
        + "; ".join(parts)
        + f". They were {how}. Every later version was produced by a learner and had to pass the gate."
    )


def _history(registry: Registry, names: Sequence[str]) -> dict[str, list[AuditEvent]]:
    out: dict[str, list[AuditEvent]] = {}
    for name in names:
        try:
            out[name] = list(registry.history(name))
        except NotFound:
            out[name] = []
    return out


def _final_from_journal(report_dir: Path) -> dict[str, Any] | None:
    from capevo.evolve.state import Journal

    return Journal(report_dir).final()


def write_report(
    report_dir: str | os.PathLike[str],
    *,
    registry: Registry,
    manifest: RunManifest | None = None,
    final: Any = None,
) -> list[Path]:
    """Write ``report.md`` and the plots into ``report_dir`` (see the module docstring).

    Args:
        report_dir: The run's report directory (holds ``metrics.jsonl``).
        registry: The run's registry (for version 0 and the history).
        manifest: The run's manifest; default read from ``report_dir``.
        final: The loop's :class:`~capevo.evolve.loop.FinalEvaluation`, if any; default
            rebuilt from the journal.

    Returns:
        The files written.

    Raises:
        NotFound: ``report_dir`` holds no run.
    """
    from capevo.evolve.plots import plot_progress, plot_timeline

    directory = Path(report_dir)
    manifest = manifest or load_manifest(directory)
    if manifest is None:
        raise NotFound(f"{directory} holds no evolve run (no run.json)", details={"path": str(directory)})
    rows = read_metrics(directory)
    spec = task_spec(manifest.task)
    start_stats = rows[0].live if rows else None
    final_stats, final_versions, comparison = _final(final, directory, rows)

    history = _history(registry, spec.ecm_names)
    t0 = min((r.started_at for r in rows), default=manifest.created_at)
    end = max((r.started_at + r.wall_s for r in rows), default=time.time())
    files = [
        plot_progress(
            rows,
            directory / PROGRESS_PNG,
            title=f"{spec.id} {spec.name}: live episodes per iteration ({manifest.modality}, {manifest.config.preset})",
            final=final_stats,
        ),
        plot_timeline(
            history,
            directory / TIMELINE_PNG,
            t0=t0 - 5.0,
            iteration_starts=[(r.iteration, r.started_at) for r in rows],
            end=max(end, *(e.at for evs in history.values() for e in evs)) if any(history.values()) else end,
            title=f"{spec.id} {spec.name}: ECM versions (registry audit history)",
        ),
    ]
    v0 = describe_v0(registry, spec.name)
    records = version_records(registry, spec.ecm_names)
    changes = describe_changes(registry, final_versions) if final_versions else []
    text = _markdown(
        manifest, rows, v0, start_stats, final_stats, final_versions, comparison, history, records, changes
    )
    path = directory / REPORT
    write_atomically(path, text.encode())
    return [path, directory / "metrics.csv", *files]


def _final(
    final: Any, directory: Path, rows: Sequence[IterationMetrics]
) -> tuple[OutcomeStats | None, Mapping[str, int] | None, Mapping[str, Any] | None]:
    if final is not None:
        return outcome_stats(list(final.final)), dict(final.final_versions), final.comparison
    if not rows:
        return None, None, None
    done = _final_from_journal(directory)
    if done is None:
        return None, None, None
    outcomes = [EpisodeOutcome.from_dict(o) for o in done.get("outcomes") or []]
    if list(done.get("seeds") or []) != list(rows[0].live_seeds) or not outcomes:
        return None, None, None
    from capevo.runtime.gate_stats import paired_stats

    start = [EpisodeOutcome.from_dict(e) for e in rows[0].episodes]
    comparison = paired_stats(start, outcomes, alpha=0.05).to_dict() if start else None
    return outcome_stats(outcomes), dict(done.get("capability_set") or {}), comparison


def _markdown(
    manifest: RunManifest,
    rows: Sequence[IterationMetrics],
    v0: Sequence[Mapping[str, Any]],
    start: OutcomeStats | None,
    final: OutcomeStats | None,
    final_versions: Mapping[str, int] | None,
    comparison: Mapping[str, Any] | None,
    history: Mapping[str, Sequence[AuditEvent]],
    records: Mapping[str, Sequence[EcmVersion]],
    changes: Sequence[Mapping[str, Any]] = (),
) -> str:
    spec = task_spec(manifest.task)
    cfg = manifest.config
    L: list[str] = []
    add = L.append
    add(f"# capevo evolve: {spec.id} {spec.name}")
    add("")
    add(
        f"*Written {time.strftime('%Y-%m-%d %H:%M:%SZ', time.gmtime())}; {len(rows)} of {cfg.iterations} "
        f"iteration(s) finished.*"
    )
    add("")
    add("## Setup")
    add("")
    add("| | |")
    add("|---|---|")
    add(f"| task | {spec.id} `{spec.name}` (robosuite {spec.env_name}): {spec.success_text} |")
    add(f"| decomposition | {' → '.join(f'`{n}`' for n in spec.ecm_names)} |")
    add(f"| hand-offs | {spec.handoff_text} |")
    add(
        f"| preset | `{cfg.preset}`: {cfg.live_episodes} live episodes/iteration, gate N = {cfg.gate_episodes} "
        f"paired held-out seeds, horizon {cfg.horizon or spec.default_horizon} |"
    )
    learner = {
        "code": "CEM over the skill's PARAMS",
        "hybrid": "LLM edit + CEM (CEM alone without an endpoint)",
        "rl": "SAC warm start",
        "il": "behaviour cloning",
    }.get(manifest.modality, manifest.modality)
    add(f"| modality | `{manifest.modality}` ({learner}); learner {manifest.learner} |")
    if manifest.modality in ("code", "hybrid"):
        c = cfg.cem
        add(
            f"| CEM budget | population {c.population}, {c.iterations} iteration(s), {c.episodes_per_candidate} "
            f"episode(s)/candidate: ≤ {c.episodes_per_update} training episodes per update |"
        )
        if c.tie_siblings:
            add(
                "| tied siblings | on (`--tie-siblings`): each search sets one θ in an ECM and its siblings, the "
                "same hand-written skill for another object, which run with it and are gated with it |"
            )
    else:
        add(f"| neural learner budget | learner preset `{cfg.learner_preset}` (`capevo.learner.presets`) |")
    perturbed = "on (object jitter, observation noise, dropped actions)" if manifest.perturbations else "off"
    add(f"| perturbations | {perturbed} |")
    add(f"| safety envelope Φ | {envelope_text(cfg.phi, spec, connect=manifest.mode == 'connect')} |")
    add(f"| registry | {manifest.mode}: `{manifest.registry}` |")
    if manifest.mode == "connect":
        add(
            "| runtime | episodes ran on runtime workers over Zenoh; their own horizon, perturbation and Φ settings "
            "applied |"
        )
    add(f"| seeds | seed plan {manifest.seed}: disjoint training / gate / live ranges (`SeedPlan`) |")
    g = cfg.gate
    add(
        f"| gate | min N {g.min_n}, α {g.alpha}, non-inferiority δ {g.delta}, max slowdown "
        f"{g.max_slowdown if g.max_slowdown is not None else 'off'}, first-version floor {g.first_min_success}, "
        f"safety sign test {g.safety_alpha if g.safety_alpha is not None else 'off'}"
        + (f", unsafe-episode ceiling {g.max_unsafe_rate}" if g.max_unsafe_rate is not None else "")
        + " |"
    )
    add("")
    add("## What version 0 is")
    add("")
    add(v0_statement(v0))
    add("")
    if v0:
        add("| ECM | kind | origin | created by | v0 parameters |")
        add("|---|---|---|---|---|")
        for r in v0:
            params = r.get("params")
            shown = ", ".join(f"{k}={v:.4g}" for k, v in params.items()) if params else "-"
            add(f"| `{r['name']}` | {r['kind']} | {r['origin']} | {r['created_by']} | {shown} |")
        add("")
    add("## Result")
    add("")
    if start is None:
        add("No iteration has finished yet.")
    else:
        add("| | capability set | success (95% CI) | mean reward | σ² |")
        add("|---|---|---|---|---|")
        add(
            f"| start (iteration 0, live seeds) | {_versions(rows[0].active_versions)} | {_rate(start)} | "
            f"{start.reward_mean:.2f} | {start.reward_var:.2f} |"
        )
        if final is not None and final_versions is not None:
            add(
                f"| final (same seeds) | {_versions(final_versions)} | {_rate(final)} | {final.reward_mean:.2f} | "
                f"{final.reward_var:.2f} |"
            )
        add("")
        if comparison:
            t = comparison.get("table", {})
            d = comparison.get("success_difference", {})
            add(
                f"Paired on the same {comparison.get('n')} seeds: final-only successes {t.get('candidate_only')}, "
                f"start-only {t.get('active_only')}; success difference {_pct(d.get('estimate'))} "
                f"{_ci(d.get('low'), d.get('high'))}; exact McNemar p = {_p(comparison.get('p_success'))}; "
                f"Wilcoxon p (reward) = {_p(comparison.get('p_reward'))}."
            )
        elif final is not None:
            add(
                "The final capability set is the starting one (no candidate was promoted), so its result is the "
                "start's."
            )
        add("")
        promoted = [g for r in rows for g in r.gates if g.decision == "promote"]
        rejected = [g for r in rows for g in r.gates if g.decision == "reject"]
        rollbacks, unconfirmed = split_monitor_actions([rb for r in rows for rb in r.rollbacks])
        kept = f" ({len(unconfirmed)} more not confirmed on the same seeds)" if unconfirmed else ""
        add(
            f"Gate: {len(promoted)} promoted, {len(rejected)} rejected; monitor rollbacks: {len(rollbacks)}{kept}. "
            f"Total wall time of the iterations: {sum(r.wall_s for r in rows):.0f} s "
            f"(live {sum(r.wall_live_s for r in rows):.0f} s, learning {sum(r.wall_learn_s for r in rows):.0f} s, "
            f"gating {sum(r.wall_gate_s for r in rows):.0f} s)."
        )
        add("")
    if changes:
        add("## What search changed")
        add("")
        add(
            "The final set's code ECMs past version 0: the parameters whose value differs from version 0 "
            "(the code around them is version 0's; only the `PARAMS` literal is rewritten)."
        )
        add("")
        add("| ECM | final version | changed parameters (v0 → final) |")
        add("|---|---|---|")
        for c in changes:
            shown = ", ".join(f"{k} {_num(a)} → {_num(b)}" for k, (a, b) in c["changed"].items()) or "none"
            add(f"| `{c['name']}` | {c['version']} | {shown} |")
        add("")
    add("## The persistent agent")
    add("")
    hashes = sorted({r.identity_hash for r in rows})
    add(f"- identity hash (π_A + M_id): `{manifest.identity_hash}`")
    if rows:
        same = hashes == [manifest.identity_hash]
        add(
            f"- checked at the start of each of the {len(rows)} iterations: "
            f"{'unchanged every time' if same else 'CHANGED: ' + ', '.join(hashes)}"
        )
        add(f"- policy drift Δπ per iteration: {', '.join(f'{r.delta_pi:g}' for r in rows)} (must be exactly 0)")
    add("- the agent only chose and sequenced ECMs; all improvement came from new ECM versions")
    add("")
    add("## Iterations")
    add("")
    if rows:
        add(
            "| it | capability set | success (95% CI) | reward mean | σ² | Δπ | interv. | unsafe | ECM failures "
            "| updated | learner eps | gate | wall s |"
        )
        add("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            s = r.live
            gate = ", ".join(g.decision for g in r.gates) if r.gates else (r.update_note or "-")
            upd = (
                f"`{r.ecm_updated}` v{r.candidate_version}"
                if r.candidate_version is not None
                else (f"`{r.ecm_updated}`" if r.ecm_updated else "-")
            )
            upd += "".join(f", `{u.ecm}` v{u.version}" for u in r.further)
            add(
                f"| {r.iteration} | {_versions(r.active_versions)} | {_rate(s)} | {s.reward_mean:.2f} | "
                f"{s.reward_var:.2f} | {r.delta_pi:g} | {s.interventions} | {s.unsafe_steps} | {s.ecm_failures} | "
                f"{upd} | {r.learner_episodes} | {gate} | {r.wall_s:.0f} |"
            )
        add("")
        add("Success intervals are 95% Wilson score intervals over that iteration's live episodes.")
        add("")
    add("## Gate decisions")
    add("")
    gated = [(r, g) for r in rows for g in r.gates]
    if gated:
        add(
            "| it | candidate | vs | mode | N | candidate success | active success | difference | McNemar p "
            "| non-inferiority p | Wilcoxon p | decision | failed checks |"
        )
        add("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r, gs in gated:
            cand = f"{gs.candidate_successes}/{gs.n} {_ci(gs.candidate_low, gs.candidate_high)}"
            act = (
                "-"
                if gs.active_successes is None
                else f"{gs.active_successes}/{gs.n} {_ci(gs.active_low, gs.active_high)}"
            )
            diff = _ci(gs.diff_low, gs.diff_high)
            add(
                f"| {r.iteration} | `{gs.ecm}` v{gs.candidate_version} | "
                f"{'v' + str(gs.active_version) if gs.active_version is not None else '-'} | {gs.mode} | {gs.n} | "
                f"{cand} | {act} | {diff} | {_p(gs.p_success)} | {_p(gs.p_noninferiority)} | {_p(gs.p_reward)} | "
                f"**{gs.decision}** | {', '.join(gs.failed_checks) or '-'} |"
            )
        add("")
        add(
            "Intervals: Wilson (success rates) and Tango (difference) at the gate's level 1 − 2α. The full evidence "
            "(per-seed outcomes, checks, traces) is in the registry: `capevo ecm show NAME --version V`."
        )
    else:
        add("No candidate was gated.")
    add("")
    notes = [(r.iteration, r.update_note) for r in rows if r.update_note]
    if notes:
        add("Notes: " + "; ".join(f"iteration {i}: {n}" for i, n in notes))
        add("")
    add("## Rollbacks")
    add("")
    rbs = [(r.iteration, rb) for r in rows for rb in r.rollbacks]
    if rbs:
        for i, rb in rbs:
            add(f"- iteration {i}: {rb.get('reason')}")
    else:
        add("The degradation monitor did not fire.")
    add("")
    add("## Version history (registry)")
    add("")
    add("| ECM | version | origin | parent | learner | state now | audit events |")
    add("|---|---|---|---|---|---|---|")
    for name, versions in records.items():
        acts: dict[int, list[str]] = {}
        for e in history.get(name, ()):
            if e.version is not None:
                acts.setdefault(int(e.version), []).append(e.action.value)
        for v in versions:
            parent = "-" if v.parent is None else str(v.parent)
            learner = v.provenance.learner_id or "-"
            add(
                f"| `{name}` | {v.version} | {v.origin.value} | {parent} | {learner} | {v.state.value} | "
                f"{' → '.join(acts.get(v.version, [])) or '-'} |"
            )
    add("")
    add("## Files")
    add("")
    add(f"- `{PROGRESS_PNG}`: success and reward per iteration; `{TIMELINE_PNG}`: versions per ECM over time")
    add("- `metrics.csv` / `metrics.jsonl`: one row per iteration (fsynced as each iteration finishes)")
    add(
        "- `traces/live`, `traces/monitor`, `traces/gate`, `traces/final`, `traces/learner`: MCAP traces "
        "(`capevo trace summary FILE`; `monitor`: the replaced version replayed on a live window's seeds)"
    )
    add("- `agent/episodic.jsonl`: the agent's episodic memory M_ep; `journal.jsonl`, `run.json`: resume state")
    add("")
    add(f"![progress]({PROGRESS_PNG})")
    add("")
    add(f"![timeline]({TIMELINE_PNG})")
    add("")
    return "\n".join(L)


def version_records(registry: Registry, names: Sequence[str]) -> dict[str, list[EcmVersion]]:
    """Every version of each ECM (for callers that want more than the audit history)."""
    out: dict[str, list[EcmVersion]] = {}
    for name in names:
        try:
            out[name] = list(registry.get_ecm(name).versions)
        except NotFound:
            out[name] = []
    return out


__all__ = [
    "PROGRESS_PNG",
    "REPORT",
    "TIMELINE_PNG",
    "describe_changes",
    "describe_v0",
    "v0_statement",
    "version_records",
    "write_report",
]

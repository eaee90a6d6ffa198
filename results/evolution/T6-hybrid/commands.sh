#!/usr/bin/env bash
# Issue 19, the hybrid path on T6 decided by capevo's gate as one change: the evolved code set's
# successful live traces become behaviour-cloning data for a neural version of every ECM that has
# any, and the gate judges the whole distilled set against the code set (capevo runtime gate
# --with), as capevo evolve judges a chain. results/evolution/T6-distil gated each clone alone, and
# the one that mattered (orient_peg, 4 to 0 on 30 paired seeds) could not pass alone.
#
# Fixed before the run (2026-12-07): the code run (6 iterations, cpu-small, gate second look 20),
# the distillation (capevo learner serve --modality il --once --preset cpu-small), the gate
# (cpu-small, --extension 20: 30 paired seeds, batch 10 of seed plan 0, which the code run's six
# iterations (batches 0-5) never used), and the held-out blocks: 250000-250029 (the run's own
# held-out seeds, as every report in results/evolution) and 280000-280029 (used by no run before).
#
# Usage: commands.sh CODE_RUN OUT
#   CODE_RUN: the work directory of the code run:
#     benchmarks/bench_evolution.py --tasks T6 --preset cpu-small --iterations 6 --live-episodes 10
#       --gate-extension 20 --heldout 30 --work-dir CODE_RUN --name evolution_T6_hybrid_code
#   OUT: a new directory for this run (registry copy, logs, JSON outcomes).
# Run from the repository root with its .venv; resumable only by starting over in a new OUT.
set -euo pipefail
CODE_RUN=$1
OUT=$2
PY=${PY:-.venv/bin/python}
capevo() { "$PY" -m capevo "$@"; }
T=peg_in_hole
ECMS="orient_peg orient_hole approach_peg approach_hole align pre_insert insert hold"
mkdir -p "$OUT"
[ -e "$OUT/data" ] && { echo "$OUT/data exists: use a new OUT" >&2; exit 2; }
cp -r "$CODE_RUN/T6/data" "$OUT/data"
TRACES=$CODE_RUN/T6/report/traces/live
echo "start $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg) cores $(nproc)"

# 1. One behaviour-cloned candidate per ECM with demonstration rows (its own steps in successful
#    live episodes in which it handed over). ECMs with none stay code.
for e in $ECMS; do
  if capevo learner serve --root "$OUT/data" --ecm $T.$e --modality il --once --preset cpu-small \
       --traces "$TRACES" --json > "$OUT/distil-$e.jsonl" 2> "$OUT/distil-$e.err"; then
    echo "distilled $e"
  else
    echo "no candidate for $e: $(tail -1 "$OUT/distil-$e.err")"
  fi
done
capevo ecm list --root "$OUT/data" --json > "$OUT/versions-before-gate.json"

# 2. The gate: the code set against the set with every distilled candidate, one decision.
pins=()
for e in $ECMS; do
  v=$("$PY" - "$OUT/data" $T.$e <<'PYEOF'
import sys
from capevo.registry.local import LocalRegistry
with LocalRegistry(sys.argv[1], actor="reader") as r:
    c = [v.version for v in r.get_ecm(sys.argv[2]).versions if v.state.value == "candidate" and v.origin.value == "il"]
print(c[-1] if c else "")
PYEOF
)
  [ -n "$v" ] && pins+=("$T.$e=$v")
done
[ ${#pins[@]} -gt 0 ] || { echo "nothing distilled" >&2; exit 1; }
first=${pins[0]}
with=()
for p in "${pins[@]:1}"; do with+=(--with "$p"); done
capevo runtime gate "${first%%=*}" "${first##*=}" "${with[@]}" --root "$OUT/data" --task T6 --preset cpu-small \
  --extension 20 --round 10 --json > "$OUT/gate.json" 2> "$OUT/gate.err"
echo "gate ${pins[*]} (batch 10): $("$PY" -c "import json,sys; d=json.load(open(sys.argv[1])); print('promoted' if d['promoted'] else 'rejected', d['reason'])" "$OUT/gate.json")"

# 3. Held-out: the registry's set after the gate, the code set, and the distilled set whatever
#    the gate said.
pin_args=()
for p in "${pins[@]}"; do pin_args+=(--version "$p"); done
for seeds in 250000-250029 280000-280029; do
  capevo runtime evaluate --root "$OUT/data" --task T6 --seeds $seeds --json > "$OUT/heldout-final-$seeds.json" 2>/dev/null
  capevo runtime evaluate --root "$CODE_RUN/T6/data" --task T6 --seeds $seeds --json > "$OUT/heldout-code-$seeds.json" 2>/dev/null
  capevo runtime evaluate --root "$OUT/data" --task T6 --seeds $seeds "${pin_args[@]}" --json > "$OUT/heldout-distilled-$seeds.json" 2>/dev/null
done
for f in "$OUT"/heldout-*.json; do
  "$PY" -c "
import json, sys
d = json.load(open(sys.argv[1]))
print(sys.argv[1].rsplit('/', 1)[1], sum(o['success'] for o in d), '/', len(d), 'unsafe', sum(o['unsafe_steps'] > 0 for o in d),
      'strict', sum(bool(o.get('strict_success')) for o in d), d[0]['capability_set'])" "$f"
done
echo "end $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)"

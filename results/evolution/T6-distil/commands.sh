#!/usr/bin/env bash
# Issue 19, "hybrid across modalities" on T6: the evolved code set's successful live traces
# become behaviour-cloning data for a neural version of each ECM; the gate decides.
#
# Usage: commands.sh CODE_RUN OUT
#   CODE_RUN: the work directory of the code run (benchmarks/bench_evolution.py --tasks T6
#             --work-dir CODE_RUN ...): its registry CODE_RUN/T6/data and live traces
#             CODE_RUN/T6/report/traces/live.
#   OUT:      a new directory for this run (registry copy, logs, JSON outcomes).
# Run from the repository root with its .venv; resumable only by starting over in a new OUT.
set -euo pipefail
CODE_RUN=$1
OUT=$2
PY=${PY:-.venv/bin/python}
capevo() { "$PY" -m capevo "$@"; }
T=peg_in_hole
mkdir -p "$OUT"
[ -e "$OUT/data" ] && { echo "$OUT/data exists: use a new OUT" >&2; exit 2; }
cp -r "$CODE_RUN/T6/data" "$OUT/data"
TRACES=$CODE_RUN/T6/report/traces/live

# 1. One behaviour-cloned candidate per ECM with demonstration rows (the ECM's own steps in
#    successful episodes in which it handed over). ECMs with none are left as they are.
for e in orient_peg orient_hole approach_peg approach_hole align pre_insert insert hold; do
  if capevo learner serve --root "$OUT/data" --ecm $T.$e --modality il --once --preset cpu-small \
       --traces "$TRACES" --json > "$OUT/distil-$e.jsonl" 2> "$OUT/distil-$e.err"; then
    echo "distilled $e"
  else
    echo "no candidate for $e: $(tail -1 "$OUT/distil-$e.err")"
  fi
done
capevo ecm list --root "$OUT/data" --json > "$OUT/versions-before-gate.json"

# 2. The gate, in plan order, each candidate against the active set, on batches of the seed
#    plan's gate seeds that the code run (6 iterations: batches 0-5) never used.
round=10
for e in orient_peg orient_hole approach_peg approach_hole align pre_insert insert hold; do
  v=$("$PY" - "$OUT/data" $T.$e <<'PYEOF'
import sys
from capevo.registry.local import LocalRegistry
with LocalRegistry(sys.argv[1], actor="reader") as r:
    c = [v.version for v in r.get_ecm(sys.argv[2]).versions if v.state.value == "candidate" and v.origin.value == "il"]
print(c[-1] if c else "")
PYEOF
)
  [ -n "$v" ] || continue
  capevo runtime gate $T.$e "$v" --root "$OUT/data" --task T6 --preset cpu-small --extension 20 \
    --round $round --json > "$OUT/gate-$e.json" 2> "$OUT/gate-$e.err"
  echo "gate $e v$v (batch $round): $("$PY" -c "import json,sys; print(json.load(open(sys.argv[1]))['reason'])" "$OUT/gate-$e.json")"
  round=$((round + 1))
done

# 3. Held-out evaluations (seeds no learner, gate or live episode used): the registry's final
#    set, the code set, and every distilled candidate in place whatever the gate said.
pins=()
for e in orient_peg orient_hole approach_peg approach_hole align pre_insert insert hold; do
  [ -f "$OUT/gate-$e.json" ] || continue
  pins+=(--version "$T.$e=$("$PY" -c "import json,sys; print(json.load(open(sys.argv[1]))['candidate_version'])" "$OUT/gate-$e.json")")
done
for seeds in 250000-250029 260000-260029 270000-270029; do
  capevo runtime evaluate --root "$OUT/data" --task T6 --seeds $seeds --json > "$OUT/heldout-final-$seeds.json" 2>/dev/null
  capevo runtime evaluate --root "$CODE_RUN/T6/data" --task T6 --seeds $seeds --json > "$OUT/heldout-code-$seeds.json" 2>/dev/null
  capevo runtime evaluate --root "$OUT/data" --task T6 --seeds $seeds "${pins[@]}" --json > "$OUT/heldout-distilled-$seeds.json" 2>/dev/null
done
for f in "$OUT"/heldout-*.json; do
  "$PY" -c "
import json, sys
d = json.load(open(sys.argv[1]))
print(sys.argv[1].rsplit('/', 1)[1], sum(o['success'] for o in d), '/', len(d), 'unsafe', sum(o['unsafe_steps'] > 0 for o in d),
      'strict', sum(bool(o.get('strict_success')) for o in d), d[0]['capability_set'])" "$f"
done

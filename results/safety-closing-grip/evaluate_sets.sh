#!/usr/bin/env bash
# evaluate_sets.sh REPO OUT EVOLVED: on held-out seeds 250000-250029 under REPO's default Φ (--phi task),
# the evolved T1-T3 sets (EVOLVED/T1/data ..., from bench_evolution.py --work-dir EVOLVED) and the
# hand-set T1-T5 sets (capevo.learner.skills.hand_set, each seeded into a fresh registry under OUT).
# Writes OUT/{evolved-T1..T3,T1..T5}.json (capevo runtime evaluate --json) and OUT/summary.txt.
set -euo pipefail
REPO=$(cd "$1" && pwd); OUT=$2; EVOLVED=$3
PY=${PY:-/work/main/.venv/bin/python}
mkdir -p "$OUT"; OUT=$(cd "$OUT" && pwd)
summarise() {  # NAME FILE
  "$PY" -c "import json,sys; rows=json.load(open(sys.argv[2])); print(sys.argv[1], sum(r['success'] for r in rows), len(rows), 'unsafe', sum(r['unsafe_steps']>0 for r in rows), 'steps', sum(r['steps'] for r in rows)/len(rows))" "$1" "$2" >> "$OUT/summary.txt"
}
cd "$REPO"
for T in T1 T2 T3; do
  PYTHONPATH=$REPO "$PY" -m capevo runtime evaluate --root "$EVOLVED/$T/data" --task $T --seeds 250000-250029 --phi task --json > "$OUT/evolved-$T.json" 2> "$OUT/evolved-$T.err"
  summarise "evolved $T" "$OUT/evolved-$T.json"
done
for T in T1 T2 T3 T4 T5; do
  ROOT=$OUT/$T-reg; rm -rf "$ROOT"
  PYTHONPATH=$REPO "$PY" -c "
import sys
from capevo.learner.skills.hand_set import seed_hand_set
from capevo.registry.local import LocalRegistry
with LocalRegistry(sys.argv[1], actor='bench-hand-set') as r: seed_hand_set(r, sys.argv[2])
" "$ROOT" $T 2>/dev/null
  PYTHONPATH=$REPO "$PY" -m capevo runtime evaluate --root "$ROOT" --task $T --seeds 250000-250029 --phi task --json > "$OUT/$T.json" 2> "$OUT/$T.err"
  summarise "$T" "$OUT/$T.json"
done

#!/usr/bin/env bash
# Issue 19, T5 with code ECMs whose siblings share their parameters (--tie-siblings), on two runtime workers.
#
# Fixed before the run (2026-12-08, 00:50 UTC): everything as in ../T5-code/workers/commands.sh
# (seed plan 0, cpu-small, 10 live episodes per iteration, the gate's second look +20 seeds, the
# default Φ `task`, the paper's perturbations, two idle runtime workers), plus --tie-siblings:
# each CEM search sets one parameter set in a step's three ECMs (milk, bread, can), as the
# hand-set row shares one. Nothing about the task, its skills or its v0 changes.
# Iterations: 6 declared, as the untied run. One session here fits about 4 (35 min each on two
# workers), so the run is started with 4 and evaluated held out; it is resumed to 6 with the same
# WORK (`commands.sh WORK 6`) only if the machine is still there.
# Held out: seeds 250000-250029 (no learner, gate or live episode uses them), the final set and
# the hand-set parameters (capevo.learner.skills.hand_set) on the same seeds.
#
# Usage: commands.sh WORK [ITERATIONS]
#   Run from the repository root with its .venv. Resumable: run the same command again on the
#   same WORK after a crash or a stop (capevo evolve continues after its last finished
#   iteration; a finished run only redoes the held-out evaluation).
set -euo pipefail
WORK=$1
ITERATIONS=${2:-6}
PY=${PY:-.venv/bin/python}
PORT=${PORT:-7621}
EP=tcp/127.0.0.1:$PORT
export OMP_NUM_THREADS=1
capevo() { "$PY" -m capevo "$@"; }
mkdir -p "$WORK/logs"
echo "start $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg) cores $(getconf _NPROCESSORS_ONLN) commit $(git rev-parse --short HEAD)"

pids=()
stop_all() { for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done; wait 2>/dev/null || true; }
trap stop_all EXIT

# (backgrounded as "$PY" itself, not the capevo function, so that $! is the server and the trap
# stops it; the function's subshell would leave it running)
"$PY" -m capevo registry serve --root "$WORK/data" --listen "$EP" --no-multicast > "$WORK/logs/registry.out" 2> "$WORK/logs/registry.err" &
pids+=($!)
for w in t5-a t5-b; do
  "$PY" -m capevo runtime serve --connect "$EP" --task T5 --idle --worker-id "$w" > "$WORK/logs/$w.out" 2> "$WORK/logs/$w.err" &
  pids+=($!)
done

capevo evolve --task T5 --connect "$EP" --preset cpu-small --iterations "$ITERATIONS" --live-episodes 10 \
  --gate-extension 20 --tie-siblings --report-dir "$WORK/report" --worker-wait 300 --json \
  > "$WORK/evolve.json" 2> "$WORK/logs/evolve.err"
echo "evolved $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)"

# Held out, on the same two workers: the registry's final set.
capevo runtime evaluate --connect "$EP" --task T5 --seeds 250000-250029 --json > "$WORK/heldout-final.json"
stop_all
trap - EXIT

# The hand-set parameters in a registry of their own, embedded (nothing else runs now).
rm -rf "$WORK/hand-set"
"$PY" - "$WORK/hand-set" <<'PYEOF'
import sys
from capevo.learner.skills.hand_set import seed_hand_set
from capevo.registry.local import LocalRegistry
with LocalRegistry(sys.argv[1], actor="hand-set") as r:
    seed_hand_set(r, "T5")
PYEOF
capevo runtime evaluate --root "$WORK/hand-set" --task T5 --seeds 250000-250029 --json > "$WORK/heldout-hand-set.json"
echo "held out $(date -u +%FT%TZ) load $(cut -d' ' -f1-3 /proc/loadavg)"

for f in "$WORK"/heldout-final.json "$WORK"/heldout-hand-set.json; do
  "$PY" - "$f" <<'PYEOF'
import json, sys
from capevo.runtime.gate_stats import wilson_interval
rows = json.load(open(sys.argv[1]))
ok = sum(r["success"] for r in rows)
ci = wilson_interval(ok, len(rows), alpha=0.025)
print(f"{sys.argv[1].rsplit('/', 1)[1]}: {ok}/{len(rows)} [{ci.low:.0%}, {ci.high:.0%}], "
      f"unsafe {sum(r['unsafe_steps'] > 0 for r in rows)}, mean steps {sum(r['steps'] for r in rows) / len(rows):.0f}")
PYEOF
done

#!/usr/bin/env bash
# Usage: results/finish-run.sh RESULTS_DIR CELLS
# After `capevo experiment run CONFIG --out RESULTS_DIR/run` has finished all CELLS cells: copy the
# small records of the run out of run/ (where git tracks only them) into RESULTS_DIR/cells, and write
# and check the report in RESULTS_DIR. Run from the repository root.
set -euo pipefail
D=${1:?usage: results/finish-run.sh RESULTS_DIR CELLS}
N=${2:?usage: results/finish-run.sh RESULTS_DIR CELLS}
PY=${PY:-.venv/bin/python}
done_cells=$(ls -d "$D"/run/cells/*/ 2>/dev/null | grep -vc '\.partial/$' || true)
[ "$done_cells" -eq "$N" ] || { echo "$done_cells of $N cells have finished: resume the run first" >&2; exit 2; }
for cell in "$D"/run/cells/*/; do
  name=$(basename "$cell")
  [ -f "$cell/done.json" ] || { echo "$name has not finished: resume the run first" >&2; exit 2; }
  mkdir -p "$D/cells/$name"
  cp "$cell"/cell.json "$cell"/done.json "$cell"/metrics.jsonl "$D/cells/$name/"
  # a cell resumed after an interruption says when, on which host and with which code
  if [ -f "$cell/resumes.jsonl" ]; then cp "$cell/resumes.jsonl" "$D/cells/$name/"; fi
  # ours' gate evidence, per iteration (the loop's own metrics)
  if [ -f "$cell/evolve/metrics.jsonl" ]; then cp "$cell/evolve/metrics.jsonl" "$D/cells/$name/evolve-metrics.jsonl"; fi
done
cp "$D"/run/experiment.json "$D"/run/provenance.json "$D/"
"$PY" -m capevo experiment report "$D"
"$PY" -m capevo experiment verify "$D"

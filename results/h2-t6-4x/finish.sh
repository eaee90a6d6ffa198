#!/usr/bin/env bash
# After `capevo experiment run results/h2-t6-4x/h2-t6-4x.yaml --out results/h2-t6-4x/run` has
# finished every cell: copy the small records of the run out of run/ (where git tracks only them) and write
# and check the report. Run from the repository root.
set -euo pipefail
D=results/h2-t6-4x
PY=${PY:-.venv/bin/python}
done_cells=$(ls -d "$D"/run/cells/*/ 2>/dev/null | wc -l)
[ "$done_cells" -eq 8 ] || { echo "$done_cells of 8 cells have finished: resume the run first" >&2; exit 2; }
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

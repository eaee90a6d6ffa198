# Sourced by scripts/demo and scripts/test: create .venv on first use and (re)install the
# package whenever pyproject.toml changed since the last install.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="$ROOT/.venv"
PY="${PYTHON:-python3}"
STAMP="$VENV/.capevo-install-stamp"
WANT="$(sha256sum "$ROOT/pyproject.toml" | cut -d' ' -f1)-${CAPEVO_EXTRAS:-test}"
if [ ! -x "$VENV/bin/python" ]; then
  echo "capevo: creating virtual environment in $VENV" >&2
  "$PY" -m venv "$VENV"
fi
if [ ! -f "$STAMP" ] || [ "$(cat "$STAMP")" != "$WANT" ]; then
  echo "capevo: installing capevo[${CAPEVO_EXTRAS:-test}] (first run takes a few minutes)" >&2
  "$VENV/bin/python" -m pip install --quiet --upgrade pip "setuptools>=68" >&2
  # torch is pinned in pyproject (2.13.0, CPU build): an unpinned torch would pull CUDA wheels.
  "$VENV/bin/python" -m pip install --quiet -e "$ROOT[${CAPEVO_EXTRAS:-test}]" >&2
  echo "$WANT" > "$STAMP"
fi
export PATH="$VENV/bin:$PATH"
cd "$ROOT"

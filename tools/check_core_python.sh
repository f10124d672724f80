#!/usr/bin/env bash
# The core install (no extras) on another Python: a fresh venv, `pip install .`, then ingest, split, doctor --verify
# and export on real bags, and the one-line error of a stage that needs an extra. Prints what each step printed.
#   tools/check_core_python.sh /path/to/python3.13 BAGS_DIR        (bags: adlpipe record ... --out BAGS_DIR)
set -euo pipefail
py=$1; bags=$2
work=$(mktemp -d); trap 'rm -rf "$work"' EXIT
"$py" -m venv "$work/venv"; bin=$work/venv/bin
"$bin/pip" install -q "$(dirname "$0")/.." 2>&1 | grep -v "^WARNING: Location" || true
echo "$("$bin/python" -c 'import sys; print(sys.version.split()[0])'): core installed; torch, mujoco, dvc, rerun-sdk present:" \
     "$("$bin/pip" list 2>/dev/null | grep -ciE '^(torch|mujoco|dvc|rerun-sdk) ' || true)"
cd "$work"
"$bin/adlpipe" ingest "$bags"/*.mcap -o adl.h5 --size 64 | tail -1
"$bin/adlpipe" split adl.h5 -o split.json --test-fraction 0.34 | tail -1
"$bin/adlpipe" doctor adl.h5 --json doctor.json | tail -1
"$bin/adlpipe" doctor adl.h5 --verify "$bags"/*.mcap | tail -1
"$bin/adlpipe" export --format lerobot adl.h5 lerobot | tail -1
"$bin/adlpipe" train --model fm_cnn --data adl.h5 --out m 2>&1 && exit 1 || true   # must fail in one line

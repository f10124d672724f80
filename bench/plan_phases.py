"""Where a plan's time goes, per host (issue P2): evaluate's encoder and sampler parts of each default sampler's
plan, and the speed claim as the report judges it (on the sampler) beside the whole plan's ratio on this host.

    python -m adlpipe.evaluate --models models/fm_cnn models/dp_cnn models/bc_cnn --metrics /tmp/e.json \
        --details /tmp/plan_details.json --plots /tmp/s.csv --table /tmp/t.md
    python bench/plan_phases.py /tmp/plan_details.json > results/bench/plan_phases.txt

Run it on an idle machine: the medians are of batch-1 plans timed one after another (evaluate --repeats).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from adlpipe.evaluation.claims import speed_verdict

ROWS = (("fm_cnn", "euler/1", "FM-1"), ("fm_cnn", "euler/16", "FM-16"), ("dp_cnn", "ddpm/16", "DP-16"),
        ("dp_cnn", "ddpm_trailing/1", "DP-1 (trailing)"), ("bc_cnn", "direct/1", "BC"))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("details", type=Path, help="evaluate's details (--details)")
    ev = json.loads(p.parse_args().details.read_text())
    host = ev.get("host", {})
    print(f"host: {host.get('cpu')}, {host.get('cores')} cores, {host.get('torch_threads')} torch threads, "
          f"torch {host.get('torch')}{', ' + host['gpu'] if host.get('gpu') else ''}; best checkpoints, batch 1")
    print(f"{'plan':18} {'evaluations':>11} {'plan ms':>9} {'encoder ms':>11} {'sampler ms':>11} {'encoder share':>14}")
    for model, key, label in ROWS:
        r = ev["models"].get(model, {}).get("best", {}).get(key)
        if r and r.get("sampler_ms") is not None:
            print(f"{label:18} {r['evaluations']:>11} {r['ms']:>9.2f} {r['encoder_ms']:>11.2f} {r['sampler_ms']:>11.2f}"
                  f" {100 * r['encoder_ms'] / r['ms']:>13.0f}%")
    fm1, dp16 = ev["models"]["fm_cnn"]["best"]["euler/1"], ev["models"]["dp_cnn"]["best"]["ddpm/16"]
    print(f"\nFM-1 much faster than DP-16 (at least 8x): {speed_verdict(fm1, dp16, host)}")


if __name__ == "__main__":
    main()

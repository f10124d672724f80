"""Do the dataset tools robot-learning users install read adlpipe's LeRobot export? (issue E.2)

    python bench/export_peers.py DATA [--peers DIR]

Exports DATA three times (the default: cameras as video, depth and affordance maps as PNG; --maps video; --maps none)
and runs each peer installed in a venv of its own under DIR (bench/doctor_peers.py says how) on each: kalanos grade,
deepen grade (JSON), lerobot-doctor check (JSON). Prints per peer and export whether it read every episode or what
it refused with. LeRobot itself: bench/lerobot_check.py.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def kalanos(venv: Path, export: Path) -> str:
    out = subprocess.run([str(venv / "bin" / "kalanos"), "grade", str(export), "--json", "--no-color"],
                         capture_output=True, text=True, timeout=1800).stdout
    report = json.loads(out)
    unread = [s for s in report.get("skipped", []) or []] + list(report.get("operational_errors", []) or [])
    eligible = report.get("eligibility_counts", {})
    refused = report["inventory"].get("refused") if isinstance(report.get("inventory"), dict) else None
    return (f"{len(report['episodes'])} episodes graded, eligibility {eligible}"
            + (f"; refused: {refused}" if refused else "") + (f"; not read: {unread}" if unread else ""))


def deepen(venv: Path, export: Path) -> str:
    proc = subprocess.run([str(venv / "bin" / "deepen"), "grade", str(export), "--json", "--quiet"],
                          capture_output=True, text=True, timeout=1800)
    if proc.returncode not in (0, 1) or not proc.stdout.strip():
        return f"failed: {proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else proc.returncode}"
    report = json.loads(proc.stdout)
    return (f"format {report['format']}, {len(report['episodes'])} episodes graded, grade "
            f"{report['overall']['grade']}, calibration: {report['calibration']['verdict']}")


def lerobot_doctor(venv: Path, export: Path) -> str:
    proc = subprocess.run([str(venv / "bin" / "lerobot-doctor"), "check", str(export), "--json"],
                          capture_output=True, text=True, timeout=1800)
    report = json.loads(proc.stdout)
    checks = {c["name"]: c["severity"] for c in report["checks"]}
    return (f"{report['total_episodes']} episodes, {report['total_frames']} frames; metadata and format "
            f"{checks.get('Metadata & Format Compliance')}, video integrity {checks.get('Video Integrity')}")


PEERS = {"kalanos": (kalanos, "kalanos"), "deepen-grade": (deepen, "deepen"),
         "lerobot-doctor": (lerobot_doctor, "lerobot-doctor")}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("data", type=Path)
    p.add_argument("--peers", type=Path, default=REPO / "bench" / "peers")
    a = p.parse_args()
    root = Path(tempfile.mkdtemp(prefix="adlpipe-export-peers-"))
    exports = {"default (video + PNG maps)": root / "video", "--maps video": root / "video_maps",
               "--maps none": root / "no_maps"}
    for out, extra in zip(exports.values(), ([], ["--maps", "video"], ["--maps", "none"]), strict=True):
        subprocess.run([sys.executable, "-m", "adlpipe.export", str(a.data), str(out), *extra], check=True,
                       capture_output=True)
    for name, (run, cli) in PEERS.items():
        venv = a.peers / name
        if not (venv / "bin" / cli).exists():
            print(f"{name}: not installed under {a.peers}")
            continue
        for label, out in exports.items():
            try:
                print(f"{name} on {label}: {run(venv, out)}")
            except (subprocess.SubprocessError, json.JSONDecodeError, KeyError) as exc:
                print(f"{name} on {label}: failed ({type(exc).__name__}: {exc})")


if __name__ == "__main__":
    main()

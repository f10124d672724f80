"""The peers of adlpipe's doctor, each run from a venv of its own on the same planted recordings
(bench/doctor_vs_peers.py), their findings read per episode from their JSON reports.

    python -m venv PEERS/kalanos && PEERS/kalanos/bin/pip install "kalanos[all]"              # 0.8.2 measured
    python -m venv PEERS/deepen-grade && PEERS/deepen-grade/bin/pip install "deepen-grade[all]"   # 0.4.1
    python -m venv PEERS/lerobot-doctor && PEERS/lerobot-doctor/bin/pip install lerobot-doctor   # 0.2.0

kalanos grades the folder of bags (its MCAP adapter): a finding is each reason of an episode not eligible.
deepen-grade grades each bag: a finding is each check at warn or fail. lerobot-doctor checks the dataset's LeRobot
export (python -m adlpipe.export): a finding is each check whose warn or fail message names the episode.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

Findings = dict[str, set[str]]  # bag name -> what the tool found on its episode


def _run(cmd: list[str]) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=1800)


def kalanos(venv: Path, root: Path) -> Findings:
    proc = _run([str(venv / "bin" / "kalanos"), "grade", str(root / "bags"), "--json", "--no-color"])
    report = json.loads(proc.stdout)
    out: Findings = {}
    for ep in report["episodes"]:
        bag = Path(ep["source_paths"][0]["path"]).name
        el = ep["eligibility"]
        out[bag] = set() if el["status"] in ("pass", "eligible") else {r["id"] for r in el["reasons"]}
    return out


def deepen(venv: Path, root: Path) -> Findings:
    out: Findings = {}
    for bag in sorted((root / "bags").glob("*.mcap")):
        proc = _run([str(venv / "bin" / "deepen"), "grade", str(bag), "--json", "--quiet"])
        report = json.loads(proc.stdout)
        out[bag.name] = {c["check_id"] for ep in report["episodes"] for c in ep["checks"]
                         if c["severity"] in ("warn", "fail")}
    return out


def lerobot_doctor(venv: Path, root: Path) -> Findings:
    import pyarrow.parquet as pq

    export = root / "lerobot"
    if not export.exists():
        # a LeRobot dataset has one state vector: an episode whose joint names differ from most (a planted swap)
        # cannot go in, so the export takes the others and lerobot-doctor checks those
        import h5py

        with h5py.File(root / "adl.h5") as f:
            names = {n: tuple(map(str, f["episodes"][n]["series/joint_pos"].attrs["joint_names"]))
                     for n in f["episodes"]}
        common = max(set(names.values()), key=list(names.values()).count)
        subprocess.run([sys.executable, "-m", "adlpipe.export", str(root / "adl.h5"), str(export), "--episodes",
                        *sorted(n for n, j in names.items() if j == common)], check=True, capture_output=True)
    episodes = pq.read_table(next((export / "meta" / "episodes").rglob("*.parquet"))).to_pylist()
    bag_of = json.loads((root / "bag_of_episode.json").read_text())
    by_index = {ep["episode_index"]: bag_of[ep["adlpipe/name"]] for ep in episodes}
    proc = _run([str(venv / "bin" / "lerobot-doctor"), "check", str(export), "--json"])
    out: Findings = {bag: set() for bag in by_index.values()}
    for check in json.loads(proc.stdout)["checks"]:
        for msg in check["messages"]:
            if msg["severity"] not in ("WARN", "FAIL"):
                continue
            named = re.findall(r"[Ee]pisode (\d+)", msg["message"])
            named += [i for pair in re.findall(r"\((\d+), (\d+)\)", msg["message"]) for i in pair]
            for i in named:
                if int(i) in by_index:
                    out[by_index[int(i)]].add(check["name"])
    return out


PEERS = {"kalanos": (kalanos, "kalanos"), "deepen-grade": (deepen, "deepen"),
         "lerobot-doctor": (lerobot_doctor, "lerobot-doctor")}


def peer_findings(peers: Path, root: Path) -> dict[str, Findings | str]:
    """Each installed peer's findings, or why it gave none."""
    out: dict[str, Findings | str] = {}
    for name, (run, cli) in PEERS.items():
        venv = peers / name
        if not (venv / "bin" / cli).exists():
            continue
        try:
            out[name] = run(venv, root)
        except (subprocess.SubprocessError, json.JSONDecodeError, KeyError, OSError) as exc:
            out[name] = f"failed: {type(exc).__name__}: {exc}"
    return out

"""adlpipe's doctor beside the dataset checkers robot-learning users already install, on the same recordings with
planted defects (issue E.3).

    python bench/doctor_vs_peers.py [--out DIR] [--peers DIR]

Records 30 episodes (3 per task, 64 px, 10 Hz camera), plants one defect in each of 8 of them (bench/plant_defects.py:
frozen camera, tf glitch between frames and on a frame, idle start, camera dropout, joint-value spike, joint NaN, the
same demonstration saved twice), ingests all 30 and runs `python -m adlpipe.doctor`. A defect is found when the
episode carries the flag that names it; a clean episode with any flag is a false flag. Each peer installed in a venv
of its own under --peers (bench/peers.md says how) runs on the same bags or on their LeRobot export
(`python -m adlpipe.export`); its table row says what it flagged. Prints the table README shows.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from doctor_peers import Findings, peer_findings  # noqa: E402
from plant_defects import DEFECTS, plant  # noqa: E402

EPISODES_PER_TASK = 3
COPY = "near-duplicate episode"
TASK_OF_COPY = "brush_the_teeth"  # its third bag is its first saved again


def adlpipe(*args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", *args], cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    if proc.returncode:
        sys.exit(f"{args[0]} failed: {proc.stderr.strip()}")
    return proc


def recordings(root: Path) -> tuple[dict[str, str], list[str]]:
    """Record the clean episodes and plant the defects: (bag name -> defect, clean bag names)."""
    clean = root / "clean"
    adlpipe("adlpipe.record", "--out", str(clean), "--episodes", str(EPISODES_PER_TASK), "--size", "64",
            "--camera-hz", "10", "--format", "mcap", "--seed", "7", "--workers", "2")
    bags = sorted(clean.glob("*.mcap"))
    planted = root / "bags"
    planted.mkdir()
    others = [b for b in bags if not b.name.startswith(TASK_OF_COPY)]
    victims = others[:: len(others) // (len(DEFECTS) - 1)][: len(DEFECTS) - 1]  # one per task, spread
    defects = {}
    for bag, defect in zip(victims, [d for d in DEFECTS if d != COPY], strict=True):
        plant(bag, planted / bag.name, defect)
        defects[bag.name] = defect
    plant(clean / f"{TASK_OF_COPY}_0000.mcap", planted / f"{TASK_OF_COPY}_0002.mcap", COPY)  # saved twice
    defects[f"{TASK_OF_COPY}_0002.mcap"] = COPY
    for bag in bags:
        if bag.name not in defects:
            shutil.copy(bag, planted / bag.name)
    return defects, [b.name for b in bags if b.name not in defects]


def doctor_flags(root: Path) -> dict[str, list[str]]:
    """Bag name -> the doctor's flags on its episode (and bag_of_episode.json for the peers on the export)."""
    import h5py

    data = root / "adl.h5"
    adlpipe("adlpipe.ingest", *map(str, sorted((root / "bags").glob("*.mcap"))), "-o", str(data), "--size", "64")
    adlpipe("adlpipe.doctor", str(data), "--json", str(root / "doctor.json"))
    figs = json.loads((root / "doctor.json").read_text())["episodes"]
    with h5py.File(data) as f:
        bag_of = {n: Path(str(f["episodes"][n].attrs["source_path"])).name for n in f["episodes"]}
    (root / "bag_of_episode.json").write_text(json.dumps(bag_of))
    return {bag_of[n]: fig["flags"] for n, fig in figs.items()}


def score(findings: Findings, defects: dict[str, str], clean: list[str]) -> tuple[dict[str, bool], int]:
    """(defect -> found, clean episodes with any finding). Found: the episode carries a finding that no clean
    episode carries (a finding every episode of a task gets does not single the defect out)."""
    everyday = set().union(*(findings.get(b, set()) for b in clean))
    found = {defect: bool(findings.get(bag, set()) - everyday) for bag, defect in defects.items()}
    return found, sum(bool(findings.get(b)) for b in clean)


def table(rows: dict[str, tuple[dict, int] | str], n_clean: int) -> str:
    head = "| tool | " + " | ".join(DEFECTS) + f" | found | clean episodes flagged (of {n_clean}) |"
    lines = [head, "| --- |" + " :---: |" * len(DEFECTS) + " ---: | ---: |"]
    for tool, row in rows.items():
        if isinstance(row, str):
            lines.append(f"| {tool} | {row} |" + " |" * (len(DEFECTS) + 1))
            continue
        found, false = row
        cells = " | ".join("yes" if found.get(d) else "-" for d in DEFECTS)
        lines.append(f"| {tool} | {cells} | {sum(found.values())} of {len(DEFECTS)} | {false} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, help="keep the bags and the dataset here (default: a temporary folder)")
    p.add_argument("--peers", type=Path, default=REPO / "bench" / "peers", help="folder of the peers' venvs")
    a = p.parse_args()
    root = a.out or Path(tempfile.mkdtemp(prefix="adlpipe-doctor-peers-"))
    root.mkdir(parents=True, exist_ok=True)
    defects, clean = recordings(root)
    flags = doctor_flags(root)
    clean = [b for b in clean if b != f"{TASK_OF_COPY}_0000.mcap"]  # the copy's original: one of the planted pair
    tools: dict[str, Findings | str] = {"adlpipe doctor": {b: {f.split(":")[0] for f in fl} for b, fl in flags.items()}}
    tools.update(peer_findings(a.peers, root))
    rows: dict[str, tuple[dict, int] | str] = {}
    for tool, findings in tools.items():
        rows[tool] = findings if isinstance(findings, str) else score(findings, defects, clean)
        if isinstance(findings, str):
            continue
        print(f"## {tool}")
        for bag, defect in defects.items():
            print(f"  {defect} ({bag}): {', '.join(sorted(findings.get(bag, set()))) or '-'}")
        for bag in clean:
            if findings.get(bag):
                print(f"  clean {bag}: {', '.join(sorted(findings[bag]))}")
    print(table(rows, len(clean)))


if __name__ == "__main__":
    main()

"""Where flow matching's Kitchen rollouts fail against Diffusion Policy's (issue L3, item 1): each sub-task of the
demonstrator's order (microwave, light switch, slide cabinet, kettle) per model, from the committed benchmark
details, on the same 100 initial conditions; paired per sub-task (McNemar's exact test on the initial conditions
where one model completed it and the other did not), and each phase's rate among the rollouts that completed the
phases before it (the environment counts the sub-tasks as a set: a later one done without an earlier is counted
at its own column, not as reached).

    python pipelines/kitchen_levers/phases.py > pipelines/kitchen_levers/results/phases.md
"""

from __future__ import annotations

import json
from pathlib import Path

from adlpipe.envs.kitchen import TASKS
from adlpipe.evaluation.stats import paired_success

RESULTS = Path(__file__).with_name("results")
ORDER = ("microwave", "light switch", "slide cabinet", "kettle")  # the demonstrator's (adlpipe.envs.kitchen)
RUNS = {"15 epochs": ("kitchen_levers_details.json", "fm_cnn", "dp_cnn"),
        "30 epochs": ("kitchen_long_details.json", "fm_cnn_e30", "dp_cnn_e30"),
        "60 epochs": ("kitchen_e60_details.json", "fm_cnn_e60", "dp_cnn_e60")}


def episodes(details: dict, model: str, steps: int) -> dict[int, set[str]]:
    row = next(r for r in details["results"] if r["model"] == model and r["steps"] == steps
               and r["checkpoint"] == "last")
    return {e["seed"]: set(e["tasks"]) for e in row["per_episode"]}


def phase_cells(done: list[set[str]]) -> list[str]:
    """Per phase: completed of those that completed every earlier phase."""
    out, reached = [], done
    for task in ORDER:
        hit = [d for d in reached if task in d]
        out.append(f"{len(hit)} of {len(reached)}")
        reached = hit
    return out


def main() -> None:
    assert set(ORDER) == set(TASKS)
    print("# Franka Kitchen: sub-tasks per model, FM against DP on the same initial conditions\n")
    print("Last checkpoints, 100 initial conditions (100000-100099), Ta 8; `phases.py` reads the committed "
          "benchmark details. Per sub-task: completions (FM vs DP) and McNemar's exact test on the initial "
          "conditions only one of them completed it in; then each phase in the demonstrator's order among the "
          "rollouts that completed every earlier phase.\n")
    print("| budget | steps | sub-task | FM | DP | FM only : DP only | p | FM in order | DP in order |")
    print("| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for budget, (name, fm, dp) in RUNS.items():
        details = json.loads((RESULTS / name).read_text())
        for steps in (2, 16):
            a, b = episodes(details, fm, steps), episodes(details, dp, steps)
            seeds = sorted(set(a) & set(b))
            fa, fb = phase_cells([a[s] for s in seeds]), phase_cells([b[s] for s in seeds])
            for k, task in enumerate(ORDER):
                x, y = [task in a[s] for s in seeds], [task in b[s] for s in seeds]
                t = paired_success(x, y)
                print(f"| {budget} | {steps} | {task} | {sum(x)} | {sum(y)} | {t.only_first} : {t.only_second} | "
                      f"{t.p_value:.3f} | {fa[k]} | {fb[k]} |")


if __name__ == "__main__":
    main()

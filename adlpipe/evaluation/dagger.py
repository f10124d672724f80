"""The DAgger and HG-DAgger rounds' table (pipelines/closed_loop, docs/science/dagger.md): each arm's closed-loop
success on the same fresh scenes, paired with the arm it went on from and with open loop, how often its rollouts
left the demonstrated path and how far they planned there, the force on the person, how many states were labelled
(and by whom), and whether each model converged."""

from __future__ import annotations

import numpy as np

from ..sim.tasks import FORCE_LIMIT_N
from .stats import paired_success, rate_cell

# (arm, what it is, the arm it went on from)
ARMS = (("r0", "round 0: the demonstrations", None),
        ("r1", "DAgger round 1", "r0"),
        ("r2", "DAgger round 2", "r1"),
        ("hg_r1", "HG-DAgger round 1", "r0"),
        ("more", "the demonstrations, as many more steps as a round", "r0"))
# replay label of the closed-loop policy (Ta 8) -> (its name, the open-loop label of the same objective, model folder)
POLICIES = {"fm_cnn/euler-1/Ta-8": ("FM-1", "fm_cnn/euler-1", "fm_cnn"),
            "dp_cnn/ddpm-16/Ta-8": ("DP-16", "dp_cnn/ddpm-16", "dp_cnn"),
            "bc_cnn/Ta-8": ("BC", "bc_cnn", "bc_cnn")}


def merged(*details: dict) -> dict:
    """One replay's details from several (the pair's and BC's replays of the same arm and scenes)."""
    out: dict = {"per_episode": {}, "diagnostics": {}, "training": {}}
    for d in details:
        for key in out:
            out[key].update(d.get(key, {}))
    return out


# the rollouts each DAgger arm was trained on (every round's so far), and the operator's arm's
EXPERT_ROLLOUTS = {"r1": ("dagger_rollout_r1",), "r2": ("dagger_rollout_r1", "dagger_rollout_r2")}
OPERATOR_ROLLOUTS = {"hg_r1": "hg_rollout_r1"}


def labelled(arm: str, model: str, rollouts: dict[str, dict]) -> str:
    """The states labelled for this arm's training: re-plans the expert labelled (DAgger: every one of the rounds'
    rollouts) or the operator drove (HG-DAgger), with the operator's seconds."""
    if arm in EXPERT_ROLLOUTS:
        found = [rollouts.get(f"{r}_{model}") for r in EXPERT_ROLLOUTS[arm]]
        return "-" if None in found else f"{sum(int(s['plans']) for s in found if s):,} re-plans (expert)"
    if arm in OPERATOR_ROLLOUTS:
        s = rollouts.get(f"{OPERATOR_ROLLOUTS[arm]}_{model}")
        return f"{s['operator_plans']:,} of {s['plans']:,} re-plans (operator, {s['operator_s']:.0f} s)" if s else "-"
    return "0"


def arm_row(name: str, arm: str, label: str, det: dict, prev: dict | None, open_loop: dict,
            rollouts: dict[str, dict]) -> str:
    policy, open_label, model = POLICIES[label]
    per, diag = det["per_episode"][label], det.get("diagnostics", {}).get(label, {})
    scenes = sorted(per)
    ok = [per[s] for s in scenes]

    def versus(other: dict | None, other_label: str) -> str:
        if other is None or other_label not in other["per_episode"]:
            return "-"
        theirs = other["per_episode"][other_label]
        if not set(scenes) <= set(theirs):
            return "-"
        ref = [theirs[s] for s in scenes]
        pair = paired_success(ok, ref)
        return f"{100 * (sum(ok) - sum(ref)) / len(ok):+.1f} (p = {pair.p_value:.2f})"

    d = [diag.get(s, {}) for s in scenes]
    replans = sum(x.get("replans", 0) for x in d)
    off = sum(x.get("replans_off_path", 0) for x in d)
    ratios = [x["plan_ratio_off_path"] for x in d if x.get("plan_ratio_off_path") is not None]
    force = sum(x.get("peak_force_n", 0.0) > FORCE_LIMIT_N for x in d)
    peak = max((x.get("peak_force_n", 0.0) for x in d), default=float("nan"))
    conv = {True: "yes", False: "no"}.get(det.get("training", {}).get(model, {}).get("converged"), "-")
    return (f"| {policy} | {name} | {labelled(arm, model, rollouts)} | {rate_cell(sum(ok), len(ok))} | "
            f"{versus(prev, label)} | {versus(open_loop, open_label)} | "
            f"{100 * off / replans:.0f} % | {np.median(ratios) if ratios else float('nan'):.2f} | "
            f"{force} (max {peak:.0f} N) | {conv} |")


def dagger_lines(arms: dict[str, dict], open_loop: dict, rollouts: dict[str, dict], person: str = "still") -> list[str]:
    """The rounds' table for one world: a row per policy and arm present in `arms` (arm -> replay details)."""
    lines = ["| policy | arm | labelled for training | success % [95 %] | vs the arm before (pts, p) | "
             "vs open loop (pts, p) | re-plans off the path | plan / demo there | over 20 N (the highest peak) | "
             "converged |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    n = 0
    for label in POLICIES:
        for arm, name, before in ARMS:
            det = arms.get(arm)
            if det is None or label not in det["per_episode"]:
                continue
            n = len(det["per_episode"][label])
            lines.append(arm_row(name, arm, label, det, arms.get(before) if before else None, open_loop, rollouts))
    if n == 0:
        return []
    lines += ["", f"Closed loop, Ta 8 of 16 waypoints at 10 Hz, on the same {n} fresh scenes in every row, the person "
              f"{person}. Success with Wilson's 95 % interval; against the arm the round went on from and against "
              "the same objective's first-frame policy open loop on the same scenes: points and McNemar's exact p on "
              "the paired scenes. Off the path: the share of re-plans whose anchor was more than 2 cm from the "
              "demonstrated path; plan / demo there: the median ratio of a plan's path length off the path to the "
              f"demonstration's over the same time. Force: rollouts over {FORCE_LIMIT_N:g} N on the person. "
              "Converged: the 2 % rule on the arm's own training (validation over demonstrations and rollouts "
              "alike)."]
    return lines


FIT_ARMS = ("round 0", "DAgger round 1", "DAgger round 2", "control")  # pipelines/closed_loop/dagger_fit.py
FIT_TRAINED_ON = {"round 0": "demonstrations", "DAgger round 1": "+ round 1's rollouts",
                  "DAgger round 2": "+ rounds 1 and 2's rollouts", "control": "demonstrations"}


def fit_lines(fits: dict[str, dict]) -> list[str]:
    """How each arm's policy plans at the rollouts' states against the expert's labels (dagger_fit.py), one row
    per objective and arm: the error on the demonstrations' test windows, on round 1's rollouts (what round 1
    trained on) and on round 2's (states the round-1 policy reached, which round 1 never trained on), on and off
    the path, and the plans' length against the labels' off the path."""
    lines = ["| policy | arm | trained on | demo test (cm) | round 1's rollouts: on / off the path (cm) | "
             "round 2's rollouts: on / off the path (cm) | plan / label length off the path (round 2's) |",
             "| --- | --- | --- | ---: | ---: | ---: | ---: |"]
    cm = lambda v: "-" if v is None else f"{v:.1f}"  # noqa: E731
    name = {"fm_cnn": "FM-1", "dp_cnn": "DP-16", "bc_cnn": "BC"}
    for model in ("fm_cnn", "dp_cnn", "bc_cnn"):
        fit = fits.get(model, {})
        for arm in FIT_ARMS:
            if arm not in fit:
                continue
            sets = fit[arm]
            demo, r1, r2 = (sets.get(k, {}) for k in ("demo_test", "rollouts_r1", "rollouts_r2"))
            ratio = r2.get("plan_over_label_length", {}).get("off")
            lines.append(f"| {name[model]} | {arm} | {FIT_TRAINED_ON[arm]} | {cm(demo.get('error_cm'))} | "
                         f"{cm(r1.get('error_on_path_cm'))} / {cm(r1.get('error_off_path_cm'))} | "
                         f"{cm(r2.get('error_on_path_cm'))} / {cm(r2.get('error_off_path_cm'))} | "
                         f"{'-' if ratio is None else f'{ratio:.2f}'} |")
    if len(lines) == 2:
        return []
    first = next(iter(fits.values()))
    return lines + ["", f"Each policy's plan (its default sampler, fixed noise) against the expert's label at the same "
                    f"window, in the training windows' own format: the mean distance over the 16 waypoints, at "
                    f"{first['per_episode']} evenly spaced frames of every episode ({first['sets'].get('demo_test')} "
                    f"test demonstrations, {first['sets'].get('rollouts_r1')} rollouts per round, on the training "
                    "split's scenes); off the path: the anchor more than 2 cm from the demonstrated path. "
                    "pipelines/closed_loop/dagger_fit.py."]

"""The closed-loop trio trained on demonstrations with recoveries (record --recoveries, train --target recovery)
against the same trio trained on the undisturbed demonstrator's commands: success at each Ta on the same fresh
scenes, paired per scene, beside the first-frame twin open loop, with how often each re-planned off the path and
pushed the person."""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from ..dataset import schema
from ..dataset.loader import command_series, reference_series
from ..geometry.transforms import path_at
from ..sim.tasks import FORCE_LIMIT_N
from .stats import paired_success, rate_cell

OPEN_LOOP_OF = {"fm_cnn": "fm_cnn/euler-1", "dp_cnn": "dp_cnn/ddpm-16", "bc_cnn": "bc_cnn"}


def _share(diags: dict, part: str, whole: str | None = None) -> str:
    """Re-plans off the path over all re-plans (part, whole), or the share of scenes over the force limit."""
    if whole is not None:
        total = sum(d.get(whole, 0) for d in diags.values())
        return f"{100 * sum(d.get(part, 0) for d in diags.values()) / total:.0f} %" if total else "-"
    return f"{100 * sum(d.get(part, 0.0) > FORCE_LIMIT_N for d in diags.values()) / max(len(diags), 1):.1f} %"


def _converged(details: dict, policy: str) -> str:
    """Whether the policy's model met the convergence rule in training, as replay recorded it."""
    flag = details.get("training", {}).get(policy.split("/")[0], {}).get("converged")
    return {True: "yes", False: "no"}.get(flag, "-")


def _paired(first: dict, second: dict, names: list[str]) -> str:
    a, b = [bool(first[n]) for n in names], [bool(second[n]) for n in names]
    return f"{100 * (sum(a) - sum(b)) / max(len(names), 1):+.1f} points ({paired_success(a, b)})"


def recoveries_lines(worlds: list[tuple[str, dict, dict, dict]]) -> list[str]:
    """worlds: (the person still or moving, the path-trained trio's replay details, the recovery-trained trio's,
    the first-frame trio's open-loop replay on the same scenes). One row per policy and Ta both replayed."""
    lines = ["| closed-loop policy | person | Ta | trained on the path | with recoveries | recoveries - path "
             "(discordant, McNemar) | open loop, first frame | recoveries - open loop (discordant, McNemar) | "
             f"re-plans off the path: path / recoveries | force > {FORCE_LIMIT_N:.0f} N: path / recoveries | "
             "converged (2 % rule): path / recoveries |",
             "| --- | --- | ---: | ---: | ---: | --- | ---: | --- | --- | --- | --- |"]
    for world, path, rec, open_loop in worlds:
        order = sorted(rec.get("per_episode", {}), key=lambda label: (label.rsplit("/Ta-", 1)[0],
                                                                      int(label.rsplit("/Ta-", 1)[1])))
        for label in order:
            mine, theirs = rec["per_episode"][label], path.get("per_episode", {}).get(label)
            head, ta = label.rsplit("/Ta-", 1)
            if theirs is None or head.startswith("oracle"):
                continue
            names = sorted(n for n in mine if n in theirs)
            ol = open_loop.get("per_episode", {}).get(OPEN_LOOP_OF.get(head.split("/")[0], ""), {})
            both = [n for n in names if n in ol]
            dp, dr = path.get("diagnostics", {}).get(label, {}), rec.get("diagnostics", {}).get(label, {})
            lines.append(
                f"| {head} | {world} | {ta} | {rate_cell(sum(map(bool, (theirs[n] for n in names))), len(names))} | "
                f"{rate_cell(sum(map(bool, (mine[n] for n in names))), len(names))} | {_paired(mine, theirs, names)} | "
                + (f"{rate_cell(sum(map(bool, (ol[n] for n in both))), len(both))} | {_paired(mine, ol, both)} | "
                   if len(both) == len(names) and both else "- | - | ")
                + f"{_share(dp, 'replans_off_path', 'replans')} / {_share(dr, 'replans_off_path', 'replans')} | "
                f"{_share(dp, 'peak_force_n')} / {_share(dr, 'peak_force_n')} | "
                f"{_converged(path, head)} / {_converged(rec, head)} |")
    return lines if len(lines) > 2 else []


OFF_M = 0.01  # a command sample this far from the reference counts as off the path


def recording_disturbances(index: str | Path, names: list[str]) -> dict:
    """How far a recording's demonstrator was pushed off its path (record --recoveries): per episode, the largest
    distance of its command from its reference stream, and the share of command samples more than OFF_M off.
    Reads one episode at a time; an episode without a reference stream counts as undisturbed (offset 0)."""
    largest, off, samples, disturbed = [], 0, 0, 0
    with h5py.File(index, "r") as f:
        for name in names:
            g = f[schema.EPISODES][name]
            t, cmd = command_series(g, f"{index}: {name}")
            ref_t, ref = reference_series(g, f"{index}: {name}")
            gap = np.linalg.norm(cmd - path_at(t, ref_t, ref[:, :3]), axis=1)
            largest.append(float(gap.max()))
            off, samples = off + int((gap > OFF_M).sum()), samples + len(gap)
            disturbed += bool(gap.max() > OFF_M)
    q = np.percentile(largest, [0, 50, 100]) if largest else np.zeros(3)
    return {"episodes": len(names), "disturbed": disturbed, "largest_offset_m": [round(float(v), 4) for v in q],
            "samples_off": round(off / max(samples, 1), 4), "off_m": OFF_M}


def recording_line(rec: dict) -> str:
    """One sentence on recording_disturbances' figures, for the table's preamble."""
    lo, med, hi = (100 * v for v in rec["largest_offset_m"])
    return (f"The recording with recoveries: {rec['disturbed']} of {rec['episodes']} demonstrations pushed more than "
            f"{100 * rec['off_m']:.0f} cm off their path, the largest offset per demonstration {med:.1f} cm median "
            f"({lo:.1f}-{hi:.1f}), {100 * rec['samples_off']:.1f} % of command samples more than "
            f"{100 * rec['off_m']:.0f} cm off.")

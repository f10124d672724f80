"""Which policy to put on the robot: a stated rule applied to paired outcomes, with anytime-valid tests
(adlpipe.evaluation.sequential), so the same rule decides after a fixed set of scenes, after every batch of a
sequential replay, and after every trial on a real robot.

The rule, in order:
1. Safety. An episode is unsafe when the contact force on the person exceeded the limit (20 N, the task predicate's).
   A policy is out when its unsafe rate is resolved above another policy's (a paired one-sided test).
2. Success. Among the policies left, a policy is out when another is resolved better. The others stay candidates.
3. Latency. The recommendation is the fastest candidate resolved "not worse than every other candidate by more than
   the margin" (a one-sided paired non-inferiority test, so equivalence for the purpose is a finding, not only a
   difference); a single candidate left is recommended as it stands. When no candidate is, the decision is
   "undecided", with about how many more scenes (or trials) would decide it if the observed differences held.

Error rates: each family of comparisons (safety, success) holds its family-wise error at alpha, Bonferroni over the
pairs of policies (adlpipe.evaluation.sequential.PairedComparison runs each pair at that level).
"""

from __future__ import annotations

import math
import re
import textwrap
from collections.abc import Callable
from dataclasses import dataclass

from ..sim.tasks import FORCE_LIMIT_N
from .latency import POLICY_NAMES
from .sequential import BettingTest, PairedComparison


@dataclass(frozen=True)
class Rule:
    margin: float = 0.05  # non-inferiority margin on the success rate (5 points)
    alpha: float = 0.05  # family-wise error rate of each step's comparisons

    def describe(self) -> str:
        return (f"safety first (force on the person > {FORCE_LIMIT_N:.0f} N), then success with a "
                f"{100 * self.margin:.0f}-point non-inferiority margin, then latency; anytime-valid paired tests "
                f"(testing by betting), family-wise error {100 * self.alpha:.0f} % per step")


def scene_order(names: list[str]) -> list[str]:
    """The order a paired sequence is read in, fixed before any outcome: scenes by their index first (the i-th
    scene of every task, then the (i+1)-th), so a sequence that stops early has seen every task alike."""
    def key(name: str) -> tuple[int, str]:
        m = re.search(r"(\d+)$", name)
        return (int(m.group(1)) if m else 0, name)
    return sorted(names, key=key)


def _pairs(policies: list[str], outcomes: dict[str, dict[str, float]], margin: float,
           alpha: float) -> dict[tuple[str, str], PairedComparison]:
    """Every pair's comparison on the scenes (or trials) both ran, in scene_order."""
    k = max(1, math.comb(len(policies), 2))
    out = {}
    for i, a in enumerate(policies):
        for b in policies[i + 1:]:
            pc = PairedComparison(a, b, margin, alpha / k)
            for name in scene_order(sorted(set(outcomes[a]) & set(outcomes[b]))):
                pc.update(outcomes[a][name], outcomes[b][name])
            out[(a, b)] = pc
    return out


def _pair(pairs: dict, a: str, b: str) -> PairedComparison:
    return pairs[(a, b)] if (a, b) in pairs else pairs[(b, a)]


def _screen(members: list[str], counts: dict[str, tuple[int, int]], lines: list[str],
            beaten: Callable[[str, str], BettingTest], kept: str, out: str) -> dict[str, list[str]]:
    """One step of the rule: each member out when beaten(p, q) (the test that p loses to q) is rejected for some
    q, with a line of its count and evidence; returns member -> the members it lost to."""
    lost: dict[str, list[str]] = {}
    for p in members:
        by = [q for q in members if q != p and beaten(p, q).rejected]
        k, m = counts[p]
        verdict = kept
        if by:
            lost[p] = by
            verdict = f"**out**: {out.format(', '.join(by))} ({_e(beaten(p, by[0]))})"
        lines.append(f"   - {p}: {k} of {m} ({100 * k / max(m, 1):.1f} %), {verdict}")
    return lost


def _e(test) -> str:  # noqa: ANN001 - BettingTest
    return f"e = {math.exp(float(test.peak)):.3g} of {1 / test.alpha:.0f} needed"


def decide(success: dict[str, dict[str, bool]], peak_force: dict[str, dict[str, float]],
           latency_ms: dict[str, float | None], rule: Rule = Rule(),  # noqa: B008 - frozen dataclass
           unit: str = "scenes") -> dict:
    """The rule applied to per-scene outcomes (policy -> scene -> success / peak force in N; a scene without a
    force is safe), each pair of policies compared on the scenes both ran. Returns the recommendation (None:
    undecided), the status and each step's evidence as lines."""
    policies = list(success)
    n = max((len(v) for v in success.values()), default=0)
    unsafe = {p: {s: float(peak_force.get(p, {}).get(s, 0.0) > FORCE_LIMIT_N) for s in success[p]} for p in policies}
    ok = {p: {s: float(v) for s, v in success[p].items()} for p in policies}
    lines = [f"Rule: {rule.describe()}; each pair compared on the {unit} both ran (up to {n}), read in a fixed "
             "order.", ""]
    if len(policies) < 2 or n == 0:
        only = policies[0] if len(policies) == 1 and n else None
        return {"recommended": only, "status": "decided" if only else "undecided", "n": n, "lines": lines,
                "needs": None, "rule": rule.__dict__}

    safety = _pairs(policies, unsafe, 0.0, rule.alpha)  # a policy is out when it is resolved the more unsafe
    succ = _pairs(policies, ok, rule.margin, rule.alpha)  # ... or when another is resolved better
    return apply_rule(policies, n, _counts(unsafe), _counts(ok), safety, succ, latency_ms, rule, unit, lines)


def _counts(values: dict[str, dict[str, float]]) -> dict[str, tuple[int, int]]:
    return {p: (int(sum(v.values())), len(v)) for p, v in values.items()}


def apply_rule(policies: list[str], n: int, unsafe: dict[str, tuple[int, int]], ok: dict[str, tuple[int, int]],
               safety: dict[tuple[str, str], PairedComparison], succ: dict[tuple[str, str], PairedComparison],
               latency_ms: dict[str, float | None], rule: Rule, unit: str, lines: list[str]) -> dict:
    """The rule's steps on each policy's counts ((unsafe or successful, of how many)) and every pair's tests, built
    at once (decide) or trial by trial (adlpipe.evaluation.trials.TrialSeries)."""
    lines.append(f"1. Safety ({unit} with force on the person above the limit):")
    out_safety = _screen(policies, unsafe, lines, lambda p, q: _pair(safety, p, q).test_of(p, "better"),
                         "in", "resolved above {}")
    safe = [p for p in policies if p not in out_safety]
    lines.append(f"2. Success (paired, the same {unit}):")
    out_success = _screen(safe, ok, lines, lambda p, q: _pair(succ, p, q).test_of(q, "better"), "candidate",
                          "{} resolved better")
    candidates = [p for p in safe if p not in out_success]

    by_speed = sorted(candidates, key=lambda p: (latency_ms.get(p) is None, latency_ms.get(p) or 0.0,
                                                 -ok[p][0] / max(ok[p][1], 1)))
    lines.append("3. Latency among the candidates: " + ", ".join(
        f"{p} {latency_ms[p]:.1f} ms" if latency_ms.get(p) is not None else f"{p} (not measured)" for p in by_speed))
    recommended, needs = None, None
    for r in by_speed:
        others = [c for c in candidates if c != r]
        if all(_pair(succ, r, c).not_worse(r) for c in others):
            recommended = r
            break
    if recommended is not None:
        others = [c for c in candidates if c != recommended]
        why = ("the only candidate left" if not others else
               "not worse than " + ", ".join(f"{c} by more than {100 * rule.margin:.0f} points "
                                             f"({_e(_pair(succ, recommended, c).test_of(recommended, 'not_worse'))})"
                                             for c in others) + ", and the fastest such")
        lines += ["", f"**Recommended: {recommended}** ({why})."]
    else:
        needs = _needs(by_speed, succ)
        lines += ["", f"**Undecided** after {n} {unit}: no candidate is yet shown not worse than every other by more "
                  f"than {100 * rule.margin:.0f} points, and none better. "
                  + (f"About {needs} more {unit} would decide it if the observed differences held."
                     if needs else f"The observed differences point no way: more {unit} may not decide it; a wider "
                     "margin or more seeds would.")]
    return {"recommended": recommended, "status": "decided" if recommended else "undecided", "n": n,
            "needs": needs, "out_safety": out_safety, "out_success": out_success, "candidates": candidates,
            "lines": lines, "rule": rule.__dict__}


def _needs(by_speed: list[str], succ: dict) -> int | None:
    """The fewest more scenes after which some candidate (fastest first) would be resolved not worse than all the
    others or some other resolved better than it, if every observed difference held."""
    best: int | None = None
    for r in by_speed:
        worst: int | None = 0
        for c in by_speed:
            if c == r:
                continue
            pc = _pair(succ, r, c)
            ways = [x for x in (pc.test_of(r, "not_worse").more_needed(), pc.test_of(c, "better").more_needed())
                    if x is not None]
            if not ways:
                worst = None
                break
            worst = max(worst or 0, min(ways))
        if worst is not None and (best is None or worst < best):
            best = worst
    return best


def policies_of(ev: dict) -> dict[str, float | None]:
    """The policies the rule chooses between: each evaluated model with its default sampler (replay's label), with
    its median latency in ms; the blind baseline is a floor, not a candidate."""
    from ..policy.blind import BLIND
    from .tables import default_row, replay_label

    out = {}
    for model in ev.get("models", {}):
        row = default_row(ev, model)
        if model != BLIND and row is not None:
            out[replay_label(model, row)] = row.get("ms")
    return out


def decide_replay(ev: dict, rp: dict, rule: Rule = Rule()) -> dict | None:  # noqa: B008 - frozen dataclass
    """The rule on a replay's outcomes (replay details) with the latencies of evaluate's details; None when fewer
    than two of the evaluated policies were replayed."""
    latency = {p: ms for p, ms in policies_of(ev).items() if p in rp.get("per_episode", {})}
    if len(latency) < 2:
        return None
    force = {p: {s: d.get("peak_force_n", 0.0) for s, d in rp.get("diagnostics", {}).get(p, {}).items()}
             for p in latency}
    return decide({p: rp["per_episode"][p] for p in latency}, force, latency, rule)


SHORT_NAMES = {**POLICY_NAMES, "bc_cnn": "BC"}
MEANING = {"FM-1": "flow matching, one Euler step", "DP-16": "Diffusion Policy, 16 DDPM steps",
           "BC": "behaviour cloning"}


def decision_lines(ev: dict, rp: dict) -> list[str]:
    """README's paragraph on a committed default run's decision: the rule re-applied to its replay and evaluate
    details (the recommendation, when it was decided, safety, each candidate's success and latency)."""
    rule = Rule(**rp.get("sequential", {}).get("rule", {}))
    got = decide_replay(ev, rp, rule)
    if got is None:
        return []
    name = {p: SHORT_NAMES.get(p, p) for p in rp["per_episode"]}
    rate = {p: 100 * sum(v.values()) / max(len(v), 1) for p, v in rp["per_episode"].items()}
    ms = {p: m for p, m in policies_of(ev).items() if p in name}
    looks = rp.get("sequential", {}).get("looks", [])
    n = got["n"]
    when = f"at {n} scenes"
    if looks:
        early = [str(look["scenes"]) for look in looks[:-1]]
        tasks = len(set(rp.get("tasks", {}).values()))
        capped = tasks > 0 and rp["sequential"]["scenes"] >= rp["sequential"]["cap_per_task"] * tasks
        when = f"after {n} scenes" + (", its cap" if capped else "") + \
            (f"; undecided at {', '.join(early[:-1])}{' and ' if len(early) > 1 else ''}{early[-1]}" if early else "")
    out_safety = got.get("out_safety", {})
    safety = ("no policy was out on safety" if not out_safety else
              f"{', '.join(name[p] for p in out_safety)} out on safety")
    pct = lambda p: f"{name[p]} ({rate[p]:.1f} %)".replace(".0 %", " %")  # noqa: E731
    r = got["recommended"]
    if r is None:
        return textwrap.wrap(f"**The default run is undecided** after {n} fresh scenes ({safety}): "
                             + ", ".join(pct(p) for p in name) + ".", 115, break_on_hyphens=False)
    others = [c for c in got["candidates"] if c != r]
    slowest = max(others, key=lambda c: ms.get(c) or 0.0) if others else None
    first = f"**The default run ends in a decision: deploy {name[r]}**" + \
        (f" ({MEANING[name[r]]})" if name[r] in MEANING else "")
    rest = f". Replay ran fresh scenes until the rule was decided ({when}): {safety}" + (
        f", and {pct(r)} was resolved not worse than {' or '.join(pct(c) for c in others)} by more than "
        f"{100 * rule.margin:.0f} points" if others else f"; {pct(r)} was the only candidate left")
    speed = (f", at {ms[r]:.1f} ms per plan against {name[slowest]}'s {ms[slowest]:.1f}."
             if slowest and ms.get(r) is not None and ms.get(slowest) is not None else ".")
    return textwrap.wrap(first + rest + speed, 115, break_on_hyphens=False)

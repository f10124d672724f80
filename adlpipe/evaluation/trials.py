"""Trials on a real robot: each trial's policy and outcome, read from a CSV or from the trial's bag, and the decision
rule (adlpipe.evaluation.decision) after every trial, with the policy to run next.

The accepted forms, the same for CSVs and bags:
- success: 1/0, true/false, yes/no, y/n, success/failure (any case); in a bag also a std_msgs/Bool.
- A CSV (UTF-8, a byte-order mark allowed) has a header naming at least `policy` and `success`, and optionally
  `trial` (the order: a number on every row, each once; without the column, the row order), `force_n` (the peak
  contact force on the person, N, 0 to 1e6) and `progress` (0..1, kept for the record).
- A trial bag is a recording like any other, plus exactly one outcome on /adl/outcome: a std_msgs/String holding a
  JSON object ({"policy": "fm_cnn", "success": true, "force_n": 4.2}) or one of the success forms, or a
  std_msgs/Bool; the policy's name in the JSON or as one std_msgs/String on /adl/policy. Bags are taken in the
  order their trials ended (the outcome's log time).
- Every input is a regular file (a bag may be a rosbag2 folder) given once; a CSV is at most 64 MiB.

Trials are paired in time: each policy's k-th trial is compared with every other policy's k-th, so run them
alternating (the suggested next policy does that: the candidate with the fewest trials). The rule runs after every
trial in time linear in the trials (TrialSeries).
"""
from __future__ import annotations

import csv
import json
import math
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..bags.reader import BagSource
from ..bags.topics import OUTCOME, POLICY
from ..plumbing.errors import AdlError, read_json_object
from ..sim.tasks import FORCE_LIMIT_N
from .decision import Rule, apply_rule, policies_of
from .sequential import PairedComparison

TRUE, FALSE = {"1", "true", "yes", "y", "success"}, {"0", "false", "no", "n", "failure", "fail"}


@dataclass(frozen=True)
class Trial:
    policy: str
    success: bool
    force_n: float | None
    progress: float | None
    source: str  # where it was read: file:line or the bag


def _flag(text: str, where: str) -> bool:
    t = str(text).strip().lower()
    if t in TRUE or t in FALSE:
        return t in TRUE
    shown = repr(str(text)) if len(str(text)) <= 40 else repr(str(text)[:40]) + f" ... ({len(str(text))} characters)"
    raise AdlError(f"{where}: success {shown} is not one of 1/0, true/false, yes/no")


def _number(text: object, field: str, where: str, lo: float, hi: float) -> float | None:
    if text is None or str(text).strip() == "":
        return None
    try:
        x = float(str(text))
    except (TypeError, ValueError):
        raise AdlError(f"{where}: {field} {text!r} is not a number") from None
    if not lo <= x <= hi:
        raise AdlError(f"{where}: {field} {x} is outside [{lo}, {hi}]")
    return x


MAX_CSV_BYTES = 64 << 20  # about a million trials: more is not a trials file


def _regular(path: Path, what: str) -> None:
    """A file to read must be a regular file (a bag may be a rosbag2 folder): a FIFO would block, a device never end."""
    try:
        mode = path.stat().st_mode
    except OSError as exc:
        raise AdlError(f"{path}: cannot read it ({exc.strerror})") from None
    if not (stat.S_ISREG(mode) or (what == "bag" and stat.S_ISDIR(mode))):
        raise AdlError(f"{path}: not a regular file; a trials {what} is a file")


def read_csv(path: Path) -> list[Trial]:
    _regular(path, "CSV")
    if path.stat().st_size > MAX_CSV_BYTES:
        raise AdlError(f"{path}: {path.stat().st_size} bytes, over the {MAX_CSV_BYTES >> 20} MiB a trials CSV may be")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:  # a byte-order mark is not part of the first name
            reader = csv.DictReader(f)
            header, rows = [h.strip() for h in reader.fieldnames or []], list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise AdlError(f"{path}: cannot read it as a CSV of trials ({exc})") from None
    missing = [c for c in ("policy", "success") if c not in header]
    if missing:
        raise AdlError(f"{path}: no column {', '.join(missing)} (a trials CSV needs policy and success; "
                       f"it has {', '.join(header) or 'none'})")
    trials = []
    seen: dict[float, int] = {}
    for i, raw in enumerate(rows, start=2):
        row = {(k or "").strip(): v for k, v in raw.items()}
        where = f"{path}:{i}"
        if not (row.get("policy") or "").strip():
            raise AdlError(f"{where}: empty policy")
        order = _number(row.get("trial"), "trial", where, 0, 1e12) if "trial" in header else None
        if "trial" in header:
            if order is None:
                raise AdlError(f"{where}: empty trial number (the column orders the trials: fill it on every row, "
                               "or leave the column out to keep the row order)")
            if order in seen:
                raise AdlError(f"{where}: trial {order:g} again (first on line {seen[order]})")
            seen[order] = i
        trials.append((order if order is not None else i, Trial(
            row["policy"].strip(), _flag(row["success"], where), _number(row.get("force_n"), "force_n", where, 0, 1e6),
            _number(row.get("progress"), "progress", where, 0, 1), where)))
    return [t for _, t in sorted(trials, key=lambda x: x[0])]


def read_bag(path: Path) -> tuple[int, Trial]:
    """(the log time of its outcome in ns: when the trial ended, its trial)."""
    _regular(path, "bag")
    src = BagSource(path)
    topics = src.topics()
    if OUTCOME not in topics:
        raise AdlError(f"{path}: no {OUTCOME} topic: a trial bag carries its outcome there "
                       "(std_msgs/String JSON or std_msgs/Bool)")
    outcomes, policies, ended = [], [], 0
    for topic, t, decode in src.messages([OUTCOME] + ([POLICY] if POLICY in topics else [])):
        msg: Any = decode()
        data = getattr(msg, "data", None)
        if topic == POLICY:
            if not isinstance(data, str):
                raise AdlError(f"{path} {POLICY}: {type(data).__name__}, not a std_msgs/String naming the policy")
            policies.append(data.strip())
        else:
            if not isinstance(data, str | bool):
                raise AdlError(f"{path} {OUTCOME}: a {type(msg).__name__} holding {type(data).__name__}; the outcome "
                               "is a std_msgs/String (JSON, or true/false) or a std_msgs/Bool")
            outcomes.append(data)
            ended = t
    where = f"{path} {OUTCOME}"
    if not outcomes:
        raise AdlError(f"{where}: no message")
    if len(outcomes) > 1 or len(policies) > 1:
        topic, n = (OUTCOME, len(outcomes)) if len(outcomes) > 1 else (POLICY, len(policies))
        raise AdlError(f"{path} {topic}: {n} messages; a trial bag holds one trial")
    outcome, policy = outcomes[0], (policies[0] if policies else None)
    force = progress = None
    if isinstance(outcome, bool):
        success = outcome
    else:
        try:
            doc = json.loads(outcome)
        except (json.JSONDecodeError, RecursionError):
            doc = {"success": outcome}
        if isinstance(doc, bool | int) and not isinstance(doc, dict):  # "true", "false", "1", "0"
            doc = {"success": str(doc).lower()}
        if not isinstance(doc, dict) or "success" not in doc:
            raise AdlError(f"{where}: {outcome[:80]!r} holds no success (a JSON object with 'success', or "
                           "true/false)")
        success = _flag(doc["success"], where)
        named = doc.get("policy", policy)
        if named is not None and not isinstance(named, str):
            raise AdlError(f"{where}: policy {str(named)[:40]!r} is a {type(named).__name__}, not a name")
        policy = (named or "").strip() or policy
        force = _number(doc.get("force_n"), "force_n", where, 0, 1e6)
        progress = _number(doc.get("progress"), "progress", where, 0, 1)
    if not policy:
        raise AdlError(f"{path}: names no policy (put \"policy\" in the {OUTCOME} JSON, or a std_msgs/String on "
                       f"{POLICY})")
    return ended, Trial(policy, success, force, progress, str(path))


def read_trials(paths: list[Path]) -> list[Trial]:
    """Every trial of the CSVs (in their order) and of the bags (by recording time), CSVs first."""
    trials: list[Trial] = []
    bags = []
    seen: dict[Path, Path] = {}
    for p in paths:
        real = Path(p).resolve()
        if real in seen:
            raise AdlError(f"{p}: given twice (as {seen[real]} too); each trial counts once")
        seen[real] = Path(p)
        if p.suffix.lower() == ".csv":
            trials += read_csv(p)
        else:
            bags.append(read_bag(p))
    return trials + [t for _, t in sorted(bags, key=lambda x: x[0])]


class TrialSeries:
    """The rule after every trial, in time linear in the trials: each pair's tests are updated once per new pair of
    k-th trials (exactly the order decide reads them in), each policy's counts kept as they come. A policy first
    seen mid-series changes the number of pairs (Bonferroni), so the pairs are rebuilt then, once per policy."""

    def __init__(self, latency_ms: dict[str, float | None], rule: Rule, policies: list[str] | None = None) -> None:
        self.latency, self.rule = latency_ms, rule
        self.names: list[str] = list(dict.fromkeys(policies or []))
        self.ok: dict[str, list[float]] = {p: [] for p in self.names}
        self.unsafe: dict[str, list[float]] = {p: [] for p in self.names}
        self.sums: dict[str, list[int]] = {p: [0, 0] for p in self.names}  # successes, unsafe trials
        self._rebuild()

    def _rebuild(self) -> None:
        k = max(1, math.comb(len(self.names), 2))
        self.safety: dict[tuple[str, str], PairedComparison] = {}
        self.succ: dict[tuple[str, str], PairedComparison] = {}
        for i, a in enumerate(self.names):
            for b in self.names[i + 1:]:
                self.safety[(a, b)] = PairedComparison(a, b, 0.0, self.rule.alpha / k)
                self.succ[(a, b)] = PairedComparison(a, b, self.rule.margin, self.rule.alpha / k)
                for j in range(min(len(self.ok[a]), len(self.ok[b]))):
                    self._update(a, b, j)

    def _update(self, a: str, b: str, j: int) -> None:
        self.safety[(a, b)].update(self.unsafe[a][j], self.unsafe[b][j])
        self.succ[(a, b)].update(self.ok[a][j], self.ok[b][j])

    def add(self, trial: Trial) -> None:
        p = trial.policy
        if p not in self.ok:
            self.names.append(p)
            self.ok[p], self.unsafe[p], self.sums[p] = [], [], [0, 0]
            self._rebuild()
        self.ok[p].append(float(trial.success))
        self.unsafe[p].append(float(trial.force_n is not None and trial.force_n > FORCE_LIMIT_N))
        self.sums[p][0] += int(trial.success)
        self.sums[p][1] += int(self.unsafe[p][-1])
        j = len(self.ok[p]) - 1
        for q in self.names:
            if q != p and len(self.ok[q]) > j:  # the pair's j-th trials are both in: the next in its order
                a, b = (p, q) if self.names.index(p) < self.names.index(q) else (q, p)
                self._update(a, b, j)

    def decision(self) -> tuple[dict, str | None]:
        """The rule on the trials so far, and the policy to run next (None once decided): the candidate with the
        fewest trials, in the order policies first appeared."""
        names = self.names
        n = max((len(v) for v in self.ok.values()), default=0)
        lines = [f"Rule: {self.rule.describe()}; each pair compared on the trials both ran (up to {n}), read in a "
                 "fixed order.", ""]
        latency = {p: self.latency.get(p) for p in names}
        if len(names) < 2 or n == 0:
            only = names[0] if len(names) == 1 and n else None
            decision = {"recommended": only, "status": "decided" if only else "undecided", "n": n, "lines": lines,
                        "needs": None, "rule": self.rule.__dict__}
        else:
            counts = {p: (self.sums[p][0], len(self.ok[p])) for p in names}
            unsafe = {p: (self.sums[p][1], len(self.ok[p])) for p in names}
            decision = apply_rule(names, n, unsafe, counts, self.safety, self.succ, latency, self.rule, "trials",
                                  lines)
        if decision["status"] == "decided" and len(names) > 1:
            return decision, None
        candidates: list[str] = decision.get("candidates") or []  # type: ignore[assignment]
        left = candidates or names
        return decision, None if not left else min(left, key=lambda p: (len(self.ok[p]), names.index(p)))


@dataclass(frozen=True)
class TrialsConfig:
    """What `adlpipe trials` was asked (its options, one field each: `adlpipe trials --help` says what each does)."""

    inputs: list[Path]
    policies: list[str] | None = None
    eval_details: Path | None = None  # evaluate's details: each policy's latency
    latency: list[str] | None = None  # POLICY=MS, over eval_details'
    margin: float = 0.05
    alpha: float = 0.05


def latencies(c: TrialsConfig) -> dict[str, float | None]:
    """Each policy's latency in ms: evaluate's details, then --latency POLICY=MS over them."""
    out: dict[str, float | None] = dict(policies_of(read_json_object(c.eval_details, "evaluate details", "models"))
                                        if c.eval_details else {})
    for item in c.latency or []:
        name, _, ms = item.partition("=")
        try:
            value = float(ms)
        except ValueError:
            raise AdlError(f"--latency {item!r}: expected POLICY=MS, e.g. fm_cnn=3.5") from None
        if not name.strip() or not math.isfinite(value) or value < 0:
            raise AdlError(f"--latency {item!r}: expected POLICY=MS with a policy name and a finite ms >= 0")
        out[name.strip()] = value
    return out


def check_names(c: TrialsConfig, trials: list[Trial]) -> None:
    """--policies without empty names, --latency only for policies under trial."""
    if c.policies and not all(p.strip() for p in c.policies):
        raise AdlError("--policies: an empty policy name")
    known = set(c.policies or []) | {t.policy for t in trials}
    unknown = [p for p in (item.partition("=")[0].strip() for item in c.latency or []) if p not in known]
    if unknown:
        raise AdlError(f"--latency {unknown[0]}: no such policy among the trials ({', '.join(sorted(known))})")


def run_trials(c: TrialsConfig) -> tuple[list[str], dict]:
    """The rule after every trial, in the order the trials were run, until it decides: what to print (a line per
    trial read, then the decision's lines) and the decision as a document (`next`: the policy to run next, None
    once decided)."""
    trials = read_trials(c.inputs)
    if not trials:
        raise AdlError(f"{', '.join(map(str, c.inputs))}: no trials")
    latency = latencies(c)
    check_names(c, trials)
    decision: dict = {}
    nxt: str | None = None
    said = []
    series = TrialSeries(latency, Rule(c.margin, c.alpha), c.policies)  # updated trial by trial: linear in the trials
    for i, t in enumerate(trials, start=1):
        series.add(t)
        decision, nxt = series.decision()
        what = (f"stop: {decision['recommended']}" if nxt is None else f"continue: run {nxt} next")
        said.append(f"trial {i} ({t.policy}: {'success' if t.success else 'failure'}"
                    + (f", {t.force_n:.1f} N" if t.force_n is not None else "") + f"): {what}")
        if nxt is None:
            if i < len(trials):
                said.append(f"decided after trial {i}; the {len(trials) - i} later trial(s) are not needed for it")
            break
    said += decision["lines"]
    return said, {**{k: v for k, v in decision.items() if k != "lines"}, "next": nxt, "trials": len(trials)}

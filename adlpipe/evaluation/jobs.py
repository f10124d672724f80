"""Running replay's jobs in worker processes, resumable through a journal, and their success rates."""

from __future__ import annotations

import sys
from collections import Counter, defaultdict

import numpy as np
from tqdm import tqdm

from ..plumbing.journal import Journal, Section
from ..plumbing.runtime import Placement
from ..plumbing.workers import stoppable_pool
from .stats import success_interval


def run_jobs(worker, jobs: list[tuple], workers: int, placement: Placement,  # noqa: ANN001
             journal: Journal | Section | None = None) -> tuple[dict, dict, dict]:
    """(label -> task -> outcomes, label -> scene -> success, label -> scene -> diagnosis). Each label's outcomes
    go into the journal as soon as its last job is in; a label the journal holds is not run again."""
    order = list(dict.fromkeys(job[0] for job in jobs))
    expected = Counter(job[0] for job in jobs)
    done: dict = journal.done if journal else {}
    outcomes: dict[str, list] = {label: list(done[label]) for label in order if label in done}
    todo = [job for job in jobs if job[0] not in outcomes]
    # CUDA cannot be used in a forked child of a process that has used it: closed-loop workers on a GPU are spawned.
    # A pool that stops at once on Ctrl-C (an executor would wait for every job already queued to its workers).
    context = "spawn" if placement.device.type == "cuda" else "fork"
    with stoppable_pool(max(1, workers), context=context) as pool:
        for label, name, task, ok, diag in tqdm(pool.imap(worker, todo, chunksize=4), total=len(todo),
                                                desc="replay", unit="ep", file=sys.stderr, disable=None):
            outcomes.setdefault(label, []).append([name, task, bool(ok), diag])
            if journal and len(outcomes[label]) == expected[label]:
                journal.add(label, outcomes[label])
    wins: dict[str, dict[str, list[bool]]] = defaultdict(lambda: defaultdict(list))
    per_episode: dict[str, dict[str, bool]] = defaultdict(dict)
    diagnostics: dict[str, dict[str, dict]] = defaultdict(dict)
    for label in order:  # the jobs' order, resumed or not
        for name, task, ok, diag in outcomes[label]:
            wins[label][task].append(ok)
            per_episode[label][name] = ok
            if diag:
                diagnostics[label][name] = diag
    return wins, per_episode, diagnostics


def success_summary(wins: dict[str, dict[str, list[bool]]]) -> dict[str, dict]:
    result = {}
    for label, per in wins.items():
        every = [o for v in per.values() for o in v]
        result[label] = {"overall": float(np.mean(every)), "n": len(every),
                         "interval": list(success_interval(sum(every), len(every))),
                         "per_task": {t: float(np.mean(v)) for t, v in sorted(per.items())},
                         "per_task_n": {t: len(v) for t, v in sorted(per.items())}}
    return result

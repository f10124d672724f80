"""Every trial a bag: a closed-loop rollout written as an MCAP bag with the real writer, as a demonstration is, plus
its plans (/adl/plan, nav_msgs/Path per re-plan), the policy (/adl/policy) and the outcome (/adl/outcome, JSON), so
that `adlpipe ingest` keeps it as data and `adlpipe trials` decides from it (adlpipe.evaluation.trials)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from ..bags import messages as M
from ..bags.topics import OUTCOME, POLICY


def trial_bag_path(out: Path, index: int, policy: str, scene: str) -> Path:
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", f"{policy}_{scene}").strip("_")
    return out / f"trial_{index:05d}_{safe}.mcap"


def write_trial_bag(st: object, out: Path, policy: str, scene: str, index: int, success: bool,
                    force_n: float) -> Path:
    """Write the rollout `st` (adlpipe.sim.episode.Streams, filled by the closed-loop executor) as trial `index`:
    its clock starts index * 100 s after the recorder's base time, so the trials are read in this order."""
    from ..sim.recording import write_episode_bag

    out.mkdir(parents=True, exist_ok=True)
    doc = json.dumps({"policy": policy, "success": bool(success), "force_n": round(float(force_n), 3)})
    return write_episode_bag(st, trial_bag_path(out, index, policy, scene), "mcap", "raw", "32FC1", index,
                             outcome=[(POLICY, M.STRING, policy), (OUTCOME, M.STRING, doc)])

"""Deployment: the public planning API (planner), the policy server (server, `adlpipe serve`), its torch-free
robot-side client (client, wire) and trial bags (trial_bags).

    from adlpipe.deploy import Observation, Planner          # torch: plan in-process
    from adlpipe.deploy.client import PolicyClient          # no torch: plan through `adlpipe serve`

The package imports its torch parts lazily, so that the client runs on a robot's computer without torch.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Observation", "Plan", "Planner", "PlannerSpec"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from . import planner

        return getattr(planner, name)
    raise AttributeError(f"module 'adlpipe.deploy' has no attribute {name!r}")

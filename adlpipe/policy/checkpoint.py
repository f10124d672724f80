"""Checkpoints: written atomically, read with torch.load(weights_only=True) (never unpickling code from a file),
and a trained policy loaded for inference without importing the training loop."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import torch

from ..plumbing.atomic import atomic_path
from ..plumbing.errors import AdlError
from ..plumbing.runtime import Placement
from .models import ModelConfig, Policy

CHECKPOINTS = {"best": "best.pt", "last": "model.pt"}  # the best validation epoch's EMA weights, and the last ones


def save_atomic(obj: dict, path: Path) -> None:
    with atomic_path(path) as tmp:
        try:
            torch.save(obj, tmp)
        except RuntimeError as exc:  # torch reports a full disk as "unexpected pos ..." from its zip writer
            if shutil.disk_usage(tmp.parent).free < (1 << 20):
                raise OSError(errno.ENOSPC, "No space left on device", str(path)) from exc
            raise


def load_checkpoint(path: Path) -> dict:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)  # never unpickle code from a user file
    except Exception as exc:  # noqa: BLE001 - a corrupt or foreign file
        raise AdlError(f"{path}: not a loadable adlpipe checkpoint ({type(exc).__name__}: {exc})") from exc


def load_policy(path: Path, placement: Placement | None = None) -> tuple[Policy, dict]:
    """An EMA policy saved by training (model.pt: the last epoch, best.pt: the best validation epoch), ready for
    inference on the placement's device (compiled if it says so), and its checkpoint metadata."""
    if not path.is_file():
        raise AdlError(f"{path}: no such checkpoint; train the model first (python -m adlpipe.train)")
    ck = load_checkpoint(path)
    if not isinstance(ck, dict) or not {"config", "ema", "stats"} <= set(ck):
        raise AdlError(f"{path}: not an adlpipe policy checkpoint (needs config, ema and stats)")
    try:
        policy = Policy(ModelConfig.from_dict(ck["config"]))
        policy.load_state_dict(ck["ema"])
    except (TypeError, ValueError, KeyError, RuntimeError, AttributeError) as exc:
        raise AdlError(f"{path}: checkpoint does not match this adlpipe's models ({type(exc).__name__})") from exc
    bad = [k for k, v in _tensors(ck["stats"]) if not torch.isfinite(v).all()]
    bad += [k for k, v in ck["ema"].items()
            if torch.is_tensor(v) and v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:  # a policy that would act on NaN: every prediction, every physics step after it, would be garbage
        raise AdlError(f"{path}: checkpoint holds non-finite values in {', '.join(sorted(bad)[:3])}"
                       f"{' and more' if len(bad) > 3 else ''}; retrain or use another checkpoint")
    placement = placement or Placement()
    policy = policy.to(placement.device).eval()
    return (policy.compile_for_inference() if placement.compile else policy), ck


def _tensors(tree: object, prefix: str = "stats") -> list[tuple[str, torch.Tensor]]:
    """Every tensor (or number array) in a nested stats dict, with its key path."""
    if isinstance(tree, dict):
        return [x for k, v in tree.items() for x in _tensors(v, f"{prefix}.{k}")]
    if torch.is_tensor(tree):
        return [(prefix, tree.float())]
    if isinstance(tree, int | float | list | tuple):
        try:
            return [(prefix, torch.as_tensor(tree, dtype=torch.float64))]
        except (TypeError, ValueError):
            return []
    return []

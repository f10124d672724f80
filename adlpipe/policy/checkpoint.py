"""Checkpoints: written atomically, read with torch.load(weights_only=True) (never unpickling code from a file),
and a trained policy loaded for inference without importing the training loop."""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import torch

from ..atomic import atomic_path
from ..errors import AdlError
from ..runtime import Placement
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
    placement = placement or Placement()
    policy = policy.to(placement.device).eval()
    return (policy.compile_for_inference() if placement.compile else policy), ck

"""Devices and precisions: a missing GPU is one line; bf16 autocast and torch.compile keep the predictions."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from adlpipe.plumbing.errors import AdlError
from adlpipe.plumbing.runtime import Placement, resolve_device
from adlpipe.policy.inference import predict
from adlpipe.policy.models import ModelConfig, Policy

TINY = dict(image_size=32, encoder_width=8, obs_dim=16, down_dims=(16, 32, 64), d_model=32, n_layers=1, n_heads=2)
no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA")


@no_cuda
@pytest.mark.parametrize("stage", ["train", "evaluate", "replay", "inspect"])
def test_asking_for_a_missing_gpu_is_one_line(stage: str, tmp_path: Path) -> None:
    from conftest import one_line_error, run_module

    args = {"train": ["--model", "fm_cnn", "--out", tmp_path / "m"], "evaluate": ["--models", tmp_path / "m"],
            "replay": ["--models", tmp_path / "m"], "inspect": ["--model", tmp_path / "m"]}[stage]
    line = one_line_error(run_module(stage, *args, "--data", tmp_path / "none.h5", "--device", "cuda:1"))
    assert "--device cuda:1: no CUDA device on this machine" in line, line
    assert not (tmp_path / "m").exists()


def test_device_names() -> None:
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(AdlError, match="not a device"):
        resolve_device("gpu0")
    with pytest.raises(AdlError, match="cpu or cuda"):
        resolve_device("meta")


def _policy(model: str) -> tuple[Policy, torch.Tensor]:
    torch.manual_seed(0)
    return Policy(ModelConfig(model=model, **TINY)).eval(), torch.randn(4, 4, 32, 32)


@pytest.mark.parametrize("model", ["fm_cnn", "dp_cnn", "bc_transformer"])
def test_bf16_autocast_predicts_what_fp32_does_to_bf16_precision(model: str) -> None:
    policy, obs = _policy(model)
    steps = 16 if model == "dp_cnn" else 1
    fp32 = predict(policy, obs, steps, None, torch.Generator().manual_seed(1), Placement())
    bf16 = predict(policy, obs, steps, None, torch.Generator().manual_seed(1), Placement(precision="bf16"))
    assert bf16.dtype == torch.float32 and torch.isfinite(bf16).all()
    err = float((bf16 - fp32).abs().max() / fp32.abs().max())
    assert 0 < err < 0.05, err  # bf16 keeps 8 bits of mantissa: about 0.4 % per operation, and it did run in bf16


def test_a_bf16_training_step_keeps_fp32_weights_and_gradients() -> None:
    from adlpipe.plumbing.runtime import autocast

    policy, obs = _policy("fm_cnn")
    policy.train()
    act = torch.rand(4, 32, 5) * 2 - 1
    with autocast(torch.device("cpu"), "bf16"):
        loss = policy.loss(obs, act, gen=torch.Generator().manual_seed(0))
    loss.backward()
    grads = [p.grad for p in policy.parameters() if p.grad is not None]
    assert torch.isfinite(loss) and grads and all(g.dtype == torch.float32 and torch.isfinite(g).all() for g in grads)


def test_compiled_inference_predicts_what_eager_inference_does() -> None:
    policy, obs = _policy("fm_cnn")
    eager = predict(policy, obs, 1, None, torch.Generator().manual_seed(1), Placement())
    policy.compile_for_inference()
    compiled = predict(policy, obs, 1, None, torch.Generator().manual_seed(1), Placement(compile=True))
    assert torch.allclose(eager, compiled, atol=1e-4), float((eager - compiled).abs().max())

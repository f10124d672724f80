"""The image encoder's options (issue V.3): spatial softmax pooling, each observation frame through the shared
encoder, and a random crop in training with the centre crop at test, each against what it promises."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from adlpipe.dataset.loader import Augment
from adlpipe.policy.models import ModelConfig, Policy
from adlpipe.policy.nets.resnet import ResNet18GN
from adlpipe.policy.nets.spatial_softmax import SpatialSoftmax

TINY = dict(encoder_width=8, obs_dim=16, down_dims=(16, 32, 64), n_obs=2, rate_hz=10.0, state_dim=4, action_dim=2,
            target="action", horizon=16)


def test_spatial_softmax_finds_a_peak_where_it_is() -> None:
    pool = SpatialSoftmax(channels=1, keypoints=1)
    with torch.no_grad():
        pool.project.weight.fill_(1.0)
        pool.project.bias.zero_()
    x = torch.zeros(2, 1, 8, 16)
    x[0, 0, 3, 10] = 50.0  # a sharp peak: its softmax is one-hot there
    x[1, 0, 7, 0] = 50.0
    xy = pool(x)
    assert xy.shape == (2, 2)
    assert torch.allclose(xy[0], torch.tensor([-1 + 2 * 10 / 15, -1 + 2 * 3 / 7]), atol=1e-4)
    assert torch.allclose(xy[1], torch.tensor([-1.0, 1.0]), atol=1e-4)
    flat = pool(torch.zeros(1, 1, 8, 16))  # no peak: the mean position, the centre
    assert torch.allclose(flat, torch.zeros(1, 2), atol=1e-6)


def test_the_encoder_pools_by_spatial_softmax_on_request() -> None:
    torch.manual_seed(0)
    enc = ResNet18GN(3, 16, width=8, pool="spatial_softmax").eval()
    assert enc.pool is not None and enc.proj.in_features == 64  # 32 keypoints x (x, y), whatever the width
    with torch.no_grad():
        out = enc(torch.randn(2, 3, 32, 32))
        keypoints = enc.pool(enc.layers(enc.stem(torch.randn(2, 3, 32, 32))))
    assert out.shape == (2, 16) and bool(keypoints.abs().le(1).all())  # expected positions lie in the image
    assert ResNet18GN(3, 16, width=8).pool is None  # today's default: global average pooling
    with pytest.raises(ValueError, match="unknown pooling"):
        ResNet18GN(3, 16, width=8, pool="max")


def test_each_frame_goes_through_the_one_shared_encoder() -> None:
    torch.manual_seed(0)
    policy = Policy(ModelConfig(model="fm_cnn", image_size=32, per_frame=True, pool="spatial_softmax", **TINY)).eval()
    assert policy.encoder.stem[0].in_channels == 4 and policy.cfg.encoder_passes == 2
    stack = torch.randn(3, 8, 32, 32)  # (B, To * C, S, S): frame 0's channels first
    features = policy.encode(stack)
    assert features.shape == (3, 32)
    assert torch.allclose(features[:, :16], policy.encoder(stack[:, :4]), atol=1e-6)
    assert torch.allclose(features[:, 16:], policy.encoder(stack[:, 4:]), atol=1e-6)
    swapped = policy.encode(torch.cat([stack[:, 4:], stack[:, :4]], dim=1))
    assert torch.allclose(swapped, torch.cat([features[:, 16:], features[:, :16]], dim=1), atol=1e-6)
    stacked = Policy(ModelConfig(model="fm_cnn", image_size=32, **TINY))  # today's: one pass over 8 channels
    assert stacked.encoder.stem[0].in_channels == 8 and stacked.cfg.encoder_passes == 1


def test_a_random_crop_in_training_is_the_centre_crop_moved_with_its_targets() -> None:
    """The loader's crop keeps real pixels (no padding) and moves the pixel targets by the window's offset from
    the centre, which is what the model sees at test: a marked pixel and its target stay together."""
    s, crop, stored = 40, 32, 80
    aug = Augment(stored, jitter=0.0, crop=crop)
    obs = np.full((4, s, s), -1.0, np.float32)
    obs[:, 17, 25] = 1.0  # a marked pixel at (u, v) = (25, 17) of the 40 px input
    target = np.array([[25 * stored / s, 17 * stored / s, 0, 0, 0]], np.float32)
    centre = (s - crop) // 2
    seen = set()
    for seed in range(20):
        out, moved = aug(obs, target, np.random.default_rng(seed), 4)
        assert out.shape == (4, crop, crop)
        v, u = (int(i) for i in np.argwhere(out[0] == 1.0)[0])
        # in the crop at (u, v); the centre crop would show it at (25 - centre, 17 - centre): the target moved by
        # the difference, in stored pixels
        assert moved[0, 0] == pytest.approx((25 + (u - (25 - centre))) * stored / s)
        assert moved[0, 1] == pytest.approx((17 + (v - (17 - centre))) * stored / s)
        seen.add((u, v))
    assert len(seen) > 10  # the window moves
    # the model centre-crops a whole image: the same feature as the centre window given directly
    torch.manual_seed(0)
    policy = Policy(ModelConfig(model="fm_cnn", image_size=s, crop=crop, **TINY)).eval()
    whole = torch.randn(2, 8, s, s)
    window = whole[..., centre:centre + crop, centre:centre + crop]
    assert torch.allclose(policy.encode(whole), policy.encode(window), atol=1e-6)

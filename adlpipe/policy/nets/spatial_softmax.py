"""Spatial softmax pooling (Levine et al. 2016; the pooling robomimic, Diffusion Policy and LeRobot put on their
ResNet-18 in place of global average pooling): each of `keypoints` learned 1x1 projections of the feature map is a
softmax over the pixels, and its expected (x, y) position is the output. Where things are survives the pooling;
with average pooling it survives only as much as the features encode it."""

from __future__ import annotations

import torch
from torch import nn


class SpatialSoftmax(nn.Module):
    """(B, C, H, W) -> (B, 2 * keypoints): the expected x and y, in [-1, 1], of each keypoint's softmax."""

    def __init__(self, channels: int, keypoints: int = 32) -> None:
        super().__init__()
        self.keypoints = keypoints
        self.project = nn.Conv2d(channels, keypoints, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, _, h, w = x.shape
        weights = self.project(x).flatten(2).softmax(dim=-1)  # (B, K, H*W)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, h, device=x.device, dtype=weights.dtype),
                                torch.linspace(-1, 1, w, device=x.device, dtype=weights.dtype), indexing="ij")
        grid = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1)  # (H*W, 2)
        return (weights @ grid).reshape(b, 2 * self.keypoints)

"""A compact U-Net heatmap detector: 128x128 RGB crop -> K heatmaps at stride 2 (64x64)."""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F


def conv_bn(cin: int, cout: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(cin, cout, 3, stride=stride, padding=1, bias=False),
        nn.BatchNorm2d(cout),
        nn.ReLU(inplace=True),
    )


class Down(nn.Sequential):
    """Halve the resolution, then refine: two 3x3 convolutions."""

    def __init__(self, cin: int, cout: int, depth: int = 2) -> None:
        super().__init__(conv_bn(cin, cout, stride=2), *[conv_bn(cout, cout) for _ in range(depth - 1)])


class Up(nn.Module):
    """Bilinear upsampling, add a 1x1-projected skip connection, one 3x3 convolution."""

    def __init__(self, cin: int, cskip: int, cout: int) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(cin, cout, 1)
        self.skip = nn.Conv2d(cskip, cout, 1)
        self.conv = conv_bn(cout, cout)

    def forward(self, x: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(self.reduce(x), size=skip.shape[-2:], mode="bilinear", align_corners=False)
        return self.conv(F.relu(x + self.skip(skip)))


class HeatmapUNet(nn.Module):
    """Encoder 64->32->16->8 (stride 2..16), decoder back to 64x64, one channel per keypoint."""

    def __init__(self, num_keypoints: int, widths: tuple[int, ...] = (16, 48, 96, 160)) -> None:
        super().__init__()
        w0, w1, w2, w3 = widths
        self.stem = Down(3, w0)  # 64x64
        self.down1 = Down(w0, w1)  # 32x32
        self.down2 = Down(w1, w2, depth=3)  # 16x16
        self.down3 = Down(w2, w3, depth=3)  # 8x8
        self.up2 = Up(w3, w2, w2)
        self.up1 = Up(w2, w1, w1)
        self.up0 = Up(w1, w0, w0)
        self.head = nn.Conv2d(w0, num_keypoints, 1)
        nn.init.normal_(self.head.weight, std=1e-3)  # start near zero: no early push that kills the ReLUs
        nn.init.zeros_(self.head.bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        s0 = self.stem(x)
        s1 = self.down1(s0)
        s2 = self.down2(s1)
        x = self.down3(s2)
        x = self.up2(x, s2)
        x = self.up1(x, s1)
        x = self.up0(x, s0)
        return self.head(x)

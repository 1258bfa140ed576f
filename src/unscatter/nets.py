"""The master and slave networks: Guan et al. 2022, Fig. 4 ('Neural network training').

"The network consists of 14 building blocks. [...] The first 7 blocks each has a
convolution layer with stride 2 [...] followed by a batch normalization layer and a
ReLU function. The other 7 blocks each has a deconvolution layer with stride 2 [...]
followed with batch normalization and ReLU, except the last layer uses the hyperbolic
tangent function (Tanh) instead of the ReLU. The U-Net style skip connections copy the
feature map from the first six block outputs to the last six blocks' input features."

- Kernel 4, stride 2, padding 1 in every block, as in pix2pix (refs. 33, 34 of the paper):
  each block halves (or doubles) the resolution exactly, so a 512 x 512 input has a
  4 x 4 bottleneck and a 128 x 128 crop a 1 x 1 one. Sides must be multiples of 2^7.
- Channels as in Fig. 4: width x (1, 2, 4, 8, 8, 8, 8) down, mirrored up (capped at 8x);
  the paper's width is 64. Skips are concatenated, as in U-Net.
- The last block has no batch norm (as in pix2pix): normalising the output map over the
  batch would fix its mean and spread.
- Master: one output channel, Tanh: the mask in [-1, 1].
  Slave: two output channels, the print's class logits (void, solid). The paper ends both
  nets alike; for the slave we leave out the Tanh, because the cross-entropy of Eq. 2
  takes logits (a Tanh would bound them to [-1, 1], i.e. probabilities in [0.12, 0.88]).
- Weights: N(0, 0.02) (paper, 'Neural network training'). Batch-norm scales are drawn
  from N(1, 0.02), as in pix2pix: a scale around 0 would switch every feature off.
"""

from __future__ import annotations

import torch
from torch import nn

DEPTH = 7  # Guan et al. 2022, Fig. 4: 7 down- and 7 up-sampling blocks
INIT_STD = 0.02  # Guan et al. 2022, 'Neural network training'


def channels(width: int, depth: int = DEPTH) -> list[int]:
    """Output channels of the down blocks: width x 1, 2, 4, 8, 8, ... (Fig. 4)."""
    return [width * min(2**i, 8) for i in range(depth)]


class UNet(nn.Module):
    """Fig. 4's encoder-decoder: ``depth`` strided convolutions, ``depth`` transposed
    convolutions, skips from the first depth-1 down blocks to the last depth-1 up blocks."""

    def __init__(self, in_channels: int = 1, out_channels: int = 1, width: int = 64, depth: int = DEPTH, tanh: bool = True):
        super().__init__()
        if width < 1 or depth < 2:
            raise ValueError("width must be >= 1 and depth >= 2")
        self.in_channels, self.out_channels, self.width, self.depth = in_channels, out_channels, width, depth
        ch = channels(width, depth)
        self.down = nn.ModuleList()
        prev = in_channels
        for c in ch:
            self.down.append(nn.Sequential(nn.Conv2d(prev, c, 4, 2, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU(inplace=True)))
            prev = c
        self.up = nn.ModuleList()
        for i in range(depth - 1, 0, -1):  # up block j takes the bottleneck or (previous up, skip)
            cin = ch[i] if i == depth - 1 else 2 * ch[i]
            self.up.append(nn.Sequential(nn.ConvTranspose2d(cin, ch[i - 1], 4, 2, 1, bias=False), nn.BatchNorm2d(ch[i - 1]), nn.ReLU(inplace=True)))
        last = nn.ConvTranspose2d(2 * ch[0], out_channels, 4, 2, 1, bias=True)
        self.up.append(nn.Sequential(last, nn.Tanh()) if tanh else nn.Sequential(last))
        init_weights(self)

    @property
    def multiple(self) -> int:
        """Input sides must be multiples of this."""
        return 2**self.depth

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        if h % self.multiple or w % self.multiple:
            raise ValueError(f"input sides must be multiples of {self.multiple}, got {h} x {w}")
        skips = []
        for blk in self.down:
            x = blk(x)
            skips.append(x)
        x = self.up[0](skips[-1])
        for blk, s in zip(self.up[1:], reversed(skips[:-1])):
            x = blk(torch.cat([x, s], dim=1))
        return x


def init_weights(net: nn.Module, std: float = INIT_STD, generator: torch.Generator | None = None) -> nn.Module:
    """Convolution weights ~ N(0, std), biases 0; batch-norm scales ~ N(1, std), shifts 0."""
    with torch.no_grad():
        for m in net.modules():
            if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d)):
                m.weight.normal_(0.0, std, generator=generator)
                if m.bias is not None:
                    m.bias.zero_()
            elif isinstance(m, nn.BatchNorm2d):
                m.weight.normal_(1.0, std, generator=generator)
                m.bias.zero_()
    return net


def master_net(width: int = 64, in_channels: int = 1, depth: int = DEPTH) -> UNet:
    """The master: target print (and coordinates) -> mask in [-1, 1] (Tanh)."""
    return UNet(in_channels, 1, width, depth, tanh=True)


def slave_net(width: int = 64, in_channels: int = 1, depth: int = DEPTH) -> UNet:
    """The slave: mask (and coordinates) -> print class logits (void, solid)."""
    return UNet(in_channels, 2, width, depth, tanh=False)

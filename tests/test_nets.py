"""The master and slave U-Nets of Fig. 4."""

import pytest
import torch
from torch import nn

from unscatter.nets import UNet, channels, init_weights, master_net, slave_net


def _bottleneck(net, x):
    seen = {}

    def hook(module, inputs, output):
        seen["shape"] = tuple(output.shape)

    h = net.down[-1].register_forward_hook(hook)
    out = net(x)
    h.remove()
    return out, seen["shape"]


def test_fig4_channels_and_blocks():
    assert channels(64) == [64, 128, 256, 512, 512, 512, 512]  # Fig. 4, capped at 8 x 64
    net = master_net(64)
    assert len(net.down) == 7 and len(net.up) == 7  # 14 blocks
    convs = [m for m in net.down.modules() if isinstance(m, nn.Conv2d)]
    assert all(c.kernel_size == (4, 4) and c.stride == (2, 2) and c.padding == (1, 1) for c in convs)
    deconvs = [m for m in net.up.modules() if isinstance(m, nn.ConvTranspose2d)]
    assert len(deconvs) == 7 and all(d.stride == (2, 2) for d in deconvs)
    # every block but the last: batch norm and ReLU; the master ends with Tanh
    for blk in list(net.down) + list(net.up[:-1]):
        assert isinstance(blk[1], nn.BatchNorm2d) and isinstance(blk[2], nn.ReLU)
    assert isinstance(net.up[-1][-1], nn.Tanh)
    # six skips: the last six up blocks take twice the channels of the matching down block
    for j, blk in enumerate(net.up[1:]):
        assert blk[0].in_channels == 2 * channels(64)[5 - j]


def test_512_input_has_a_4px_bottleneck_and_full_size_outputs():
    m, s = master_net(8), slave_net(8)
    x = torch.randn(2, 1, 512, 512)
    with torch.no_grad():
        out, bott = _bottleneck(m, x)
        assert bott == (2, 64, 4, 4)
        assert out.shape == (2, 1, 512, 512)
        assert out.abs().max() <= 1
        assert s(x).shape == (2, 2, 512, 512)


def test_small_crops_down_to_a_1px_bottleneck():
    m = master_net(4, in_channels=3)
    x = torch.randn(2, 3, 128, 128)
    out, bott = _bottleneck(m, x)  # train mode: batch norm over two samples
    assert bott == (2, 32, 1, 1) and out.shape == (2, 1, 128, 128)
    out.mean().backward()
    m.eval()
    with torch.no_grad():
        assert m(torch.randn(1, 3, 256, 256)).shape == (1, 1, 256, 256)


def test_slave_outputs_logits_not_tanh():
    s = slave_net(4)
    assert not any(isinstance(mod, nn.Tanh) for mod in s.modules())
    with torch.no_grad():
        s.up[-1][0].bias.fill_(3.0)
        assert s.eval()(torch.randn(1, 1, 128, 128)).min() > 1.5  # unbounded


def test_sides_must_be_multiples_of_128():
    with pytest.raises(ValueError, match="multiples of 128"):
        master_net(4)(torch.randn(2, 1, 100, 128))


def test_weights_drawn_from_n0_002():
    torch.manual_seed(0)
    net = master_net(64)
    w = torch.cat([m.weight.flatten() for m in net.modules() if isinstance(m, (nn.Conv2d, nn.ConvTranspose2d))])
    assert w.std().item() == pytest.approx(0.02, rel=0.02)
    assert abs(w.mean().item()) < 1e-3
    bn = torch.cat([m.weight.flatten() for m in net.modules() if isinstance(m, nn.BatchNorm2d)])
    assert bn.mean().item() == pytest.approx(1.0, abs=0.01)
    g = torch.Generator().manual_seed(1)
    a = init_weights(UNet(1, 1, 4), generator=g)
    b = init_weights(UNet(1, 1, 4), generator=torch.Generator().manual_seed(1))
    assert all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))

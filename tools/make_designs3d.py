"""Write the 3-D test designs of data/designs3d/<name>/ (one 0/255 PNG a layer, bottom
first; 256 x 256 DMD pixels at 2.96 um, 16 layers). Run once by a developer; the
workflow only reads data/designs3d/.

    python tools/make_designs3d.py data/designs3d

- channel_network: a block with a branching channel (one inlet, two outlets) through it,
  open on its faces: is it perfusable end to end?
- bridge: two pillars and a span between them: does the overhang grow downward?
- lattice: a woodpile of rods, alternating direction every two layers.
- hollow_tube: an upright tube: does its lumen stay open, its wall thin?
"""

import sys
from pathlib import Path

import numpy as np
from skimage.draw import disk

from unscatter.io import write_png

N, L = 256, 16


def channel_network():
    d = np.zeros((L, N, N), bool)
    d[:, 48:208, 32:224] = True
    w = 14  # channel width (px)
    for j in range(6, 10):  # the channel runs in layers 6..9
        d[j, 128 - w // 2:128 + w // 2, 32:128] = False  # inlet from the left face
        d[j, 80:176, 128 - w // 2:128 + w // 2] = False  # branches up and down
        d[j, 80 - w // 2 + 1:80 + w // 2 + 1, 128:224] = False  # outlets to the right face
        d[j, 176 - w // 2:176 + w // 2, 128:224] = False
    return d


def bridge():
    d = np.zeros((L, N, N), bool)
    d[:, 88:168, 40:72] = True
    d[:, 88:168, 184:216] = True
    d[L - 4:, 88:168, 40:216] = True
    return d


def lattice():
    d = np.zeros((L, N, N), bool)
    pitch, rod = 40, 14
    for j in range(L):
        for k in range(24, N - 24 - rod + 1, pitch):
            if (j // 2) % 2 == 0:
                d[j, 24:N - 24, k:k + rod] = True
            else:
                d[j, k:k + rod, 24:N - 24] = True
    return d


def hollow_tube():
    d = np.zeros((L, N, N), bool)
    outer, inner = np.zeros((N, N), bool), np.zeros((N, N), bool)
    outer[disk((N / 2, N / 2), 70)] = True
    inner[disk((N / 2, N / 2), 50)] = True
    d[:] = outer & ~inner
    return d


DESIGNS = {"channel_network": channel_network, "bridge": bridge, "lattice": lattice, "hollow_tube": hollow_tube}


def main(out):
    for name, make in DESIGNS.items():
        d = make()
        for j, layer in enumerate(d):
            write_png(Path(out) / name / f"{j:03d}.png", layer)
        print(f"{name}: {L} layers of {N}x{N}, {d.mean():.3f} solid")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "data/designs3d")

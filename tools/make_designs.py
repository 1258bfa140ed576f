"""Write the test designs of data/designs/ (binary 0/255 PNG, 512x512 at 2.96 um/px).

Shapes with sharp convex and concave features and rings of several diameters and widths,
in the spirit of Guan et al. 2022, Fig. 6. Run once by a developer; the workflow only
reads data/designs/.

    python tools/make_designs.py data/designs
"""

import sys
from pathlib import Path

import numpy as np
from skimage.draw import disk, polygon

from unscatter.io import write_png

N = 512


def star(points=5, r_out=200, r_in=85):
    m = np.zeros((N, N), bool)
    a = np.linspace(0, 2 * np.pi, 2 * points, endpoint=False) - np.pi / 2
    r = np.where(np.arange(2 * points) % 2 == 0, r_out, r_in)
    rr, cc = polygon(N / 2 + r * np.sin(a), N / 2 + r * np.cos(a), m.shape)
    m[rr, cc] = True
    return m


def cross(arm=60, half=190):
    m = np.zeros((N, N), bool)
    c = N // 2
    m[c - half : c + half, c - arm : c + arm] = True
    m[c - arm : c + arm, c - half : c + half] = True
    return m


def comb(teeth=5, tooth=28, gap=28, length=220):
    m = np.zeros((N, N), bool)
    x0 = (N - (teeth * tooth + (teeth - 1) * gap)) // 2
    m[100:160, x0 : N - x0] = True  # spine
    for i in range(teeth):
        x = x0 + i * (tooth + gap)
        m[160 : 160 + length, x : x + tooth] = True
    return m


def triangles():
    m = np.zeros((N, N), bool)
    for cx, cy, s, up in ((150, 180, 200, 1), (360, 330, 220, -1)):
        h = s * np.sqrt(3) / 2
        rr, cc = polygon([cy - up * 2 * h / 3, cy + up * h / 3, cy + up * h / 3], [cx, cx - s / 2, cx + s / 2], m.shape)
        m[rr, cc] = True
    return m


def rings(outer=(22, 36, 54, 80), width=14):
    """Rings of several diameters at one width: the small ones fail first."""
    m = np.zeros((N, N), bool)
    centres = ((130, 130), (130, 370), (370, 130), (370, 370))
    for (cy, cx), ro in zip(centres, outer):
        m[disk((cy, cx), ro, shape=m.shape)] = True
        m[disk((cy, cx), ro - width, shape=m.shape)] = False
    return m


def rings_widths(outer=70, widths=(8, 14, 22, 32)):
    """Rings of one diameter at several widths."""
    m = np.zeros((N, N), bool)
    centres = ((130, 130), (130, 370), (370, 130), (370, 370))
    for (cy, cx), w in zip(centres, widths):
        m[disk((cy, cx), outer, shape=m.shape)] = True
        m[disk((cy, cx), outer - w, shape=m.shape)] = False
    return m


DESIGNS = {"star": star, "cross": cross, "comb": comb, "triangles": triangles, "rings": rings, "rings_widths": rings_widths}


if __name__ == "__main__":
    out = Path(sys.argv[1] if len(sys.argv) > 1 else "data/designs")
    for name, fn in DESIGNS.items():
        write_png(out / f"{name}.png", fn())
        print(out / f"{name}.png")

# Makes lct-point.mat: a Stanford LCT-layout capture of a known scene, written by
# scipy's savemat as the Stanford release's files are (MAT v5, compressed; rect_data
# (x, y, t) uint16 counts; width = half the scanned side): one point target at
# (0.1, -0.05, 0.3) m in front of the wall, seen from an 8 x 8 confocal grid over
# [-0.2, 0.2]^2, 4 ps bins from the wall (pre-rectified: bin 0 is the wall), the
# round trip 2 * distance. Pixel (i, j) holds 100 + 10 i + j counts, so a swapped or
# mirrored axis is caught. Run with y-tal's venv (numpy, scipy):
#   python recon/tests/data/lct-point.py
import os
import numpy as np
import scipy.io

n, t, width = 8, 1024, 0.2
c, bin_s = 299792458.0, 4e-12
target = np.array([0.1, -0.05, 0.3])
xs = np.linspace(-width, width, n)
rect = np.zeros((n, n, t), dtype=np.uint16)
for i, x in enumerate(xs):
    for j, y in enumerate(xs):
        d = np.linalg.norm(target - np.array([x, y, 0.0]))
        b = int(np.floor(2 * d / (c * bin_s)))
        rect[i, j, b] = 100 + 10 * i + j
out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "lct-point.mat")
scipy.io.savemat(out, {"rect_data": rect, "width": np.array([[width]])}, do_compression=True)

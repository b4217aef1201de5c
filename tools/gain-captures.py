#!/usr/bin/env python3
"""Validation captures with unknown gains (issue 54, part 3; docs/recon.md, "Gains
from the data").

Copies ../shared/validation's confocal_planar, confocal_sparse and nonconfocal_planar
captures into OUT/scenes/<scene>/ with the `renderer:` line removed from `scene_info`
(so the laser falloff is no longer divided out from the metadata), as
capture<variant>_nometa.hdf5, and with a further gain per relay point:
capture<variant>_smooth3.hdf5, exp(ln 3 * (0.6 u + 0.4 v)) over the wall's [0, 1]^2
coordinates (1 to 3x), and capture<variant>_random30.hdf5, uniform +-30 % per point
(seed 1). Noisy (photon-count) captures are thinned binomially by the gains over
their maximum, so they stay Poisson. The truth and baselines are linked, and a copy
of the validation run.sh pointed at OUT scores them:

    python3 tools/gain-captures.py /tmp/gainval      # y-tal's venv: h5py, numpy
    OUT=/tmp/gv /tmp/gainval/run.sh                  # from the project root
    EXTRA='[gtr]
    pair-gains = "illumination"' OUT=/tmp/gv-est /tmp/gainval/run.sh
"""
import glob
import os
import shutil
import sys

import h5py
import numpy as np
HERE = os.path.dirname(os.path.abspath(__file__))
SRC = os.path.join(HERE, "..", "..", "shared", "validation", "scenes")
OUT = sys.argv[1] if len(sys.argv) > 1 else "/tmp/gainval"
rng = np.random.default_rng(1)
def strip(info):
    return '\n'.join(l for l in info.split('\n') if not l.startswith('renderer:') and not l.startswith('config:')).encode()
for scene in ['confocal_planar', 'confocal_sparse', 'nonconfocal_planar']:
    d = os.path.join(OUT, 'scenes', scene); os.makedirs(d, exist_ok=True)
    for f in glob.glob(os.path.join(SRC, scene, '*')):
        if not os.path.basename(f).startswith('capture'):
            dst = os.path.join(d, os.path.basename(f))
            if not os.path.exists(dst): os.symlink(f, dst)
    for cap in glob.glob(os.path.join(SRC, scene, 'capture*.hdf5')):
        base = os.path.basename(cap)[len('capture'):-len('.hdf5')]
        with h5py.File(cap) as f:
            H = f['H'][()]
            grid = f['sensor_grid_xyz'][()].reshape(-1, 3)
            for kind in ['nometa', 'smooth3', 'random30']:
                xy = grid[:, :2]
                u = (xy - xy.min(0)) / (xy.max(0) - xy.min(0))
                if kind == 'nometa': g = np.ones(len(grid))
                elif kind == 'smooth3': g = np.exp(np.log(3) * (0.6 * u[:, 0] + 0.4 * u[:, 1]))
                else: g = rng.uniform(0.7, 1.3, len(grid))
                Hc = H.reshape(H.shape[0], -1).astype(np.float64)
                if base.endswith('noisy'):
                    p = g / g.max()
                    Hn = rng.binomial(Hc.astype(np.int64), p[None, :]).astype(H.dtype)
                else:
                    Hn = (Hc * g[None, :]).astype(H.dtype)
                out = os.path.join(d, f'capture{base}_{kind}.hdf5')
                with h5py.File(out, 'w') as o:
                    for k in f.keys():
                        if k == 'H': o.create_dataset('H', data=Hn.reshape(H.shape))
                        elif k == 'scene_info': o.create_dataset('scene_info', data=strip(f[k][()].decode()))
                        else: f.copy(f[k], o, k)

# The validation runner, scoring the scenes under OUT with the project's release build.
run = open(os.path.join(SRC, "..", "run.sh")).read()
run = run.replace("cargo build --release --locked -q -p periscope-daemon >&2",
                  "(cd \"%s\" && cargo build --release --locked -q -p periscope-daemon) >&2" % os.path.abspath(os.path.join(HERE, "..")))
run = run.replace("BIN=${CARGO_TARGET_DIR:-target}/release/periscope", "BIN=%s/target/release/periscope" % os.path.abspath(os.path.join(HERE, "..")))
open(os.path.join(OUT, "run.sh"), "w").write(run)
os.chmod(os.path.join(OUT, "run.sh"), 0o755)
shutil.copy(os.path.join(SRC, "..", "score.py"), os.path.join(OUT, "score.py"))

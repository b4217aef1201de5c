#!/usr/bin/env python3
"""Renders an independent confocal capture of thin bars sampled more coarsely than the
bars are spaced, with mitransient, for checking `periscope recon`'s resolution on data
our own simulator did not make (docs/recon.md, "Resolution").

A planar relay at z = 0 (normal +z) is scanned confocally on an N x N grid over a
square of side SIZE centred on the origin; the laser is a point source at (0, -2, 1.2)
as in the validation set, so each transient carries its own cos/d^2 gain. The hidden
scene is three one-sided white Lambertian bars facing the relay at z = 0.5 m, each
WIDTH wide and 0.30 m long (along y), WIDTH apart (centres at x = -2W, 0, 2W): the
simulator's `wall-bars` scene. Light transport as in the validation set: third bounce
only (max_depth 3, hidden-geometry sampling, direct paths discarded), first and last
legs not counted, bins of 5 mm. Written as y-tal writes a confocal grid capture
(H_format T_Sx_Sy, grid format X_Y_3), with truth maps score.py reads on a PIX x PIX
grid over [-EXTENT, EXTENT]^2 (coverage by 16 x 16 sub-samples a pixel).

The fixture `bars_coarse.hdf5` (tests/ytal.rs) is

    render_bars.py OUT --n 12 --size 0.48 --t-start 0.9 --bins 192

a 4 cm pitch over 0.48 m for 2 cm bars 2 cm apart (about a minute on two cores).
`far_patch.hdf5` and `far_patch_ambient10.hdf5` (tests/ytal.rs, "far patch") add a 10 cm
patch at 0.8 m, noise-free and as Poisson counts under ambient light ten times the
signal:

    render_bars.py OUT --n 16 --size 0.96 --t-start 0.8 --bins 240 --spp 65536 \
        --patch 0.2,0.15,0.8,0.1 --extent 0.32 --pix 32 [--noise 50,10,1]

The
proxy in docs/recon.md is `--n 24 --size 0.96` (the same pitch over twice the aperture,
512 bins from 0).

Setup as render_torso.py:

    python3 -m venv /tmp/mit && /tmp/mit/bin/pip install mitransient==1.3.1 h5py
    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        /tmp/mit/bin/python tests/data/ytal/render_bars.py OUT_DIR
"""
import argparse
import json
import os

import numpy as np
import mitsuba as mi

mi.set_variant("llvm_ad_mono")
import h5py  # noqa: E402
import mitransient as mitr  # noqa: E402
from nlos_common import INTEGRATOR, axis  # noqa: E402

ARGS = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ARGS.add_argument("out", help="folder for capture.hdf5 and the truth maps")
ARGS.add_argument("--n", type=int, default=24, help="confocal points a side")
ARGS.add_argument("--size", type=float, default=0.96, help="side of the scanned square, m")
ARGS.add_argument("--width", type=float, default=0.02, help="bar width and gap, m")
ARGS.add_argument("--spp", type=int, default=262144, help="samples a point")
ARGS.add_argument("--bins", type=int, default=512)
ARGS.add_argument("--t-start", type=float, default=0.0, help="path length of bin 0, m")
ARGS.add_argument("--pix", type=int, default=50, help="truth pixels a side")
ARGS.add_argument("--extent", type=float, default=0.25, help="truth grid half-width, m")
ARGS.add_argument("--patch", default=None,
                  help="X,Y,Z,SIDE: also a square white patch facing the relay (label 2 in the truth)")
ARGS.add_argument("--noise", default=None,
                  help="PEAK,RATIO,SEED: write Poisson counts instead of the render's expectation: scaled to "
                       "PEAK in the brightest bin, plus a flat ambient rate whose total is RATIO times the "
                       "signal's, drawn with numpy's default_rng(SEED)")
ARGS = ARGS.parse_args()
OUT, N, SIZE, WIDTH = ARGS.out, ARGS.n, ARGS.size, ARGS.width
DELTA_T, DEPTH = 0.005, 0.5
LASER = [0.0, -2.0, 1.2]
BARS = [(2 * WIDTH * k - WIDTH / 2, 2 * WIDTH * k + WIDTH / 2, -0.15, 0.15) for k in (-1, 0, 1)]
PATCH = [float(v) for v in ARGS.patch.split(",")] if ARGS.patch else None


def render():
    white = {"type": "diffuse", "reflectance": {"type": "spectrum", "value": 1.0}}
    T = mi.ScalarTransform4f
    scene = {
        "type": "scene",
        "integrator": INTEGRATOR,
        "laser": {
            "type": "projector",
            "irradiance": {"type": "spectrum", "value": 1.0},
            "fov": 0.2,
            "to_world": T().look_at(origin=LASER, target=[0, 0, 0], up=[0, 0, 1]),
        },
        "relay_wall": {
            "type": "rectangle",
            "bsdf": white,
            "to_world": T().scale([SIZE / 2, SIZE / 2, 1]),
            # Confocal: a 1 x 1 film, the laser and the measured point moved together.
            "sensor": {
                "type": "nlos_capture_meter",
                "sensor_origin": LASER,
                "original_film_width": N,
                "original_film_height": N,
                "sampler": {"type": "independent", "sample_count": ARGS.spp, "seed": 1},
                "film": {
                    "type": "transient_hdr_film",
                    "width": 1,
                    "height": 1,
                    "temporal_bins": ARGS.bins,
                    "bin_width_opl": DELTA_T,
                    "start_opl": ARGS.t_start,
                    "rfilter": {"type": "box"},
                },
            },
        },
    }
    for i, (x0, x1, y0, y1) in enumerate(BARS):
        scene[f"bar_{i}"] = {
            "type": "rectangle",
            "bsdf": white,
            "to_world": T().translate([(x0 + x1) / 2, (y0 + y1) / 2, DEPTH])
            @ T().scale([(x1 - x0) / 2, (y1 - y0) / 2, 1])
            @ T().rotate([1, 0, 0], 180),
        }
    if PATCH:
        px, py, pz, side = PATCH
        scene["patch"] = {
            "type": "rectangle",
            "bsdf": white,
            "to_world": T().translate([px, py, pz]) @ T().scale([side / 2, side / 2, 1]) @ T().rotate([1, 0, 0], 180),
        }
    scene = mi.load_dict(scene)
    relay = next(s for s in scene.shapes() if s.id() == "relay_wall")
    laser = scene.emitters()[0]
    xs = -SIZE / 2 + (np.arange(N) + 0.5) * SIZE / N
    h = np.zeros((ARGS.bins, N, N), np.float32)
    for ix in range(N):
        for iy in range(N):
            point = mi.Point3f(float(xs[ix]), float(xs[iy]), 0.0)
            mitr.nlos.focus_emitter_at_relay_wall_3dpoint(point, relay, laser)
            _, transient = scene.integrator().render(scene, sensor=0, seed=ix * N + iy)
            h[:, ix, iy] = np.array(transient)[..., 0].reshape(ARGS.bins)
    return xs, h


def add_noise(h):
    """Poisson counts from the render's expectation (see --noise); returns them and a line
    for scene_info."""
    peak, ratio, seed = ARGS.noise.split(",")
    signal = h.astype(np.float64) * (float(peak) / h.max())
    ambient = float(ratio) * signal.sum() / signal.size
    counts = np.random.default_rng(int(seed)).poisson(signal + ambient).astype(np.float32)
    return counts, f"noise: Poisson, peak {peak} counts, ambient {ambient:.4g} a bin ({ratio} x the signal), seed {seed}\n"


def write_capture(xs, h):
    grid = np.stack(list(np.meshgrid(xs, xs, indexing="ij")) + [np.zeros((N, N))], -1)
    normals = np.zeros_like(grid)
    normals[..., 2] = 1.0
    info = (
        f"description: planar relay at z = 0, confocal {N}x{N} over {SIZE} m; three bars "
        f"{WIDTH} m wide and {WIDTH} m apart, 0.30 m long, at z = {DEPTH}"
        + (f"; a {PATCH[3]} m square patch at ({PATCH[0]}, {PATCH[1]}, {PATCH[2]})" if PATCH else "")
        + "\n"
        "generator: periscope tests/data/ytal/render_bars.py\n"
        "original_format: HDF5_TAL\n"
        "renderer: mitransient 1.3.1 / mitsuba 3.9.1 (llvm_ad_mono)\n"
        "scene: bars_coarse\n"
        f"spp: {ARGS.spp}\n"
    )
    if ARGS.noise:
        h, line = add_noise(h)
        info += line
    with h5py.File(f"{OUT}/capture.hdf5", "w") as f:
        f.create_dataset("H", data=h, compression="gzip", compression_opts=9, shuffle=True)
        f["H_format"] = np.array([1], np.int32)  # T_Sx_Sy
        f["laser_grid_format"] = np.array([2], np.int32)  # X_Y_3
        f["sensor_grid_format"] = np.array([2], np.int32)
        f["delta_t"] = np.float64(DELTA_T)
        f["t_start"] = np.float64(ARGS.t_start)
        f["t_accounts_first_and_last_bounces"] = False
        f["laser_grid_xyz"] = grid.astype(np.float32)
        f["laser_grid_normals"] = normals.astype(np.float32)
        f["sensor_grid_xyz"] = grid.astype(np.float32)
        f["sensor_grid_normals"] = normals.astype(np.float32)
        f["laser_xyz"] = np.array(LASER, np.float32)
        f["sensor_xyz"] = np.array(LASER, np.float32)
        f["scene_info"] = info


def write_truth():
    n, sub, e = ARGS.pix, 16, ARGS.extent
    centres = -e + (np.arange(n) + 0.5) * 2 * e / n
    offsets = (np.arange(sub) + 0.5) / sub * 2 * e / n - e / n
    coverage = np.zeros((n, n), np.float32)
    patch_cov = np.zeros((n, n), np.float32)
    for ix in range(n):
        for iy in range(n):
            X, Y = np.meshgrid(centres[ix] + offsets, centres[iy] + offsets, indexing="ij")
            hit = np.zeros(X.shape, bool)
            for x0, x1, y0, y1 in BARS:
                hit |= (X >= x0) & (X < x1) & (Y >= y0) & (Y < y1)
            coverage[ix, iy] = hit.mean()
            if PATCH:
                px, py, pz, side = PATCH
                on = (np.abs(X - px) <= side / 2) & (np.abs(Y - py) <= side / 2)
                patch_cov[ix, iy] = on.mean()
    depth = np.where(coverage > 0, DEPTH, -1.0)
    labels = (coverage >= 0.5).astype(np.int16)
    if PATCH:
        # The bars are nearer: where both cover a pixel, the bars are what it sees.
        far = (patch_cov >= 0.5) & (coverage < 0.5)
        labels[far] = 2
        depth = np.where((patch_cov > 0) & (coverage == 0), PATCH[2], depth)
        coverage = np.maximum(coverage, patch_cov)
    np.save(f"{OUT}/truth_coverage.npy", coverage)
    np.save(f"{OUT}/truth_depth.npy", depth.astype(np.float32))
    np.save(f"{OUT}/truth_mask.npy", labels > 0)
    np.save(f"{OUT}/truth_labels.npy", labels)

    truth = {
        "scene": "bars_coarse",
        "coordinate_system": "y-tal: relay at z=0 facing +z; hidden scene at z>0; metres",
        "targets": [{"name": "bars", "label": 1}] + ([{"name": "patch", "label": 2}] if PATCH else []),
        "recommended_volume": {
            "x": axis(-e, e, n),
            "y": axis(-e, e, n),
            "z": axis(0.195, 1.005, 81),
            "shape_xyz": [n, n, 81],
        },
    }
    with open(f"{OUT}/truth.json", "w") as f:
        json.dump(truth, f, indent=1)


if __name__ == "__main__":
    os.makedirs(OUT, exist_ok=True)
    xs, h = render()
    write_capture(xs, h)
    write_truth()
    print(f"{OUT}/capture.hdf5: {N}x{N} points, {h.shape[0]} bins, total {h.sum():.4g}")

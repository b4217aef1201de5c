#!/usr/bin/env python3
"""Writes the y-tal HDF5 fixtures in this folder with y-tal itself.

The files are what `periscope recon` must read (tests/ytal.rs), written by the
library whose format we implement, so a test against them proves compatibility
rather than agreement with our own writer. Regenerate with:

    python3 -m venv /tmp/ytal && /tmp/ytal/bin/pip install y-tal==0.20.0 h5py
    /tmp/ytal/bin/python tests/data/ytal/generate.py

The hidden scene in every file is the same: a 0.2 m x 0.2 m square patch facing the
relay, centred at (0.05, -0.05, 0.5) m, seen from a planar relay at z = 0 (y-tal's
convention: the relay is the plane z = 0 and the hidden scene lies at z > 0). The
transients are rendered analytically (three-bounce Lambertian, 1/r^2 per leg, cosine
at every surface) so the tests know the truth: depth 0.5 m over the patch.
"""
import os

import numpy as np
import tal
from tal.enums import GridFormat, HFormat

HERE = os.path.dirname(os.path.abspath(__file__))
DELTA_T = 0.01  # metres of path per bin
BINS = 256
PATCH_CENTRE = np.array([0.05, -0.05, 0.5])
PATCH_SIZE = 0.2
LASER_XYZ = np.array([-0.4, 0.1, 1.2])  # laser origin (first leg starts here)
SENSOR_XYZ = np.array([0.4, -0.1, 1.2])  # SPAD origin (last leg ends here)


def patch_points(n=24):
    u = (np.arange(n) + 0.5) / n - 0.5
    gx, gy = np.meshgrid(u * PATCH_SIZE, u * PATCH_SIZE, indexing="ij")
    pts = np.stack([gx.ravel(), gy.ravel(), np.zeros(n * n)], axis=-1) + PATCH_CENTRE
    area = (PATCH_SIZE / n) ** 2
    return pts, area


def render(xi, xd, t_start, with_legs):
    """Transient (BINS,) for illumination point xi and detection point xd on z = 0."""
    pts, area = patch_points()
    n_relay = np.array([0.0, 0.0, 1.0])
    n_patch = np.array([0.0, 0.0, -1.0])
    v1 = pts - xi
    v2 = pts - xd
    r1 = np.linalg.norm(v1, axis=1)
    r2 = np.linalg.norm(v2, axis=1)
    cos = (
        np.clip(v1 @ n_relay / r1, 0, None)
        * np.clip(-(v1 @ n_patch) / r1, 0, None)
        * np.clip(-(v2 @ n_patch) / r2, 0, None)
        * np.clip(v2 @ n_relay / r2, 0, None)
    )
    weight = cos * area / (r1**2 * r2**2)
    path = r1 + r2
    if with_legs:
        path = path + np.linalg.norm(xi - LASER_XYZ) + np.linalg.norm(xd - SENSOR_XYZ)
    pos = (path - t_start) / DELTA_T
    h = np.zeros(BINS)
    k = np.floor(pos).astype(int)
    frac = pos - k
    for kk, ff, ww in zip(k, frac, weight):
        if 0 <= kk < BINS:
            h[kk] += ww * (1 - ff)
        if 0 <= kk + 1 < BINS:
            h[kk + 1] += ww * ff
    return (h * 1e4).astype(np.float32)


def grid(n, half):
    u = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(u, u, indexing="ij")
    xyz = np.stack([gx, gy, np.zeros_like(gx)], axis=-1).astype(np.float32)
    normals = np.zeros_like(xyz)
    normals[..., 2] = 1.0
    return xyz, normals


def capture(**fields):
    data = tal.io.capture_data.NLOSCaptureData()
    for key, value in fields.items():
        setattr(data, key, value)
    return data


def confocal_xy():
    """Confocal T_Sx_Sy on an X_Y_3 grid, legs already removed, gzip-compressed."""
    xyz, normals = grid(16, 0.4)
    H = np.zeros((BINS, 16, 16), dtype=np.float32)
    for i in range(16):
        for j in range(16):
            H[:, i, j] = render(xyz[i, j], xyz[i, j], 0.0, False)
    data = capture(
        H=H, H_format=HFormat.T_Sx_Sy,
        sensor_xyz=SENSOR_XYZ.astype(np.float32), sensor_grid_xyz=xyz,
        sensor_grid_normals=normals, sensor_grid_format=GridFormat.X_Y_3,
        laser_xyz=LASER_XYZ.astype(np.float32), laser_grid_xyz=xyz.copy(),
        laser_grid_normals=normals.copy(), laser_grid_format=GridFormat.X_Y_3,
        delta_t=DELTA_T, t_start=0.0, t_accounts_first_and_last_bounces=False,
        scene_info={"original_format": "periscope fixture", "patch_depth": 0.5},
    )
    tal.io.write_capture(os.path.join(HERE, "confocal_xy.hdf5"), data, compression_level=4)


def single_laser_n3():
    """One laser point, 12 x 12 sensor points as an N_3 list (T_Si), first and last
    bounces included, t_start after the laser fires."""
    xyz, normals = grid(12, 0.4)
    sensors = xyz.reshape(-1, 3)
    laser = np.array([[0.1, 0.05, 0.0]], dtype=np.float32)
    t_start = 2.0
    H = np.stack([render(laser[0], s, t_start, True) for s in sensors], axis=1)
    data = capture(
        H=H, H_format=HFormat.T_Si,
        sensor_xyz=SENSOR_XYZ.astype(np.float32), sensor_grid_xyz=sensors,
        sensor_grid_normals=normals.reshape(-1, 3), sensor_grid_format=GridFormat.N_3,
        laser_xyz=LASER_XYZ.astype(np.float32), laser_grid_xyz=laser,
        laser_grid_normals=np.array([[0.0, 0.0, 1.0]], dtype=np.float32),
        laser_grid_format=GridFormat.N_3,
        delta_t=DELTA_T, t_start=t_start, t_accounts_first_and_last_bounces=True,
    )
    tal.io.write_capture(os.path.join(HERE, "single_laser_n3.hdf5"), data)


def exhaustive_li_si():
    """Four laser points x 8 x 8 sensor points (T_Li_Si), legs removed, float64 H."""
    xyz, normals = grid(8, 0.4)
    sensors = xyz.reshape(-1, 3)
    lasers = np.array([[-0.2, -0.2, 0], [0.2, -0.2, 0], [-0.2, 0.2, 0], [0.2, 0.2, 0]],
                      dtype=np.float32)
    H = np.zeros((BINS, len(lasers), len(sensors)))
    for li, l in enumerate(lasers):
        for si, s in enumerate(sensors):
            H[:, li, si] = render(l, s, 0.0, False)
    data = capture(
        H=H, H_format=HFormat.T_Li_Si,
        sensor_grid_xyz=sensors, sensor_grid_normals=normals.reshape(-1, 3),
        sensor_grid_format=GridFormat.N_3,
        laser_grid_xyz=lasers, laser_grid_normals=np.tile([[0.0, 0.0, 1.0]], (4, 1)),
        laser_grid_format=GridFormat.N_3,
        delta_t=DELTA_T, t_start=0.0, t_accounts_first_and_last_bounces=False,
    )
    tal.io.write_capture(os.path.join(HERE, "exhaustive_li_si.hdf5"), data, compression_level=6)


if __name__ == "__main__":
    confocal_xy()
    single_laser_n3()
    exhaustive_li_si()
    for name in sorted(os.listdir(HERE)):
        if name.endswith(".hdf5"):
            c = tal.io.read_capture(os.path.join(HERE, name))
            print(f"{name}: H {c.H.shape} {c.H_format} confocal={c.is_confocal() if c.H_format in (HFormat.T_Sx_Sy, HFormat.T_Si) else False}")

# Makes the public-format fixtures: one known point scene per layout, written by the
# writers those formats come from (h5py as Galindo's ZNLOS renderer writes HDF5;
# hdf5storage, a MATLAB v7.3 writer, for the .mat v7.3 files of the f-k and
# phasor-field releases), so a swapped axis, a wrong time origin or a wrong bin width
# puts a count where the geometry says nothing is. Each transient's peak holds a count
# that names its relay point, and lies in the bin of its path length. Layouts:
# docs/research/nlos-capture-formats.md. Run with y-tal's venv plus hdf5storage:
#   python recon/tests/data/public-formats.py
import os
import numpy as np
import h5py
import hdf5storage

HERE = os.path.dirname(os.path.abspath(__file__))
C = 299792458.0


def out(name):
    return os.path.join(HERE, name)


def savemat73(path, variables):
    # As MATLAB's save -v7.3 writes: a 512-byte userblock, MATLAB_class attributes,
    # dims reversed in HDF5 (column-major), structs as groups.
    hdf5storage.savemat(path, variables, format="7.3", matlab_compatible=True,
                        store_python_metadata=False, truncate_existing=True)


# --- Zaragoza ZNLOS (Galindo et al. 2019), confocal, column-major file ---------------
# Wall in the X-Z plane (y = 0), hidden scene at -y (the dataset's convention), laser
# and SPAD at one origin in front of it. data h5py (channel, T, bounces, cy, cx); bin k
# holds total paths t0 + k deltaT, origin -> wall -> scene -> wall -> origin. Bounce 0
# (the 2nd bounce) holds the wall's own return, bounce 2 (the 4th) a later echo; bounce
# 1 (the 3rd, the attribute third_bounce) the target.
def znlos(name, row_major):
    ny, nx, nt, bounces = 6, 8, 640, 3
    delta, t0 = 0.005, 1.5
    origin = np.array([0.2, -1.0, 0.1])
    target = np.array([0.1, -0.5, 0.05])
    xs = np.linspace(-0.35, 0.35, nx)
    zs = np.linspace(-0.25, 0.25, ny)
    pos = np.zeros((3, ny, nx), np.float32)
    data = np.zeros((1, nt, bounces, ny, nx), np.float32)
    for i, z in enumerate(zs):
        for j, x in enumerate(xs):
            p = np.array([x, 0.0, z])
            pos[:, i, j] = p
            leg = np.linalg.norm(p - origin)
            data[0, int((2 * leg - t0) // delta), 0, i, j] = 5000.0
            k = int((2 * leg + 2 * np.linalg.norm(target - p) - t0) // delta)
            data[0, k, 1, i, j] = 100 + 10 * i + j
            data[0, k + 40, 2, i, j] = 7.0
    normals = np.zeros_like(pos)
    normals[1] = -1.0
    with h5py.File(out(name), "w") as f:
        if row_major:
            f.attrs["data order"] = "row-major"
            f.create_dataset("data", data=data.transpose(), compression="gzip")
            f["cameraGridPositions"] = pos.transpose()
            f["cameraGridNormals"] = normals.transpose()
            f["laserGridPositions"] = pos.transpose()
            f["laserGridNormals"] = normals.transpose()
        else:
            f.create_dataset("data", data=data, compression="gzip")
            f["cameraGridPositions"] = pos
            f["cameraGridNormals"] = normals
            f["laserGridPositions"] = pos
            f["laserGridNormals"] = normals
        f["data"].attrs["third_bounce"] = 1
        f["cameraPosition"] = origin.astype(np.float32)
        f["laserPosition"] = origin.astype(np.float32)
        f["cameraGridSize"] = np.array([0.7, 0.5], np.float32)
        f["cameraGridPoints"] = np.array([nx, ny], np.float32)
        f["laserGridSize"] = np.array([0.7, 0.5], np.float32)
        f["laserGridPoints"] = np.array([nx, ny], np.float32)
        f["deltaT"] = np.float32(delta)
        f["t0"] = np.float32(t0)
        f["t"] = np.int32(nt)
        f["isConfocal"] = np.int32(1)
        f["hiddenVolumePosition"] = target.astype(np.float32)
        f["hiddenVolumeSize"] = np.float32(0.1)


znlos("znlos-point.hdf5", row_major=False)
znlos("znlos-point-rowmajor.hdf5", row_major=True)


# --- ZNLOS exhaustive (non-confocal): data (channel, T, bounces, cy, cx, ly, lx) -----
def znlos_exhaustive():
    nc, nl, nt = (3, 4), (2, 3), 256
    delta, t0 = 0.01, 2.0
    cam, las = np.array([-0.3, -1.2, 0.0]), np.array([0.4, -1.1, 0.2])
    target = np.array([0.0, -0.4, 0.1])
    cpos = np.zeros((3,) + nc, np.float32)
    lpos = np.zeros((3,) + nl, np.float32)
    for i in range(nc[0]):
        for j in range(nc[1]):
            cpos[:, i, j] = (-0.3 + 0.2 * j, 0.0, -0.2 + 0.2 * i)
    for a in range(nl[0]):
        for b in range(nl[1]):
            lpos[:, a, b] = (-0.2 + 0.2 * b, 0.0, -0.1 + 0.2 * a)
    data = np.zeros((1, nt, 1) + nc + nl, np.float32)
    for i in range(nc[0]):
        for j in range(nc[1]):
            for a in range(nl[0]):
                for b in range(nl[1]):
                    c, l = cpos[:, i, j], lpos[:, a, b]
                    d = (np.linalg.norm(l - las) + np.linalg.norm(target - l)
                         + np.linalg.norm(target - c) + np.linalg.norm(c - cam))
                    data[0, int((d - t0) // delta), 0, i, j, a, b] = 1000 * i + 100 * j + 10 * a + b + 1
    normals_c = np.zeros_like(cpos)
    normals_c[1] = -1.0
    normals_l = np.zeros_like(lpos)
    normals_l[1] = -1.0
    with h5py.File(out("znlos-exhaustive.hdf5"), "w") as f:
        f.create_dataset("data", data=data, compression="gzip")
        f["cameraGridPositions"] = cpos
        f["cameraGridNormals"] = normals_c
        f["laserGridPositions"] = lpos
        f["laserGridNormals"] = normals_l
        f["cameraPosition"] = cam.astype(np.float32)
        f["laserPosition"] = las.astype(np.float32)
        f["deltaT"] = np.float32(delta)
        f["t0"] = np.float32(t0)
        f["t"] = np.int32(nt)
        f["isConfocal"] = np.int32(0)


znlos_exhaustive()


# --- Stanford f-k (Lindell et al. 2019): meas_*.mat + tof.mat, MAT v7.3 --------------
# meas (y, x, t) counts in 32 ps bins as gated (not rectified); tofgrid (y, x) the
# time of flight to each scan point, ps; the reference code shifts each histogram by
# floor(tofgrid / 32) bins so that 0 is the wall. Scanned area 2 m x 2 m (the
# release's planar scenes), scan points linspace(-1, 1, n); the hidden scene at +z.
def fk():
    n, nt, bin_s = 8, 1024, 32e-12
    target = np.array([0.25, -0.1, 0.6])
    ys = xs = np.linspace(-1.0, 1.0, n)
    meas = np.zeros((n, n, nt), np.uint16)
    tof = np.zeros((n, n))
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            tof[i, j] = 3000.0 + 37.0 * i + 11.0 * j
            hidden = 2 * np.linalg.norm(target - np.array([x, y, 0.0]))
            k = int(np.floor(tof[i, j] / 32.0)) + int(hidden // (C * bin_s))
            meas[i, j, k] = 100 + 10 * i + j
    d = out("fk-point")
    os.makedirs(d, exist_ok=True)
    savemat73(os.path.join(d, "meas_10min.mat"), {"meas": meas})
    savemat73(os.path.join(d, "tof.mat"), {"tofgrid": tof})


fk()


# A hostile f-k capture in MAT v5 (scipy's writer, as an older release might be saved):
# a 2 x 2 x 64 `meas` and a `tofgrid` holding a finite but impossible 1e30 ps. Reading
# it must refuse the shift by name, not saturate a cast into an index past `meas`.
def fk_hostile():
    import scipy.io
    meas = np.ones((2, 2, 64), np.float32)
    tof = np.array([[0.0, 64.0], [1e30, 32.0]])
    scipy.io.savemat(out("fk-hostile.mat"), {"meas": meas, "tofgrid": tof}, do_compression=False)


fk_hostile()


# --- Phasor field, Liu et al. 2019 (Nature): a `dataset` struct, MAT v7.3 ------------
# data (laser index, 1 SPAD, t); bin k holds total paths t0 + k deltat, laserOrigin ->
# laserPos -> scene -> cameraPos -> cameraOrigin (y-tal's reading of the format).
def pf2019():
    nlx, nly, nt = 6, 5, 1024
    deltat, t0 = 0.004, 1.0
    laser_origin = np.array([0.3, 0.1, 1.5])
    camera_origin = np.array([-0.4, 0.0, 1.2])
    camera_pos = np.array([0.05, 0.02, 0.0])
    target = np.array([-0.1, 0.05, 0.5])
    laser_pos = np.array([(-0.25 + 0.1 * a, -0.2 + 0.1 * b, 0.0) for a in range(nlx) for b in range(nly)])
    data = np.zeros((len(laser_pos), 1, nt))
    for i, l in enumerate(laser_pos):
        d = (np.linalg.norm(l - laser_origin) + np.linalg.norm(target - l)
             + np.linalg.norm(target - camera_pos) + np.linalg.norm(camera_pos - camera_origin))
        data[i, 0, int((d - t0) // deltat)] = 100 + i
    savemat73(out("pf2019-point.mat"), {"dataset": {
        "data": data,
        "t": np.array([[float(nt)]]),
        "deltat": np.array([[deltat]]),
        "t0": np.array([[t0]]),
        "laserOrigin": laser_origin[None, :],
        "laserPos": laser_pos,
        "laserNorm": np.array([[0.0, 0.0, 1.0]]),
        "cameraOrigin": camera_origin[None, :],
        "cameraPos": camera_pos[None, :],
        "cameraNorm": np.array([[0.0, 0.0, 1.0]]),
    }})


pf2019()


# --- Phasor field diffraction, Liu et al. 2020 (Nat. Commun.): MAT v7.3 --------------
# rect_data (x, y, t): the laser scanned over an M x N grid at sampling_spacing, one
# SPAD at grid point SPAD_index ([x y], 1-based), ts the bin in seconds, bin 0 at the
# wall (paths laser point -> scene -> SPAD point). Each return spread over five bins, so
# that backprojection on this grid is not aliased.
def pf2020(name="pf2020-point.mat", empty_spacing=False):
    m, n, nt = 16, 12, 1024
    ts, spacing = 8e-12, 0.025
    spad = (7, 5)
    target = np.array([0.03, -0.02, 0.4])
    def grid(i, j):
        return np.array([(i - (m - 1) / 2) * spacing, (j - (n - 1) / 2) * spacing, 0.0])
    s = grid(spad[0] - 1, spad[1] - 1)
    rect = np.zeros((m, n, nt))
    for i in range(m):
        for j in range(n):
            d = np.linalg.norm(target - grid(i, j)) + np.linalg.norm(target - s)
            k = int(d // (C * ts))
            # The laser pulse and the SPAD's jitter spread each return over a few bins.
            rect[i, j, k - 2:k + 3] = np.array([0.25, 0.6, 1.0, 0.6, 0.25]) * (100 + 10 * i + j)
    savemat73(out(name), {
        "rect_data": rect,
        "ts": np.array([[ts]]),
        # Empty (`[]`, which MATLAB stores as its dims marked MATLAB_empty): the pitch
        # then comes from aperturefullsize, as it does for a v5 file.
        "sampling_spacing": np.zeros((0, 0)) if empty_spacing else np.array([[spacing]]),
        "aperturefullsize": np.array([[(m - 1) * spacing, (n - 1) * spacing]]),
        "SPAD_index": np.array([[float(spad[0]), float(spad[1])]]),
    })


pf2020()
pf2020("pf2020-empty-spacing.mat", empty_spacing=True)


# --- y-tal frequency-domain H (tal >= 0.21, H_format F_Sx_Sy = 10) -------------------
# As tal's write_hdf5 writes it (an HDF5 enum of shape (1,) for H_format, complex64 H
# holding a band of FFT bins); PyPI's y-tal stops at 0.20, so h5py writes it here.
def ytal_frequency():
    names = {"UNKNOWN": 0, "T_Sx_Sy": 1, "T_Lx_Ly_Sx_Sy": 2, "T_Si": 3, "T_Li_Si": 4,
             "F_Sx_Sy": 10, "F_Lx_Ly_Sx_Sy": 11, "F_Si": 12, "F_Li_Si": 13}
    n = 4
    xs = (np.arange(n) * 2 + 1) / (2 * n) - 0.5
    grid = np.stack(list(np.meshgrid(xs, xs, indexing="ij")) + [np.zeros((n, n))], -1).astype(np.float32)
    with h5py.File(out("ytal-frequency.hdf5"), "w") as f:
        f["H"] = (np.ones((9, n, n)) * (1 + 1j)).astype(np.complex64)
        f.create_dataset("H_format", data=np.array([10], np.int64), dtype=h5py.enum_dtype(names, basetype="i8"))
        f["sensor_grid_xyz"] = grid
        f["laser_grid_xyz"] = grid
        f["delta_t"] = 0.003
        f["t_start"] = 0.0


ytal_frequency()

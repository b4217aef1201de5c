#!/usr/bin/env python3
"""Renders an independent two-torso capture with mitransient, for checking `periscope
recon` on data our own simulator did not make (docs/recon.md, "A two-torso check").

The relay is two human backs side by side, each a cylinder section (radius 0.25 m,
axis along y, 0.30 m wide, 0.60 m tall) bulging towards the hidden scene, centred at
x = -0.22 (back A) and x = +0.22 (back B). A fixed laser lights the crest of back A;
24 x 32 detection points lie on back B. The hidden scene, every target a one-sided
white Lambertian rectangle facing the relay, is off to A's side, so B sees it
obliquely: an L (stem x in [-0.30, -0.22], y in [-0.25, 0.20]; foot x in [-0.22, 0.02],
y in [-0.25, -0.17]; both at z = 0.55) and a 0.14 m patch at z = 0.75. Light
transport as in the validation set: third bounce only (max_depth 3, hidden-geometry
sampling, direct paths discarded), first and last legs not counted, 512 bins of 5 mm
from 0.5 m. The file is written as y-tal writes a point-list capture (H_format T_Si,
grid format N_3), with the truth maps score.py reads on the validation grid
(32 x 32 over [-0.5, 0.5]^2; coverage by 16 x 16 sub-samples a pixel).

Setup and run (about two minutes at the default 262,144 samples a point on two cores;
drjit 1.5 needs LLVM 16 or newer: `apt-get install libllvm19`):

    python3 -m venv /tmp/mit && /tmp/mit/bin/pip install mitransient==1.3.1 h5py
    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so \\
        /tmp/mit/bin/python tests/data/ytal/render_torso.py OUT_DIR

`--scene centred` puts a T in front of the gap between the backs instead (the fixture
`torso_t.hdf5`, with `--grid 12x16 --bins 256 --t-start 0.9 --spp 65536`, which
tests/ytal.rs reconstructs).

`--scene mannequin` puts the simulator's child-sized mannequin (1 m tall: ellipsoid head
and torso, capped cylinders for arms and legs; `sim::shapes::mannequin`) in front of
the backs, its feet at y = -0.5, placed and turned by `--mannequin X,Z,DEGREES`; the
truth maps label its head, torso, arms (`arm_a` on its -x side before the turn) and
legs, cast along +z, on a volume 0.2-1.2 m deep. The laser then comes in low from A's
side (the default beam would cross the legs); `--laser X,Y` moves its spot on back A,
and `--points 500 --seed S` keeps 500 of the grid's detection points drawn at random,
the issue's kind (docs/recon.md, "The mannequin"). The detection rays then come in at
45 degrees from B's side, so the mannequin may stand in front of the gap, and the
script prints the share of the mannequin's light the scene blocks (what the backs
cannot see of it; 1.5-1.7 % for the docs' placements). `--parts` renders only some of
its parts, for seeing which carries what. About 40 s a render at the default samples;
the fixture `mannequin.hdf5` is `--mannequin=0,0.5,0 --grid 16x24 --points 256
--seed 4 --bins 256 --t-start 0.8 --spp 65536`, its truth `mannequin_mask.npy` and
`mannequin_depth.npy` (float32, indexed x then y), which tests/ytal.rs reconstructs.
`--photons PEAK,BACKGROUND,SEED` writes Poisson counts of the render instead (the
validation set's noisy copies: 50,0.05): the fixture `mannequin_near_noisy.hdf5` is
`--mannequin=0.03,0.35,-5 --laser=-0.16,0.0 --grid 16x24 --points 256 --seed 9
--spp 65536 --photons 50,0.05,1`, its truth `mannequin_near_mask.npy` and
`mannequin_near_depth.npy`.

Detection points: the sensor is attached to a rectangle under back B and looks
straight down from far above, so its pixel centres map onto B as a regular x-y grid;
each point is the first hit of that ray (on B), and the time of the sensor's leg is the
hit's own distance, which is not counted. The points' normals are the cylinder's.
"""
import argparse
import json
import os

import numpy as np
import mitsuba as mi

mi.set_variant("llvm_ad_mono")
import drjit as dr  # noqa: E402
import h5py  # noqa: E402
import mitransient as mitr  # noqa: E402
from nlos_common import INTEGRATOR, axis  # noqa: E402

ARGS = argparse.ArgumentParser(description=__doc__.splitlines()[0])
ARGS.add_argument("out", help="folder for capture.hdf5 and the truth maps")
ARGS.add_argument("--spp", type=int, default=262144, help="samples a detection point")
ARGS.add_argument("--scene", choices=["oblique", "centred", "mannequin"], default="oblique")
ARGS.add_argument("--points", type=int, default=0,
                  help="keep this many of the grid's detection points, drawn at random (0: all)")
ARGS.add_argument("--laser", default=None, help="the laser spot's x,y on back A (default: its crest, 0)")
ARGS.add_argument("--mannequin", default="0,0.7,0",
                  help="the mannequin's x, z (its feet's centre) and turn about y in degrees")
ARGS.add_argument("--seed", type=int, default=0, help="for --points")
ARGS.add_argument("--parts", default=None,
                  help="render only these of the mannequin's parts, comma-separated (the truth keeps all)")
ARGS.add_argument("--grid", default="24x32", help="detection points on back B, NXxNY")
ARGS.add_argument("--bins", type=int, default=512)
ARGS.add_argument("--t-start", type=float, default=0.5, help="path length of bin 0, m")
ARGS.add_argument("--photons", default=None,
                  help="PEAK,BACKGROUND,SEED: write photon counts instead, Poisson draws of the render "
                       "scaled to PEAK expected counts in its brightest bin plus BACKGROUND a bin")
ARGS = ARGS.parse_args()
OUT, SPP = ARGS.out, ARGS.spp
RADIUS, HALF_WIDTH, Y_RANGE = 0.25, 0.15, (-0.3, 0.3)
CENTRE_A, CENTRE_B = -0.22, 0.22
NX, NY = (int(n) for n in ARGS.grid.split("x"))
BINS, DELTA_T, T_START = ARGS.bins, 0.005, ARGS.t_start
# The mannequin stands where the default laser's beam would cross its legs, so there
# the laser comes in low from A's side.
LASER_ORIGIN = [-1.5, 0.0, 1.0] if ARGS.scene == "mannequin" else [CENTRE_A, -1.0, 2.0]
LASER_XY = [float(v) for v in ARGS.laser.split(",")] if ARGS.laser else [CENTRE_A, 0.0]
LASER_SPOT = [LASER_XY[0], LASER_XY[1], float(np.sqrt(RADIUS**2 - (LASER_XY[0] - CENTRE_A) ** 2) - RADIUS)]
# The detection rays come down onto back B from far above it, or, with the mannequin
# (which stands in front of the gap between the backs), from far above and to B's side
# at 45 degrees, so that nothing in front of the backs (x < 0.09 + z) meets them; the
# sensor's rectangle then lies 0.47 m towards -x under B.
SENSOR_ORIGIN = [CENTRE_B + 200.0, 0.0, 200.0] if ARGS.scene == "mannequin" else [CENTRE_B, 0.0, 200.0]
SENSOR_SHIFT = -0.47 if ARGS.scene == "mannequin" else 0.0
# (x0, x1, y0, y1, z, target name). Nothing may lie above back B (x > 0.09), where the
# detection rays come down.
RECTANGLES = {
    # The L 0.3-0.5 m to the side of B, seen at 35-45 degrees, and a patch behind it.
    "oblique": [
        (-0.30, -0.22, -0.25, 0.20, 0.55, "letter_L"),
        (-0.22, 0.02, -0.25, -0.17, 0.55, "letter_L"),
        (-0.12, 0.02, 0.10, 0.24, 0.75, "patch"),
    ],
    # A T in front of the gap between the backs, and a patch low and far to A's side.
    "mannequin": [],
    "centred": [
        (-0.20, 0.08, 0.10, 0.18, 0.60, "letter_T"),
        (-0.10, -0.02, -0.22, 0.10, 0.60, "letter_T"),
        (-0.42, -0.30, -0.35, -0.23, 0.45, "patch"),
    ],
}[ARGS.scene]


def mannequin_parts():
    """A child-sized mannequin 1 m tall, as the simulator's (`sim::shapes::mannequin`):
    an ellipsoid head and torso, two arms and two legs as capped cylinders, feet at
    y = -0.5, placed at (x, z) and turned about its vertical axis by --mannequin.
    Returns {part name: (vertices, triangles)}, triangles wound outwards."""
    mx, mz, turn = (float(v) for v in ARGS.mannequin.split(","))
    c, s_ = np.cos(np.radians(turn)), np.sin(np.radians(turn))
    rot = np.array([[c, 0, s_], [0, 1, 0], [-s_, 0, c]])

    def ellipsoid(radii, centre, n=24):
        th, ph = np.meshgrid(np.linspace(0, np.pi, n + 1), np.linspace(0, 2 * np.pi, 2 * n + 1), indexing="ij")
        v = np.stack([np.sin(th) * np.cos(ph), np.cos(th), np.sin(th) * np.sin(ph)], -1) * radii + centre
        return grid_mesh(v.reshape(-1, 3), n + 1, 2 * n + 1), np.asarray(centre, float)

    def cylinder(a, b, r, n=16):
        a, b = np.asarray(a, float), np.asarray(b, float)
        axis_ = (b - a) / np.linalg.norm(b - a)
        u = np.cross(axis_, [0, 0, 1.0] if abs(axis_[2]) < 0.9 else [1.0, 0, 0])
        u /= np.linalg.norm(u)
        w = np.cross(axis_, u)
        ph = np.linspace(0, 2 * np.pi, n + 1)
        ring = np.cos(ph)[:, None] * u + np.sin(ph)[:, None] * w
        rows = [a, a + r * ring, b + r * ring, b]
        v = np.concatenate([np.repeat(a[None], n + 1, 0), a + r * ring, b + r * ring, np.repeat(b[None], n + 1, 0)])
        return grid_mesh(v, len(rows), n + 1), (a + b) / 2

    parts = {"head": [ellipsoid([0.075, 0.095, 0.085], [0, 0.88, 0])],
             "torso": [ellipsoid([0.13, 0.2, 0.075], [0, 0.57, 0])], "arm_a": [], "arm_b": [], "legs": []}
    for side in (-1, 1):
        parts["arm_a" if side < 0 else "arm_b"].append(cylinder([0.14 * side, 0.72, 0], [0.21 * side, 0.40, 0.02], 0.035))
        parts["legs"].append(cylinder([0.065 * side, 0.42, 0], [0.075 * side, 0.0, 0], 0.048))
    out = {}
    for name, meshes in parts.items():
        verts, tris = [], []
        for (v, t), centre in meshes:
            t = t.copy()
            # Wind each triangle outwards (diffuse surfaces are one-sided).
            n_ = np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]])
            flip = np.einsum("ij,ij->i", n_, v[t].mean(1) - centre) < 0
            t[flip] = t[flip][:, ::-1]
            tris.append(t + sum(len(x) for x in verts))
            verts.append(v)
        v = np.concatenate(verts) @ rot.T + [mx, -0.5, mz]
        out[name] = (v, np.concatenate(tris))
    return out


def blocked_share(scene, points, samples=20000, sensors=64):
    """The share of the mannequin's third-bounce light (Lambertian, 1/r^2 a leg, both
    relay cosines) that the scene blocks between the laser spot, the mannequin and 64
    of the detection points: what the backs cannot see of it."""
    rng = np.random.default_rng(0)
    c, n, area = [], [], []
    for v, t in MANNEQUIN.values():
        a, b, d = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        cross = np.cross(b - a, d - a)
        c.append((a, b, d))
        n.append(cross / np.linalg.norm(cross, axis=1, keepdims=True))
        area.append(np.linalg.norm(cross, axis=1) / 2)
    a, b, d = (np.concatenate([x[i] for x in c]) for i in range(3))
    n, area = np.concatenate(n), np.concatenate(area)
    k = rng.choice(len(area), samples, p=area / area.sum())
    u, w = rng.random(samples), rng.random(samples)
    flip = u + w > 1
    u[flip], w[flip] = 1 - u[flip], 1 - w[flip]
    p = a[k] + u[:, None] * (b[k] - a[k]) + w[:, None] * (d[k] - a[k])
    n = n[k]
    p_off = p + 1e-4 * n

    def leg(target, target_normal):
        """Unblocked weight of each sample towards a relay point, and whether it is seen."""
        to = target - p
        dist = np.linalg.norm(to, axis=1)
        to /= dist[:, None]
        weight = np.maximum(0, (n * to).sum(1)) * np.maximum(0, -(to @ target_normal)) / dist**2
        hit = scene.ray_intersect(mi.Ray3f(mi.Point3f(*p_off.T), mi.Vector3f(*to.T)))
        seen = ~np.array(hit.is_valid()) | (np.array(hit.t) > dist - 1e-3)
        return weight, seen

    wi, si = leg(np.array(LASER_SPOT), normal(np.array([LASER_SPOT]), CENTRE_A)[0])
    total = seen = 0.0
    for j in rng.choice(len(points), min(sensors, len(points)), replace=False):
        wd, sd = leg(points[j], normal(points[j : j + 1], CENTRE_B)[0])
        total += (wi * wd).sum()
        seen += (wi * wd * (si & sd)).sum()
    return 1 - seen / total


def grid_mesh(v, rows, cols):
    """Triangles of a rows x cols vertex grid (row-major), dropping degenerate ones."""
    t = []
    for i in range(rows - 1):
        for j in range(cols - 1):
            a, b, c, d = i * cols + j, (i + 1) * cols + j, (i + 1) * cols + j + 1, i * cols + j + 1
            t += [[a, b, c], [a, c, d]]
    t = np.array(t)
    area = np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1)
    return v, t[area > 1e-12]


def write_obj(path, v, t):
    with open(path, "w") as f:
        f.writelines(f"v {a} {b} {c}\n" for a, b, c in v)
        f.writelines(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in t)


def height(x, centre):
    return np.sqrt(RADIUS**2 - (x - centre) ** 2) - RADIUS


def normal(p, centre):
    return np.stack([(p[:, 0] - centre) / RADIUS, np.zeros(len(p)), (p[:, 2] + RADIUS) / RADIUS], -1)


def write_back(path, centre):
    """The back as an OBJ with the cylinder's vertex normals, faces towards +z."""
    xs = np.linspace(centre - HALF_WIDTH, centre + HALF_WIDTH, 61)
    ys = np.linspace(*Y_RANGE, 13)
    with open(path, "w") as f:
        for x in xs:
            for y in ys:
                f.write(f"v {x} {y} {height(x, centre)}\n")
        for x in xs:
            for y in ys:
                n = normal(np.array([[x, y, height(x, centre)]]), centre)[0]
                f.write(f"vn {n[0]} {n[1]} {n[2]}\n")
        index = lambda i, j: i * len(ys) + j + 1  # noqa: E731
        for i in range(len(xs) - 1):
            for j in range(len(ys) - 1):
                a, b, c, d = index(i, j), index(i + 1, j), index(i + 1, j + 1), index(i, j + 1)
                f.write(f"f {a}//{a} {b}//{b} {c}//{c}\nf {a}//{a} {c}//{c} {d}//{d}\n")


def scene_dict(white):
    x0, x1 = CENTRE_B - 0.13 + SENSOR_SHIFT, CENTRE_B + 0.13 + SENSOR_SHIFT
    y0, y1 = -0.27, 0.27
    T = mi.ScalarTransform4f
    d = {
        "type": "scene",
        "integrator": INTEGRATOR,
        "laser": {
            "type": "projector",
            "irradiance": {"type": "spectrum", "value": 1.0},
            "fov": 0.2,
            "to_world": T().look_at(origin=LASER_ORIGIN, target=LASER_SPOT, up=[0, 0, 1]),
        },
        "back_a": {"type": "obj", "filename": f"{OUT}/back_a.obj", "bsdf": white, "face_normals": False},
        "back_b": {"type": "obj", "filename": f"{OUT}/back_b.obj", "bsdf": white, "face_normals": False},
        "relay_wall": {
            "type": "rectangle",
            "bsdf": white,
            "to_world": T().translate([CENTRE_B + SENSOR_SHIFT, 0, -0.5]) @ T().scale([(x1 - x0) / 2, (y1 - y0) / 2, 1]),
            "sensor": {
                "type": "nlos_capture_meter",
                "sensor_origin": SENSOR_ORIGIN,
                "sampler": {"type": "independent", "sample_count": SPP, "seed": 1},
                "film": {
                    "type": "transient_hdr_film",
                    "width": NX,
                    "height": NY,
                    "temporal_bins": BINS,
                    "bin_width_opl": DELTA_T,
                    "start_opl": T_START,
                    "rfilter": {"type": "box"},
                },
            },
        },
    }
    if ARGS.scene == "mannequin":
        for name in MANNEQUIN:
            if ARGS.parts and name not in ARGS.parts.split(","):
                continue
            d[f"target_{name}"] = {"type": "obj", "filename": f"{OUT}/{name}.obj", "bsdf": white, "face_normals": True}
    for i, (x0, x1, y0, y1, z, _) in enumerate(RECTANGLES):
        d[f"target_{i}"] = {
            "type": "rectangle",
            "bsdf": white,
            "to_world": T().translate([(x0 + x1) / 2, (y0 + y1) / 2, z])
            @ T().scale([(x1 - x0) / 2, (y1 - y0) / 2, 1])
            @ T().rotate([1, 0, 0], 180),
        }
    return d


def render():
    os.makedirs(OUT, exist_ok=True)
    write_back(f"{OUT}/back_a.obj", CENTRE_A)
    write_back(f"{OUT}/back_b.obj", CENTRE_B)
    for name, (v, t) in MANNEQUIN.items():
        write_obj(f"{OUT}/{name}.obj", v, t)
    white = {"type": "diffuse", "reflectance": {"type": "spectrum", "value": 1.0}}
    scene = mi.load_dict(scene_dict(white))
    relay = next(s for s in scene.shapes() if s.id() == "relay_wall")
    mitr.nlos.focus_emitter_at_relay_wall_3dpoint(mi.Point3f(*LASER_SPOT), relay, scene.emitters()[0])
    # Pixel (i, j) looks at the rectangle's point (i + 1/2, j + 1/2) / film size; x fastest.
    u, v = np.meshgrid((np.arange(NX) + 0.5) / NX, (np.arange(NY) + 0.5) / NY, indexing="xy")
    targets = relay.sample_position(0.0, mi.Point2f(u.ravel(), v.ravel())).p
    origin = mi.Point3f(*SENSOR_ORIGIN)
    hits = scene.ray_intersect(mi.Ray3f(origin, dr.normalize(targets - origin)))
    assert dr.all(hits.is_valid()), "a detection ray missed back B"
    points = np.array(hits.p).T
    on_b = (np.abs(points[:, 0] - CENTRE_B) <= HALF_WIDTH + 1e-6) & (np.abs(points[:, 2] - height(points[:, 0], CENTRE_B)) < 1e-4)
    assert np.all(on_b), f"a detection ray hit something other than back B: x {points[~on_b, 0].min():.3f}..{points[~on_b, 0].max():.3f}, z {points[~on_b, 2].min():.3f}..{points[~on_b, 2].max():.3f}"
    if MANNEQUIN:
        print(f"the mannequin's light blocked on its way from the laser spot or to back B: {blocked_share(scene, points):.2%}")
    _, transient = scene.integrator().render(scene, sensor=0)
    h = np.array(transient)[..., 0].reshape(NY * NX, BINS).T.astype(np.float32)
    if ARGS.points:
        keep = np.sort(np.random.default_rng(ARGS.seed).choice(NX * NY, ARGS.points, replace=False))
        points, h = points[keep], h[:, keep]
    return points, h


def write_capture(points, h):
    info = (
        "description: two-torso relay (backs as cylinder sections, radius 0.25 m, centres "
        f"x = {CENTRE_A} and {CENTRE_B}); laser fixed on back A at {LASER_SPOT}; {len(points)} "
        f"detection points on back B; hidden scene {ARGS.scene} {ARGS.mannequin if MANNEQUIN else ''}\n"
        "generator: periscope tests/data/ytal/render_torso.py\n"
        "original_format: HDF5_TAL\n"
        "renderer: mitransient 1.3.1 / mitsuba 3.9.1 (llvm_ad_mono)\n"
        "scene: torso_check\n"
        f"spp: {SPP}\n"
    )
    if ARGS.photons:
        peak, background, seed = ARGS.photons.split(",")
        rate = h.astype(np.float64) * (float(peak) / h.max()) + float(background)
        h = np.random.default_rng(int(seed)).poisson(rate).astype(np.float32)
        info += f"photons: Poisson, peak {peak}, background {background} a bin, seed {seed}\n"
    with h5py.File(f"{OUT}/capture.hdf5", "w") as f:
        f.create_dataset("H", data=h, compression="gzip", compression_opts=9)
        f["H_format"] = np.array([3], np.int32)  # T_Si
        f["laser_grid_format"] = np.array([1], np.int32)  # N_3
        f["sensor_grid_format"] = np.array([1], np.int32)
        f["delta_t"] = np.float64(DELTA_T)
        f["t_start"] = np.float64(T_START)
        f["t_accounts_first_and_last_bounces"] = False
        f["laser_grid_xyz"] = np.array([LASER_SPOT], np.float32)
        f["laser_grid_normals"] = normal(np.array([LASER_SPOT]), CENTRE_A).astype(np.float32)
        f["laser_xyz"] = np.array(LASER_ORIGIN, np.float32)
        f["sensor_xyz"] = np.array(SENSOR_ORIGIN, np.float32)
        f["sensor_grid_xyz"] = points.astype(np.float32)
        f["sensor_grid_normals"] = normal(points, CENTRE_B).astype(np.float32)
        f["scene_info"] = info


def write_truth():
    n, sub = 32, 16
    centres = -0.5 + (np.arange(n) + 0.5) / n
    offsets = (np.arange(sub) + 0.5) / sub / n - 0.5 / n
    names = list(dict.fromkeys(r[5] for r in RECTANGLES)) + list(MANNEQUIN)
    if MANNEQUIN:
        # The mannequin's parts as seen from the relay: rays along +z from behind it.
        alone = {name: mi.load_dict({"type": "scene", name: {"type": "obj", "filename": f"{OUT}/{name}.obj"}})
                 for name in MANNEQUIN}
    coverage = np.zeros((n, n), np.float32)
    depth = np.full((n, n), -1.0, np.float32)
    labels = np.zeros((n, n), np.int16)
    for ix in range(n):
        for iy in range(n):
            X, Y = np.meshgrid(centres[ix] + offsets, centres[iy] + offsets, indexing="ij")
            nearest = np.full(X.shape, np.inf)
            share = np.zeros(len(names))
            for x0, x1, y0, y1, z, name in RECTANGLES:
                hit = (X >= x0) & (X < x1) & (Y >= y0) & (Y < y1)
                nearest = np.where(hit, np.minimum(nearest, z), nearest)
                share[names.index(name)] += hit.mean()
            if MANNEQUIN:
                ray = mi.Ray3f(mi.Point3f(X.ravel(), Y.ravel(), np.full(X.size, -5.0)), mi.Vector3f(0, 0, 1))
                zs = {}
                for name, part in alone.items():
                    si = part.ray_intersect(ray)
                    zs[name] = np.where(np.array(si.is_valid()), np.array(si.p.z), np.inf).reshape(X.shape)
                z = np.min(list(zs.values()), axis=0)
                nearest = np.minimum(nearest, z)
                for name, zk in zs.items():  # each ray's first hit is the part it belongs to
                    share[names.index(name)] += (np.isfinite(zk) & (zk == z)).mean()
            covered = np.isfinite(nearest)
            coverage[ix, iy] = covered.mean()
            if covered.any():
                depth[ix, iy] = nearest[covered].mean()
            if coverage[ix, iy] >= 0.5:
                labels[ix, iy] = 1 + int(np.argmax(share))
    np.save(f"{OUT}/truth_coverage.npy", coverage)
    np.save(f"{OUT}/truth_depth.npy", depth)
    np.save(f"{OUT}/truth_mask.npy", coverage >= 0.5)
    np.save(f"{OUT}/truth_labels.npy", labels)
    truth = {
        "scene": "torso_check",
        "coordinate_system": "y-tal: relay at (mean) z=0 facing +z; hidden scene at z>0; metres",
        "targets": [{"name": name, "label": i + 1} for i, name in enumerate(names)],
        "recommended_volume": {
            "x": axis(-0.5, 0.5, 32),
            "y": axis(-0.5, 0.5, 32),
            "z": axis(0.195, 1.205, 101) if MANNEQUIN else axis(0.195, 1.005, 81),
            "shape_xyz": [32, 32, 101 if MANNEQUIN else 81],
        },
    }
    with open(f"{OUT}/truth.json", "w") as f:
        json.dump(truth, f, indent=1)


MANNEQUIN = mannequin_parts() if ARGS.scene == "mannequin" else {}


if __name__ == "__main__":
    points, h = render()
    write_capture(points, h)
    write_truth()
    print(f"{OUT}/capture.hdf5: {h.shape[1]} points, {h.shape[0]} bins, total {h.sum():.4g}")

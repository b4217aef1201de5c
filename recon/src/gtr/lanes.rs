//! One primitive against four pairs of a mini-batch at once, or two primitives in
//! eight lanes.
//!
//! A training step evaluates every primitive against every pair of its batch. Each
//! evaluation's geometry (distances, directions, projected areas, spread) and, in the
//! backward pass, its chain rule down to the primitive's physical parameters are a few
//! hundred scalar operations with square roots and divisions: more time than the
//! per-bin loops, which run eight bins to a vector. Here the batch's pairs go four to a
//! vector instead, lane j of group g holding the batch's pair 4g + j, with the
//! primitive's parameters in every lane. With eight lanes (an AVX-512 vector, or two
//! AVX2 ones) two primitives go together, lanes 0–3 the first against the group's
//! pairs and lanes 4–7 the second against the same pairs.
//!
//! Every lane does the IEEE operations that [`evaluate`](super::kernel::evaluate) and
//! [`Evaluation::backward`](super::kernel::Evaluation::backward) do for one pair, in the
//! same order, and the lanes' gradients are added to the primitive's in the batch's
//! order, so a training step gives bit-for-bit what the one-pair path gives (tested,
//! on the portable arrays and on this CPU's vectors).
//!
//! A group of confocal pairs (`PairGroup::shares_sides`) computes its relay side once:
//! detection equals illumination there, operand for operand, so reusing the values
//! changes no bit.
use glam::DVec3;

use super::kernel::{Kernel, PhysicalGrad, RenderOptions, SIGMA_FLOOR_BINS, Window};
use crate::simd::{self, Quad};
use crate::transient::{Pair, TimeAxis, TransientSet};

/// Pairs per group: one f64 vector of AVX2.
pub(crate) const LANES: usize = 4;

/// One value per lane.
type Lanes = [f64; LANES];

/// Up to [`LANES`] pairs of a batch as lanes. Lanes past `used` repeat the first pair,
/// so their arithmetic stays finite, and are never read back.
#[derive(Clone, Copy, Debug)]
pub(crate) struct PairGroup {
    xi: [Lanes; 3],
    ni: [Lanes; 3],
    xd: [Lanes; 3],
    nd: [Lanes; 3],
    /// Lanes holding a pair of the batch.
    pub(crate) used: usize,
    /// Every lane's pair is confocal: the same point and normal for illumination and
    /// detection, bit for bit, so the detection side's geometry is the illumination
    /// side's and is computed once.
    confocal: bool,
}

impl PairGroup {
    /// The group of `pairs` (1 to [`LANES`] of them), lane j holding `pairs[j]`.
    pub(crate) fn new(pairs: &[&Pair]) -> Self {
        assert!(
            (1..=LANES).contains(&pairs.len()),
            "a group holds 1 to {LANES} pairs"
        );
        let pair = |j: usize| pairs[if j < pairs.len() { j } else { 0 }];
        let lanes = |f: &dyn Fn(&Pair) -> DVec3| -> [Lanes; 3] {
            let v: [DVec3; LANES] = std::array::from_fn(|j| f(pair(j)));
            [v.map(|v| v.x), v.map(|v| v.y), v.map(|v| v.z)]
        };
        let same = |a: DVec3, b: DVec3| a.to_array().map(f64::to_bits) == b.to_array().map(f64::to_bits);
        Self {
            xi: lanes(&|p| p.xi),
            ni: lanes(&|p| p.ni),
            xd: lanes(&|p| p.xd),
            nd: lanes(&|p| p.nd),
            used: pairs.len(),
            confocal: pairs.iter().all(|p| same(p.xi, p.xd) && same(p.ni, p.nd)),
        }
    }

    /// Whether the detection side's geometry is the illumination side's under `opt`:
    /// a confocal group whose two cosines are both on or both off. Then every value
    /// of the detection side equals its illumination twin bit for bit (the same
    /// operations on the same operands), so it is taken from the twin instead of
    /// computed again.
    #[inline(always)]
    fn shares_sides(&self, opt: &RenderOptions) -> bool {
        self.confocal && opt.use_ni == opt.use_nd
    }
}

/// The pairs `batch` of `set`, [`LANES`] to a group, in the batch's order.
pub(crate) fn groups(set: &TransientSet, batch: &[usize]) -> Vec<PairGroup> {
    batch
        .chunks(LANES)
        .map(|slots| PairGroup::new(&slots.iter().map(|&p| &set.pairs()[p]).collect::<Vec<_>>()))
        .collect()
}

/// A 3-vector per lane.
#[derive(Clone, Copy)]
struct Vec3s<V> {
    x: V,
    y: V,
    z: V,
}

impl<V: Copy> Vec3s<V> {
    /// Lane j holds `f(j)`.
    #[inline(always)]
    fn from_fn<const N: usize, Q: simd::Lanes<N, V = V>>(q: Q, f: impl Fn(usize) -> DVec3) -> Self {
        let v: [DVec3; N] = std::array::from_fn(f);
        Self {
            x: q.load(v.map(|v| v.x)),
            y: q.load(v.map(|v| v.y)),
            z: q.load(v.map(|v| v.z)),
        }
    }

    #[inline(always)]
    fn store<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q) -> [[f64; N]; 3] {
        [q.store(self.x), q.store(self.y), q.store(self.z)]
    }

    #[inline(always)]
    fn add<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q, o: Self) -> Self {
        Self {
            x: q.add(self.x, o.x),
            y: q.add(self.y, o.y),
            z: q.add(self.z, o.z),
        }
    }

    #[inline(always)]
    fn sub<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q, o: Self) -> Self {
        Self {
            x: q.sub(self.x, o.x),
            y: q.sub(self.y, o.y),
            z: q.sub(self.z, o.z),
        }
    }

    /// Component by component.
    #[inline(always)]
    fn mul<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q, o: Self) -> Self {
        Self {
            x: q.mul(self.x, o.x),
            y: q.mul(self.y, o.y),
            z: q.mul(self.z, o.z),
        }
    }

    #[inline(always)]
    fn scale<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q, c: V) -> Self {
        Self {
            x: q.mul(c, self.x),
            y: q.mul(c, self.y),
            z: q.mul(c, self.z),
        }
    }

    #[inline(always)]
    fn div<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q, c: V) -> Self {
        Self {
            x: q.div(self.x, c),
            y: q.div(self.y, c),
            z: q.div(self.z, c),
        }
    }

    /// `(x x' + y y') + z z'`, glam's order.
    #[inline(always)]
    fn dot<const N: usize, Q: simd::Lanes<N, V = V>>(self, q: Q, o: Self) -> V {
        q.add(q.add(q.mul(self.x, o.x), q.mul(self.y, o.y)), q.mul(self.z, o.z))
    }
}

/// Lane `j` of a 3-vector.
#[inline(always)]
fn lane<const N: usize>(a: &[[f64; N]; 3], j: usize) -> DVec3 {
    DVec3::new(a[0][j], a[1][j], a[2][j])
}

/// `m v` for a matrix given by its columns, as glam's `DMat3 * DVec3`:
/// `(c0 v.x + c1 v.y) + c2 v.z`.
#[inline(always)]
fn mat_vec<const N: usize, Q: simd::Lanes<N>>(q: Q, cols: &[Vec3s<Q::V>; 3], v: Vec3s<Q::V>) -> Vec3s<Q::V> {
    cols[0]
        .scale(q, v.x)
        .add(q, cols[1].scale(q, v.y))
        .add(q, cols[2].scale(q, v.z))
}

/// `mᵀ v` for a matrix given by its columns: component j is column j dotted with v
/// (glam's `m.transpose() * v`).
#[inline(always)]
fn mat_t_vec<const N: usize, Q: simd::Lanes<N>>(
    q: Q,
    cols: &[Vec3s<Q::V>; 3],
    v: Vec3s<Q::V>,
) -> Vec3s<Q::V> {
    Vec3s {
        x: cols[0].dot(q, v),
        y: cols[1].dot(q, v),
        z: cols[2].dot(q, v),
    }
}

/// `∂A⊥/∂s` without the factor: with `c = w ⊙ w ⊙ π`,
/// `(c_y s_z + c_z s_y, c_x s_z + c_z s_x, c_x s_y + c_y s_x) / a`.
#[inline(always)]
fn area_ds<const N: usize, Q: simd::Lanes<N>>(
    q: Q,
    w: Vec3s<Q::V>,
    a: Q::V,
    pi: Vec3s<Q::V>,
    s: Vec3s<Q::V>,
) -> Vec3s<Q::V> {
    let c = w.mul(q, w).mul(q, pi);
    Vec3s {
        x: q.add(q.mul(c.y, s.z), q.mul(c.z, s.y)),
        y: q.add(q.mul(c.x, s.z), q.mul(c.z, s.x)),
        z: q.add(q.mul(c.x, s.y), q.mul(c.y, s.x)),
    }
    .div(q, a)
}

/// The centre's gradient through one relay point at distance `d` in direction `u`:
/// `g_d u + (g_u − (u·g_u) u) / d`.
#[inline(always)]
fn centre_grad<const N: usize, Q: simd::Lanes<N>>(
    q: Q,
    u: Vec3s<Q::V>,
    g_u: Vec3s<Q::V>,
    g_d: Q::V,
    d: Q::V,
) -> Vec3s<Q::V> {
    u.scale(q, g_d)
        .add(q, g_u.sub(q, u.scale(q, u.dot(q, g_u))).div(q, d))
}

/// The primitives of an evaluation in lanes: lane j holds `kernels[j / LANES]`, so four
/// lanes hold one primitive and eight hold two, each against the group's four pairs.
/// Every value is computed as the one-primitive path computes it (scalar products of
/// the kernel's fields), so every lane has its bits.
struct Prims<V> {
    x: Vec3s<V>,
    /// The rotation's columns.
    cols: [Vec3s<V>; 3],
    s: Vec3s<V>,
    pi: Vec3s<V>,
    /// `s ⊙ s` and `π ⊙ π`.
    s2: Vec3s<V>,
    pi2: Vec3s<V>,
    rho: V,
}

impl<V: Copy> Prims<V> {
    #[inline(always)]
    fn load<const N: usize, Q: simd::Lanes<N, V = V>>(q: Q, kernels: &[&Kernel]) -> Self {
        debug_assert_eq!(kernels.len() * LANES, N);
        let k = |j: usize| kernels[j / LANES];
        Self {
            x: Vec3s::from_fn(q, |j| k(j).x),
            cols: [
                Vec3s::from_fn(q, |j| k(j).r.x_axis),
                Vec3s::from_fn(q, |j| k(j).r.y_axis),
                Vec3s::from_fn(q, |j| k(j).r.z_axis),
            ],
            s: Vec3s::from_fn(q, |j| k(j).s),
            pi: Vec3s::from_fn(q, |j| k(j).pi),
            s2: Vec3s::from_fn(q, |j| k(j).s * k(j).s),
            pi2: Vec3s::from_fn(q, |j| k(j).pi * k(j).pi),
            rho: q.load(std::array::from_fn(|j| k(j).rho)),
        }
    }
}

/// A group's relay points and normals in lanes: lane j holds the group's pair
/// `j % LANES` (eight lanes repeat the four).
struct Sides<V> {
    xi: Vec3s<V>,
    ni: Vec3s<V>,
    xd: Vec3s<V>,
    nd: Vec3s<V>,
}

impl<V: Copy> Sides<V> {
    #[inline(always)]
    fn load<const N: usize, Q: simd::Lanes<N, V = V>>(q: Q, group: &PairGroup) -> Self {
        let at = |a: &[Lanes; 3]| Vec3s::from_fn(q, |j| lane(a, j % LANES));
        Self {
            xi: at(&group.xi),
            ni: at(&group.ni),
            xd: at(&group.xd),
            nd: at(&group.nd),
        }
    }
}

/// Primitives' geometry against the pairs of a [`PairGroup`], in registers: what
/// [`evaluate`](super::kernel::evaluate) computes, lane by lane.
struct Geometry<V> {
    di: V,
    dd: V,
    ui: Vec3s<V>,
    ud: Vec3s<V>,
    wi: Vec3s<V>,
    wd: Vec3s<V>,
    wv: Vec3s<V>,
    gi: V,
    gd: V,
    ai: V,
    ad: V,
    base: V,
    amplitude: V,
    sigma: V,
}

/// The geometry of the primitives `k` against the pairs `sides` (whose detection side is
/// the illumination side's when `shared`). Cheap next to keeping it: the forward pass
/// keeps only the pulses, and the backward pass computes this again.
#[inline(always)]
fn geometry<const N: usize, Q: simd::Lanes<N>>(
    q: Q,
    k: &Prims<Q::V>,
    sides: &Sides<Q::V>,
    shared: bool,
    axis: &TimeAxis,
    opt: &RenderOptions,
) -> Geometry<Q::V> {
    let (di, inv_di, ui, gi, wi, ai) = side(q, k, sides.xi, sides.ni, opt.use_ni);
    let (dd, inv_dd, ud, gd, wd, ad) = if shared {
        (di, inv_di, ui, gi, wi, ai)
    } else {
        side(q, k, sides.xd, sides.nd, opt.use_nd)
    };
    let wv = wi.add(q, wd);
    let base = q.mul(
        q.mul(q.mul(q.mul(q.splat(opt.gain), ai), ad), q.mul(inv_di, inv_di)),
        q.mul(inv_dd, inv_dd),
    );
    let amplitude = q.mul(q.mul(q.mul(base, k.rho), gi), gd);
    let floor = SIGMA_FLOOR_BINS * axis.width;
    let swv = k.s.mul(q, wv);
    let sigma = q.sqrt(q.add(
        q.add(swv.dot(q, swv), q.splat(opt.sigma_sys * opt.sigma_sys)),
        q.splat(floor * floor),
    ));
    Geometry {
        di,
        dd,
        ui,
        ud,
        wi,
        wd,
        wv,
        gi,
        gd,
        ai,
        ad,
        base,
        amplitude,
        sigma,
    }
}

/// One relay point's side of [`geometry`] (illumination or detection): distance to the
/// primitive's centre, its inverse, the direction, the relay cosine (1 when `cosine` is
/// off), the direction in the primitive's frame and the projected area.
#[allow(clippy::type_complexity)]
#[inline(always)]
fn side<const N: usize, Q: simd::Lanes<N>>(
    q: Q,
    k: &Prims<Q::V>,
    at: Vec3s<Q::V>,
    normal: Vec3s<Q::V>,
    cosine: bool,
) -> (Q::V, Q::V, Vec3s<Q::V>, Q::V, Vec3s<Q::V>, Q::V) {
    let to = k.x.sub(q, at);
    let d = q.sqrt(to.dot(q, to));
    let one = q.splat(1.0);
    let inv = q.div(one, d);
    let u = to.scale(q, inv);
    let g = if cosine { normal.dot(q, u) } else { one };
    let w = mat_t_vec(q, &k.cols, u);
    let pw = k.pi.mul(q, w);
    let a = q.sqrt(pw.dot(q, pw));
    (d, inv, u, g, w, a)
}

/// One primitive's pulse in each pair of a [`PairGroup`]: `None` where it cannot
/// contribute (as [`evaluate`](super::kernel::evaluate) returns `None`), and past the
/// group's pairs.
pub(crate) type Pulses = [Option<Window>; LANES];

/// [`evaluate`](super::kernel::evaluate) of `k` against every pair of `group`, four lanes
/// at once; `None` when it contributes to none of them.
#[cfg(test)]
pub(crate) fn evaluate_group<Q: Quad>(
    q: Q,
    k: &Kernel,
    group: &PairGroup,
    axis: &TimeAxis,
    opt: &RenderOptions,
) -> Option<Pulses> {
    let mut slot = None;
    evaluate_group_into(q, k, group, axis, opt, &mut slot);
    slot
}

/// [`evaluate_group`] written into `slot` where it is to stay (a kept evaluation's
/// place in its vector, or one reused slot): the four pulses (about 400 bytes) are
/// built there instead of aside and moved (5–7 % of a synthesis, measured).
#[inline(always)]
pub(crate) fn evaluate_group_into<Q: Quad>(
    q: Q,
    k: &Kernel,
    group: &PairGroup,
    axis: &TimeAxis,
    opt: &RenderOptions,
    slot: &mut Option<Pulses>,
) {
    evaluate_lanes_into::<4, _, 1>(q, &[k], group, axis, opt, [slot]);
}

/// [`evaluate_group_into`] of two primitives at once, `a` into `slot_a` and `b` into
/// `slot_b`, in eight lanes (one AVX-512 vector): the same bits as one at a time.
#[inline(always)]
pub(crate) fn evaluate_two_into<Q: Quad>(
    q: Q,
    [a, b]: [&Kernel; 2],
    group: &PairGroup,
    axis: &TimeAxis,
    opt: &RenderOptions,
    [slot_a, slot_b]: [&mut Option<Pulses>; 2],
) {
    evaluate_lanes_into::<8, _, 2>(q.oct(), &[a, b], group, axis, opt, [slot_a, slot_b]);
}

/// The primitives `ks` (one or two: a chunk of a primitive list) against `group`: the
/// first's pulses into `slot_a`, the second's into `slot_b` (`None` when there is none).
#[inline(always)]
pub(crate) fn evaluate_chunk_into<Q: Quad>(
    q: Q,
    ks: &[Kernel],
    group: &PairGroup,
    axis: &TimeAxis,
    opt: &RenderOptions,
    [slot_a, slot_b]: [&mut Option<Pulses>; 2],
) {
    match ks {
        [a, b] => evaluate_two_into(q, [a, b], group, axis, opt, [slot_a, slot_b]),
        [a] => {
            evaluate_group_into(q, a, group, axis, opt, slot_a);
            *slot_b = None;
        }
        _ => unreachable!("a chunk of one or two primitives"),
    }
}

/// The primitives `kernels` (lane j holding `kernels[j / LANES]`) against `group`, each
/// primitive's pulses into its slot (`None` where it reaches none of the pairs).
#[inline(always)]
fn evaluate_lanes_into<const N: usize, Q: simd::Lanes<N>, const S: usize>(
    q: Q,
    kernels: &[&Kernel; S],
    group: &PairGroup,
    axis: &TimeAxis,
    opt: &RenderOptions,
    slots: [&mut Option<Pulses>; S],
) {
    let prims = Prims::load(q, kernels);
    let sides = Sides::load(q, group);
    let g = geometry(q, &prims, &sides, group.shares_sides(opt), axis, opt);
    let mut slots = slots;
    let mut any = [false; S];
    {
        let mut pulses = slots.each_mut().map(|slot| slot.insert([None; LANES]));
        Window::lanes_into(q, g.amplitude, q.add(g.di, g.dd), g.sigma, axis, opt, &mut pulses);
        let (di, dd, gi, gd) = (q.store(g.di), q.store(g.dd), q.store(g.gi), q.store(g.gd));
        for j in 0..N {
            let w = &mut pulses[j / LANES][j % LANES];
            if j % LANES >= group.used
                || di[j] < opt.min_distance
                || dd[j] < opt.min_distance
                || gi[j] <= 0.0
                || gd[j] <= 0.0
            {
                *w = None;
            }
            any[j / LANES] |= w.is_some();
        }
    }
    for (slot, any) in slots.into_iter().zip(any) {
        if !any {
            *slot = None;
        }
    }
}

/// [`Evaluation::backward`](super::kernel::Evaluation::backward) of `k` for every lane
/// of `group` with a pulse (`pulses`, from [`evaluate_group`]), added to `grad` in
/// lane order. `dl` holds `∂loss/∂τ̂` of the group's pairs, `axis.bins` a pair.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn backward_group<Q: Quad>(
    q: Q,
    k: &Kernel,
    group: &PairGroup,
    pulses: &Pulses,
    axis: &TimeAxis,
    opt: &RenderOptions,
    dl: &[f64],
    grad: &mut PhysicalGrad,
) {
    backward_lanes::<4, _, _, 1>(q, q, &[k], group, [pulses], axis, opt, dl, [grad]);
}

/// [`backward_group`] of two primitives at once, in eight lanes (one AVX-512 vector):
/// the same bits as one at a time.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn backward_two<Q: Quad>(
    q: Q,
    kernels: [&Kernel; 2],
    group: &PairGroup,
    pulses: [&Pulses; 2],
    axis: &TimeAxis,
    opt: &RenderOptions,
    dl: &[f64],
    grads: [&mut PhysicalGrad; 2],
) {
    backward_lanes::<8, _, _, 2>(q, q.oct(), &kernels, group, pulses, axis, opt, dl, grads);
}

/// The backward pass of the primitives `kernels` (lane j holding `kernels[j / LANES]`,
/// its pulses `pulses[j / LANES]`) against `group`, each primitive's gradient added to
/// its own of `grads` in lane order. `quad` runs the per-bin sums, `q` the lanes.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn backward_lanes<const N: usize, Q: Quad, L: simd::Lanes<N>, const S: usize>(
    quad: Q,
    q: L,
    kernels: &[&Kernel; S],
    group: &PairGroup,
    pulses: [&Pulses; S],
    axis: &TimeAxis,
    opt: &RenderOptions,
    dl: &[f64],
    grads: [&mut PhysicalGrad; S],
) {
    // The per-bin sums, a lane at a time; lanes without a pulse get finite stand-ins
    // and are skipped below.
    let (mut s_cdf, mut s_pdf, mut s_zpdf) = ([0.0; N], [0.0; N], [0.0; N]);
    for j in 0..N {
        if let Some(w) = &pulses[j / LANES][j % LANES] {
            let p = j % LANES;
            (s_cdf[j], s_pdf[j], s_zpdf[j]) = w.sums(quad, axis, &dl[p * axis.bins..(p + 1) * axis.bins]);
        }
    }
    let k = Prims::load(q, kernels);
    let sides = Sides::load(q, group);
    // On a group whose sides are shared (`PairGroup::shares_sides`), every detection
    // term below equals its illumination twin bit for bit, so it is reused.
    let shared = group.shares_sides(opt);
    let geo = geometry(q, &k, &sides, shared, axis, opt);
    let inv = q.div(q.splat(1.0), geo.sigma);
    let amp = geo.amplitude;
    let minus_one = q.splat(-1.0);
    let g_amp = q.load(s_cdf);
    let g_mu = q.mul(q.mul(q.mul(minus_one, amp), q.load(s_pdf)), inv);
    let g_sigma = q.mul(q.mul(q.mul(minus_one, amp), q.load(s_zpdf)), inv);

    let (base, gi, gd) = (geo.base, geo.gi, geo.gd);
    let g_base = q.mul(g_amp, base);
    let c_rho = q.mul(q.mul(g_base, gi), gd);
    let rho = k.rho;
    let zero = q.splat(0.0);
    let g_gi = if opt.use_ni {
        q.mul(q.mul(g_base, rho), gd)
    } else {
        zero
    };
    let g_gd = if opt.use_nd {
        q.mul(q.mul(g_base, rho), gi)
    } else {
        zero
    };

    let (ai, ad) = (geo.ai, geo.ad);
    let (wi, wd, wv) = (geo.wi, geo.wd, geo.wv);
    let g_amp_amp = q.mul(g_amp, amp);
    let g_wi = wi.mul(q, k.pi2).scale(q, q.div(g_amp_amp, q.mul(ai, ai)));
    let g_wd = if shared {
        g_wi
    } else {
        wd.mul(q, k.pi2).scale(q, q.div(g_amp_amp, q.mul(ad, ad)))
    };
    let g_sigma_inv = q.mul(g_sigma, inv);
    let s = k.s;
    let g_wv = k.s2.mul(q, wv).scale(q, g_sigma_inv);

    let pi = k.pi;
    let c_si = area_ds(q, wi, ai, pi, s).scale(q, q.div(g_amp_amp, ai));
    let c_sd = if shared {
        c_si
    } else {
        area_ds(q, wd, ad, pi, s).scale(q, q.div(g_amp_amp, ad))
    };
    let c_s = c_si
        .add(q, c_sd)
        .add(q, s.mul(q, wv).mul(q, wv).scale(q, g_sigma_inv));

    let (ui, ud) = (geo.ui, geo.ud);
    let v = ui.add(q, ud);
    // Column j of outer(a, b) is a b_j.
    let c_r0 = ui
        .scale(q, g_wi.x)
        .add(q, ud.scale(q, g_wd.x))
        .add(q, v.scale(q, g_wv.x));
    let c_r1 = ui
        .scale(q, g_wi.y)
        .add(q, ud.scale(q, g_wd.y))
        .add(q, v.scale(q, g_wv.y));
    let c_r2 = ui
        .scale(q, g_wi.z)
        .add(q, ud.scale(q, g_wd.z))
        .add(q, v.scale(q, g_wv.z));

    let cols = &k.cols;
    let rg_v = mat_vec(q, cols, g_wv);
    let g_ui = mat_vec(q, cols, g_wi)
        .add(q, rg_v)
        .add(q, sides.ni.scale(q, g_gi));
    let (di, dd) = (geo.di, geo.dd);
    let minus_two = q.splat(-2.0);
    let g_di = q.add(q.div(q.mul(q.mul(minus_two, g_amp), amp), di), g_mu);
    let c_xi = centre_grad(q, ui, g_ui, g_di, di);
    // Shared sides: g_gd = g_base ρ g_i is g_gi = g_base ρ g_d, and n_d = n_i.
    let c_xd = if shared {
        c_xi
    } else {
        let g_ud = mat_vec(q, cols, g_wd)
            .add(q, rg_v)
            .add(q, sides.nd.scale(q, g_gd));
        let g_dd = q.add(q.div(q.mul(q.mul(minus_two, g_amp), amp), dd), g_mu);
        centre_grad(q, ud, g_ud, g_dd, dd)
    };

    // Into each primitive's gradient, lane by lane in the batch's order.
    let c_rho = q.store(c_rho);
    let c_s = c_s.store(q);
    let c_r = [c_r0.store(q), c_r1.store(q), c_r2.store(q)];
    let (c_xi, c_xd) = (c_xi.store(q), c_xd.store(q));
    for j in 0..N {
        if pulses[j / LANES][j % LANES].is_none() {
            continue;
        }
        let grad = &mut *grads[j / LANES];
        grad.rho += c_rho[j];
        grad.s += lane(&c_s, j);
        grad.r.x_axis += lane(&c_r[0], j);
        grad.r.y_axis += lane(&c_r[1], j);
        grad.r.z_axis += lane(&c_r[2], j);
        grad.x += lane(&c_xi, j);
        grad.x += lane(&c_xd, j);
    }
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, DQuat};
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::gtr::kernel::{Evaluation, evaluate};

    /// Primitives and pairs that exercise every branch: oblique and edge-on views,
    /// scales from sub-bin to wide, pairs behind a relay point's tangent plane, a
    /// primitive on the relay, windows cut by either end of the axis.
    fn scene(rng: &mut impl Rng) -> (Vec<Kernel>, Vec<Pair>) {
        let mut kernels: Vec<Kernel> = (0..60)
            .map(|_| {
                let axis =
                    DVec3::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), 1.0).normalize();
                let r = DMat3::from_quat(DQuat::from_axis_angle(axis, rng.random_range(-3.0..3.0)));
                let s = DVec3::new(
                    10f64.powf(rng.random_range(-4.0..-1.3)),
                    10f64.powf(rng.random_range(-4.0..-1.3)),
                    10f64.powf(rng.random_range(-4.0..-1.3)),
                );
                let x = DVec3::new(
                    rng.random_range(-0.6..0.6),
                    rng.random_range(-0.6..0.6),
                    rng.random_range(-0.2..1.6),
                );
                Kernel::new(x, r, s, rng.random_range(0.0..2.0))
            })
            .collect();
        kernels.push(Kernel::new(
            DVec3::new(0.1, 0.1, 0.0),
            DMat3::IDENTITY,
            DVec3::splat(0.01),
            1.0,
        ));
        let pairs = (0..11)
            .map(|i| {
                let xi = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
                let xd = if i % 3 == 0 {
                    xi
                } else {
                    DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0)
                };
                let tilt = DVec3::new(rng.random_range(-0.6..0.6), 0.0, 1.0).normalize();
                Pair {
                    xi,
                    ni: DVec3::Z,
                    xd,
                    nd: tilt,
                }
            })
            .chain([Pair::confocal(DVec3::new(0.1, 0.1, 0.0), DVec3::Z)])
            .collect::<Vec<_>>();
        // A run of confocal pairs on tilted normals, so that whole groups share their
        // two sides (`PairGroup::shares_sides`).
        let confocal = (0..9).map(|_| {
            let x = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
            let n = DVec3::new(rng.random_range(-0.6..0.6), rng.random_range(-0.6..0.6), 1.0).normalize();
            Pair::confocal(x, n)
        });
        let pairs = pairs.into_iter().chain(confocal).collect();
        (kernels, pairs)
    }

    fn same_pulse(a: &Window, b: &Window) -> bool {
        a.amplitude.to_bits() == b.amplitude.to_bits()
            && a.mu.to_bits() == b.mu.to_bits()
            && a.sigma.to_bits() == b.sigma.to_bits()
            && (a.lo, a.hi) == (b.lo, b.hi)
            && a.series_bits() == b.series_bits()
    }

    fn grad_bits(g: &PhysicalGrad) -> Vec<u64> {
        let r = g.r.to_cols_array();
        [g.x.to_array().as_slice(), &r, &g.s.to_array(), &[g.rho]]
            .concat()
            .into_iter()
            .map(f64::to_bits)
            .collect()
    }

    /// Every lane's pulse and the group's gradient are bit-for-bit what the one-pair
    /// path gives, for groups of 1 to 4 pairs, with and without the relay cosines and
    /// the instrument's jitter, on the portable arrays and on this CPU's vectors; and
    /// two primitives at once in eight lanes give each one's bits alone.
    fn check<Q: Quad>(q: Q) -> (usize, usize, usize) {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(7);
        let (kernels, pairs) = scene(&mut rng);
        let axis = TimeAxis {
            start: 0.3,
            width: 0.005,
            bins: 400,
        };
        let dl: Vec<f64> = (0..LANES * axis.bins)
            .map(|_| rng.random_range(-1.0..1.0))
            .collect();
        let (mut compared, mut wide, mut shared, mut twos) = (0, 0, 0, 0);
        for (use_ni, use_nd, sigma_sys) in [
            (true, true, 0.0),
            (false, true, 0.003),
            (true, false, 0.0),
            (false, false, 0.0),
        ] {
            let opt = RenderOptions {
                use_ni,
                use_nd,
                sigma_sys,
                ..RenderOptions::default()
            };
            for used in 1..=LANES {
                for first in (0..pairs.len() - used).step_by(used) {
                    let members: Vec<&Pair> = pairs[first..first + used].iter().collect();
                    let group = PairGroup::new(&members);
                    shared += usize::from(group.shares_sides(&opt));
                    for k in &kernels {
                        let one: Vec<Option<Evaluation>> =
                            members.iter().map(|p| evaluate(k, p, &axis, &opt)).collect();
                        let lanes = evaluate_group(q, k, &group, &axis, &opt);
                        let Some(pulses) = lanes else {
                            assert!(one.iter().all(Option::is_none));
                            continue;
                        };
                        assert!(pulses[used..].iter().all(Option::is_none));
                        let mut want = PhysicalGrad::default();
                        for (j, e) in one.iter().enumerate() {
                            match (e, &pulses[j]) {
                                (None, None) => {}
                                (Some(e), Some(w)) => {
                                    assert!(same_pulse(&e.window, w), "{:?} vs {:?}", e.window, w);
                                    e.backward(
                                        k,
                                        members[j],
                                        &axis,
                                        &opt,
                                        &dl[j * axis.bins..(j + 1) * axis.bins],
                                        &mut want,
                                    );
                                    compared += 1;
                                    wide += usize::from(w.series_bits().is_some());
                                }
                                (e, w) => panic!("lane {j}: one pair {e:?}, lanes {w:?}"),
                            }
                        }
                        let mut got = PhysicalGrad::default();
                        backward_group(q, k, &group, &pulses, &axis, &opt, &dl, &mut got);
                        assert_eq!(grad_bits(&got), grad_bits(&want), "{got:?} vs {want:?}");
                    }
                    // Two primitives at once, in eight lanes: each one's pulses and
                    // gradient are its bits alone.
                    for two in kernels.chunks_exact(2) {
                        let (a, b) = (&two[0], &two[1]);
                        let alone = [
                            evaluate_group(q, a, &group, &axis, &opt),
                            evaluate_group(q, b, &group, &axis, &opt),
                        ];
                        let mut together = [None, None];
                        evaluate_two_into(q, [a, b], &group, &axis, &opt, together.each_mut());
                        for (one, both) in alone.iter().zip(&together) {
                            match (one, both) {
                                (None, None) => {}
                                (Some(x), Some(y)) => {
                                    for (x, y) in x.iter().zip(y) {
                                        match (x, y) {
                                            (None, None) => {}
                                            (Some(x), Some(y)) => assert!(same_pulse(x, y), "{x:?} vs {y:?}"),
                                            (x, y) => panic!("alone {x:?}, together {y:?}"),
                                        }
                                    }
                                }
                                (x, y) => panic!("alone {x:?}, together {y:?}"),
                            }
                        }
                        if let [Some(p_a), Some(p_b)] = &alone {
                            let mut want = [PhysicalGrad::default(); 2];
                            backward_group(q, a, &group, p_a, &axis, &opt, &dl, &mut want[0]);
                            backward_group(q, b, &group, p_b, &axis, &opt, &dl, &mut want[1]);
                            let mut got = [PhysicalGrad::default(); 2];
                            backward_two(q, [a, b], &group, [p_a, p_b], &axis, &opt, &dl, got.each_mut());
                            for (got, want) in got.iter().zip(&want) {
                                assert_eq!(grad_bits(got), grad_bits(want), "{got:?} vs {want:?}");
                            }
                            twos += 1;
                        }
                    }
                }
            }
        }
        // Groups of every size whose sides are shared, under both cosine settings that
        // share them.
        assert!(shared >= 8, "only {shared} groups with shared sides");
        (compared, wide, twos)
    }

    #[test]
    fn four_and_eight_lanes_give_the_one_pair_bits() {
        let (compared, wide, twos) = check(crate::simd::Portable);
        // Most primitive–pair combinations contribute; the culled ones are checked too.
        assert!(compared > 1000, "only {compared} contributing evaluations");
        assert!(
            wide > 100 && wide < compared,
            "{wide} of {compared} on the series"
        );
        assert!(
            twos > 100,
            "only {twos} groups with two primitives' gradients compared"
        );
        let mut ran = 0;
        #[cfg(target_arch = "x86_64")]
        if let Some(v3) = crate::simd::v3() {
            assert_eq!(check(v3), (compared, wide, twos));
            ran += 1;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(v4) = crate::simd::v4() {
            assert_eq!(check(v4), (compared, wide, twos));
            ran += 1;
        }
        if ran < 2 {
            eprintln!("skipped in part: this CPU lacks AVX2 + FMA or AVX-512 ({ran} of 2 ran)");
        }
    }

    /// `render_pairs` gives, on every pair, the bits of the one-pair path's evaluations
    /// accumulated in the primitives' order, for any number of pairs (whole groups and
    /// a partial one).
    #[test]
    fn rendering_four_pairs_at_once_gives_the_one_pair_bits() {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(11);
        let (kernels, pairs) = scene(&mut rng);
        let axis = TimeAxis {
            start: 0.3,
            width: 0.005,
            bins: 400,
        };
        let opt = RenderOptions::default();
        for n in [1, 4, 7, pairs.len()] {
            let mut lanes = vec![1.0; n * axis.bins];
            crate::gtr::render_pairs(&kernels, &pairs[..n], &axis, &opt, &mut lanes);
            assert!(lanes.iter().any(|&v| v > 0.0));
            for (p, got) in pairs[..n].iter().zip(lanes.chunks(axis.bins)) {
                let mut want = vec![0.0; axis.bins];
                for k in &kernels {
                    if let Some(e) = evaluate(k, p, &axis, &opt) {
                        e.accumulate(&axis, &mut want);
                    }
                }
                assert_eq!(
                    got.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                    want.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
                );
            }
        }
    }
}

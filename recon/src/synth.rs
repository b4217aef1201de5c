//! Virtual confocal synthesis: the optimised Gaussians rendered, with the same forward
//! model they were fitted with, as a dense confocal scan of a virtual planar relay, so a
//! conventional solver (LCT, RSD) can turn them into a volume.
use rayon::prelude::*;

use crate::gpu::Compute;
use crate::gtr::{Kernel, RenderOptions, render_pairs};
use crate::relay::VirtualRelay;
use crate::solver::{
    FrameVolume, LctSettings, PlanarScan, SolverError, VIRTUAL_SCAN_SNR, check_memory, lct_of_apexes,
};
use crate::special::NORMAL;
use crate::transient::{Pair, TimeAxis, TransientError, TransientSet};
use crate::volume::VolumeGrid;
use glam::DVec3;

/// A synthesised confocal scan and the grid it lies on.
#[derive(Clone, Debug)]
pub struct VirtualScan {
    /// One confocal transient per grid point, row by row.
    pub set: TransientSet,
    /// The grid (cells in pair order).
    pub scan: PlanarScan,
}

/// A time axis for synthesis on `relay` that starts at path length 0 and reaches twice
/// the distance from the relay to the farthest corner of `volume` (plus 5 %), in `bins`
/// bins.
pub fn default_axis(relay: &VirtualRelay, volume: &VolumeGrid, bins: usize) -> TimeAxis {
    let mut far: f64 = 0.0;
    for corner in 0..8 {
        let c = glam::DVec3::new(
            volume.x[corner & 1],
            volume.y[(corner >> 1) & 1],
            volume.z[(corner >> 2) & 1],
        );
        for (ix, iy) in [(0, 0), (relay.resolution[0] - 1, 0), (0, relay.resolution[1] - 1)] {
            far = far.max(c.distance(relay.point(ix, iy)));
        }
        far = far.max(c.distance(relay.point(relay.resolution[0] - 1, relay.resolution[1] - 1)));
    }
    TimeAxis {
        start: 0.0,
        width: 2.0 * far * 1.05 / bins.max(1) as f64,
        bins: bins.max(1),
    }
}

/// Renders confocal transients at every point of `relay` from `kernels`, in parallel
/// over groups of four grid points (one vector lane each).
pub fn synthesise(
    kernels: &[Kernel],
    relay: &VirtualRelay,
    axis: TimeAxis,
    opt: &RenderOptions,
) -> Result<VirtualScan, TransientError> {
    match synthesise_on(&Compute::Cpu, kernels, relay, axis, opt) {
        Ok(scan) => Ok(scan),
        Err(SynthError::Transient(e)) => Err(e),
        Err(SynthError::Gpu(e)) => unreachable!("the CPU path has no GPU to fail: {e}"),
    }
}

/// Why [`synthesise_on`] failed.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// The rendered transients do not make a set.
    #[error(transparent)]
    Transient(#[from] TransientError),
    /// The GPU failed.
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
}

/// [`synthesise`] on `compute`: on a GPU, [`crate::gpu::render_pairs`] in f32.
pub fn synthesise_on(
    compute: &Compute,
    kernels: &[Kernel],
    relay: &VirtualRelay,
    axis: TimeAxis,
    opt: &RenderOptions,
) -> Result<VirtualScan, SynthError> {
    let pairs: Vec<Pair> = relay
        .points()
        .into_iter()
        .map(|x| Pair::confocal(x, relay.normal))
        .collect();
    let bins = axis.bins;
    if let Some(gpu) = compute.gpu() {
        let histograms = crate::gpu::render_pairs(gpu, kernels, &pairs, &axis, opt)?;
        return scan(relay, axis, &pairs, &histograms);
    }
    let mut histograms = vec![0.0f32; pairs.len() * bins];
    const GROUP: usize = 4;
    histograms
        .par_chunks_mut(GROUP * bins)
        .zip(pairs.par_chunks(GROUP))
        .for_each_init(
            || vec![0.0f64; GROUP * bins],
            |buf, (out, pairs)| {
                let buf = &mut buf[..pairs.len() * bins];
                render_pairs(kernels, pairs, &axis, opt, buf);
                for (o, v) in out.iter_mut().zip(buf.iter()) {
                    *o = *v as f32;
                }
            },
        );
    scan(relay, axis, &pairs, &histograms)
}

/// The scan of `relay` whose transients, `axis.bins` a pair, are `histograms`.
fn scan(
    relay: &VirtualRelay,
    axis: TimeAxis,
    pairs: &[Pair],
    histograms: &[f32],
) -> Result<VirtualScan, SynthError> {
    let mut set = TransientSet::new(axis)?;
    for (pair, h) in pairs.iter().zip(histograms.chunks(axis.bins)) {
        set.push(*pair, h)?;
    }
    Ok(VirtualScan {
        set,
        scan: PlanarScan::full(*relay),
    })
}

/// Quadrature points along each axis of the virtual relay in [`splat_lct`]'s
/// brightness of a primitive: the mean of its direction-dependent factor over the
/// relay, which varies on the scale of the primitive's depth, far above the relay's
/// pitch. A relay with more points a side than this takes the Gauss–Legendre rule.
const BRIGHTNESS_POINTS: usize = 8;

/// Gauss–Legendre nodes and weights of 8 points on [−1, 1].
const GAUSS_LEGENDRE_8: [(f64, f64); 8] = [
    (-0.960_289_856_497_536_2, 0.101_228_536_290_376_26),
    (-0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (-0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (-0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (0.960_289_856_497_536_2, 0.101_228_536_290_376_26),
];

/// Most bytes of deposits [`splat_lct`] holds at once (the primitives' pulses before
/// they are added into the apexes), besides one primitive's own.
const ROUND_BYTES: usize = 8 << 20;

/// The most memory [`splat_lct`] allocates before LCT's filter for a grid of `cells`
/// points and `m` bins from path length zero: the apexes in `f32`, and a round's
/// deposits, 8 MiB or one primitive's when it alone is larger (at most a
/// whole window of `f32` and a 32-byte head at every point). Saturating, so a hostile
/// size is never small. `periscope check` and the splat's own cap read the same
/// figure.
pub fn splat_bytes(cells: usize, m: usize) -> usize {
    let apexes = cells.saturating_mul(m).saturating_mul(4);
    let one = apexes.saturating_add(cells.saturating_mul(32));
    apexes.saturating_add(one.max(ROUND_BYTES))
}

/// The footprint's sub-samples reach this many standard deviations from its centre.
const FOOTPRINT_SIGMAS: f64 = 3.5;

/// LCT of the virtual confocal scan of `relay` that `kernels` would render, without
/// rendering it: each primitive is splatted once onto the scan's cells (its footprint
/// on the grid, and under each cell the profile in depth of the part of it there) and
/// the whole is filtered once by what LCT's Wiener filter makes of a light cone
/// ([`lct_of_apexes`]). Rendering 64 × 64 transients evaluates every primitive at
/// every point; this touches each primitive's own cells only. It runs on the CPU
/// whatever the compute device.
///
/// What it keeps from the renderer ([`RenderOptions`]): the gain and albedo; the
/// cosines (`use_ni`, `use_nd`) and the projected areas A⊥(u)², each primitive's taken
/// as their mean over the relay's points after LCT's radiometric weight ℓ^falloff
/// (the scan would carry each point's own); `min_distance`; the primitive's whole
/// covariance (a tilted primitive's depth changes across its footprint; its depth
/// spread under each cell becomes a pulse of the same mean and variance, widened by
/// `sigma_sys`); the pulse window of `window_sigmas`. What it does not: the scan's
/// edge. The cones here run on past the relay's border, so a primitive near the
/// border is not dimmed as the finite scan's LCT dims it; they wrap around the padded
/// grid as LCT's filter assumes.
///
/// `axis` must start at path length 0 (as [`default_axis`]'s does); the volume is on
/// the grid of [`PlanarScan::reaching`] `grid`, as [`crate::solver::lct`] gives it.
/// `settings.snr` not set: [`VIRTUAL_SCAN_SNR`], the Wiener filter's after 3D-GTR.
pub fn splat_lct(
    kernels: &[Kernel],
    relay: &VirtualRelay,
    grid: &VolumeGrid,
    axis: TimeAxis,
    opt: &RenderOptions,
    settings: &LctSettings,
) -> Result<FrameVolume, SolverError> {
    settings.validate()?;
    if axis.start != 0.0 || axis.bins == 0 || !(axis.width > 0.0) {
        return Err(SolverError::Axis(format!(
            "the splatted LCT needs bins from path length 0; this axis starts at {} m with {} bins of {} m",
            axis.start, axis.bins, axis.width
        )));
    }
    let scan = PlanarScan::full(*relay).reaching(grid);
    let (m, w) = (axis.bins, axis.width);
    let lmax = m as f64 * w;
    let [nx, ny] = scan.relay.resolution;

    // Quadrature of the brightness over the relay's rectangle: Gauss–Legendre, or the
    // relay's own points where it has fewer a side.
    let nodes = |n: usize| -> Vec<(f64, f64)> {
        if n <= BRIGHTNESS_POINTS {
            (0..n)
                .map(|i| ((i as f64 + 0.5) / n as f64 - 0.5, 1.0 / n as f64))
                .collect()
        } else {
            GAUSS_LEGENDRE_8
                .iter()
                .map(|&(x, w)| (0.5 * x, 0.5 * w))
                .collect()
        }
    };
    let (qa, qb) = (nodes(relay.resolution[0]), nodes(relay.resolution[1]));
    let quad: Vec<(DVec3, f64)> = qb
        .iter()
        .flat_map(|&(b, wb)| {
            qa.iter().map(move |&(a, wa)| {
                (
                    relay.centre + relay.u * (a * relay.size[0]) + relay.v * (b * relay.size[1]),
                    wa * wb,
                )
            })
        })
        .collect();
    let splat = Splat {
        frame: scan.relay,
        per_cell: scan.relay.spacing().map(|p| 1.0 / p),
        normal: relay.normal,
        quad,
        opt: *opt,
        falloff: settings.falloff,
        lmax,
        bins: m,
        width: w,
    };
    check_memory("splatted LCT", splat_bytes(nx * ny, m))?;
    // Each primitive's footprint first (geometry only), then rounds of them splatted in
    // parallel and added in order: the sums are the same on any number of threads, and
    // a round's deposits stay within `ROUND_BYTES` (and one primitive's) by their
    // estimate.
    let plans: Vec<Option<Footprint>> = kernels.par_iter().map(|k| splat.plan(k)).collect();
    let mut cube = vec![0.0f32; nx * ny * m];
    let mut start = 0;
    while start < plans.len() {
        let (mut end, mut bytes) = (start, 0usize);
        while end < plans.len() {
            let b = plans[end].as_ref().map_or(0, |f| f.bytes);
            if end > start && bytes + b > ROUND_BYTES {
                break;
            }
            bytes += b;
            end += 1;
        }
        const CHUNK: usize = 16;
        let parts: Vec<Deposits> = plans[start..end]
            .par_chunks(CHUNK)
            .map(|chunk| {
                let mut d = Deposits::default();
                for f in chunk.iter().flatten() {
                    splat.deposit(f, &mut d);
                }
                d
            })
            .collect();
        for part in &parts {
            for &(cell, first, ref range) in &part.heads {
                let line = &mut cube[cell * m + first..];
                for (c, v) in line.iter_mut().zip(&part.values[range.clone()]) {
                    *c += *v;
                }
            }
        }
        start = end;
    }
    lct_of_apexes(cube, &scan, m, w, settings.snr.unwrap_or(VIRTUAL_SCAN_SNR))
}

/// One chunk of primitives' apex profiles: (cell, first bin, range in `values`).
#[derive(Default)]
struct Deposits {
    heads: Vec<(usize, usize, std::ops::Range<usize>)>,
    values: Vec<f32>,
}

/// Where one primitive lands on the grid ([`Splat::plan`]).
struct Footprint {
    /// Its brightness ([`Splat::brightness`]).
    weight: f64,
    /// Its centre in the frame: along u, along v, depth.
    centre: [f64; 3],
    /// The change of its depth per metre along u and v, at a given (u, v).
    slope: [f64; 2],
    /// The variance of its depth at a given (u, v).
    var: f64,
    /// The standard deviations of its footprint along its principal axes.
    spread: [f64; 2],
    /// The principal axes, in (u, v).
    dirs: [[f64; 2]; 2],
    /// Sub-samples along each principal axis.
    counts: [usize; 2],
    /// The window of cells it reaches, inclusive: (column, row) from and to.
    lo: [usize; 2],
    hi: [usize; 2],
    /// Its deposits' size, estimated from the window and the depth's whole spread.
    bytes: usize,
}

/// What [`splat_lct`] needs to splat one primitive.
struct Splat {
    /// The scan's grid (the relay widened to the volume).
    frame: VirtualRelay,
    /// Cells per metre along u and v.
    per_cell: [f64; 2],
    /// The relay's normal (the confocal points' n_i = n_d).
    normal: DVec3,
    /// Quadrature points of the brightness and their weights (summing to 1).
    quad: Vec<(DVec3, f64)>,
    opt: RenderOptions,
    falloff: f64,
    lmax: f64,
    bins: usize,
    width: f64,
}

impl Splat {
    /// The mean over the relay of what a confocal point at q sees of `k` per unit of
    /// pulse mass, after LCT's weight (ℓ/ℓmax)^falloff: g ρ γ_i γ_d A⊥(u)² ℓ^n / d⁴.
    fn brightness(&self, k: &Kernel) -> f64 {
        let o = &self.opt;
        let mut sum = 0.0;
        // ℓ^n / d⁴ = (2/ℓmax)^n d^(n−4): a constant for the diffuse n = 4.
        let scale = (2.0 / self.lmax).powf(self.falloff);
        let power = self.falloff - 4.0;
        for &(q, weight) in &self.quad {
            let d = k.x - q;
            let r = d.length();
            if !(r >= o.min_distance && r > 0.0) {
                continue;
            }
            let u = d / r;
            let c = self.normal.dot(u).max(0.0);
            let gamma = if o.use_ni { c } else { 1.0 } * if o.use_nd { c } else { 1.0 };
            let a = (k.r.transpose() * u) * k.pi;
            let radial = if power == 0.0 { 1.0 } else { r.powf(power) };
            sum += weight * gamma * a.length_squared() * radial;
        }
        o.gain * k.rho * scale * sum
    }

    /// Where and how `k` lands on the grid; `None` when it adds nothing (dark, not a
    /// number, or off the grid).
    fn plan(&self, k: &Kernel) -> Option<Footprint> {
        let weight = self.brightness(k);
        if !(weight > 0.0 && weight.is_finite()) {
            return None;
        }
        let f = &self.frame;
        let [nx, ny] = f.resolution;
        let pitch = f.spacing();
        // The covariance in the frame (u, v, normal): Σ_ij = (M eᵢ)·(M eⱼ), M = S Rᵀ.
        let axes = [f.u, f.v, f.normal];
        let t = axes.map(|e| (k.r.transpose() * e) * k.s);
        let cov = |i: usize, j: usize| t[i].dot(t[j]);
        let p = k.x - f.centre;
        let centre = [p.dot(f.u), p.dot(f.v), p.dot(f.normal)];
        // A floor far below any pitch keeps the footprint's covariance invertible.
        let floor = 1e-12;
        let (saa, sab, sbb) = (cov(0, 0) + floor, cov(0, 1), cov(1, 1) + floor);
        let (saz, sbz, szz) = (cov(0, 2), cov(1, 2), cov(2, 2));
        let det = saa * sbb - sab * sab;
        // The depth under (a, b): z0 + βa (a − a0) + βb (b − b0), with variance `var`.
        let slope = [(sbb * saz - sab * sbz) / det, (saa * sbz - sab * saz) / det];
        let var = (szz - slope[0] * saz - slope[1] * sbz).max(0.0);
        // The footprint's principal axes.
        let half = 0.5 * (saa + sbb);
        let root = (0.25 * (saa - sbb).powi(2) + sab * sab).sqrt();
        let spread = [half + root, (half - root).max(floor)].map(f64::sqrt);
        let theta = 0.5 * (2.0 * sab).atan2(saa - sbb);
        let dirs = [[theta.cos(), theta.sin()], [-theta.sin(), theta.cos()]];
        let all = centre
            .iter()
            .chain(&slope)
            .chain(&spread)
            .chain([var, theta].iter())
            .all(|v| v.is_finite());
        if !all {
            return None;
        }
        // The window of cells the sub-samples can reach, clamped to the grid in floating
        // point before any cast.
        let mut lo = [0usize; 2];
        let mut hi = [0usize; 2];
        for axis in 0..2 {
            let reach =
                FOOTPRINT_SIGMAS * (spread[0] * dirs[0][axis].abs() + spread[1] * dirs[1][axis].abs());
            let n = [nx, ny][axis] as f64;
            let first = self.index(centre[axis] - reach, axis).floor().max(0.0);
            let last = (self.index(centre[axis] + reach, axis).floor() + 1.0).min(n - 1.0);
            if !(first <= last) {
                return None;
            }
            (lo[axis], hi[axis]) = (first as usize, last as usize);
        }
        let cells = (hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1);
        // Sub-samples at most half a pitch apart along each principal axis (and no more
        // than the grid's cells can tell apart).
        let step = 0.5 * pitch[0].min(pitch[1]);
        let cap = 4 * nx.max(ny);
        let counts =
            spread.map(|sd| ((2.0 * FOOTPRINT_SIGMAS * sd / sd.min(step)).ceil() as usize).clamp(1, cap));
        // The deposits' size by the depth's whole spread (its marginal): bins a cell.
        let sigma = (4.0 * szz + self.opt.sigma_sys.powi(2)).sqrt();
        let bins =
            ((2.0 * self.opt.window_sigmas * sigma / self.width).ceil() + 2.0).min(self.bins as f64) as usize;
        Some(Footprint {
            weight,
            centre,
            slope,
            var,
            spread,
            dirs,
            counts,
            lo,
            hi,
            bytes: cells * (bins * 4 + std::mem::size_of::<(usize, usize, std::ops::Range<usize>)>()),
        })
    }

    /// The continuous cell index along `axis` of in-plane coordinate `c`.
    fn index(&self, c: f64, axis: usize) -> f64 {
        (c + 0.5 * self.frame.size[axis]) * self.per_cell[axis] - 0.5
    }

    /// Adds the apex profiles of the primitive `fp` plans to `out`.
    fn deposit(&self, fp: &Footprint, out: &mut Deposits) {
        let nx = self.frame.resolution[0];
        let [a0, b0, z0] = fp.centre;
        let samples = |axis: usize| {
            let (sd, n) = (fp.spread[axis], fp.counts[axis]);
            let h = 2.0 * FOOTPRINT_SIGMAS * sd / n as f64;
            (0..n)
                .map(|j| {
                    let x = (j as f64 + 0.5) * h - FOOTPRINT_SIGMAS * sd;
                    (x, (-0.5 * (x / sd) * (x / sd)).exp())
                })
                .collect::<Vec<_>>()
        };
        let (s1, s2) = (samples(0), samples(1));
        let [e1, e2] = fp.dirs;
        let (lo, hi) = (fp.lo, fp.hi);
        let wx = hi[0] - lo[0] + 1;
        // Per cell of the window: mass, and the first two moments of depth about z0.
        let mut moments = vec![[0.0f64; 3]; wx * (hi[1] - lo[1] + 1)];
        let mut total = 0.0;
        for &(x1, w1) in &s1 {
            for &(x2, w2) in &s2 {
                let ws = w1 * w2;
                total += ws;
                let (da, db) = (x1 * e1[0] + x2 * e2[0], x1 * e1[1] + x2 * e2[1]);
                let dz = fp.slope[0] * da + fp.slope[1] * db;
                let (fx, fy) = (self.index(a0 + da, 0), self.index(b0 + db, 1));
                let (ix, iy) = (fx.floor(), fy.floor());
                let (tx, ty) = (fx - ix, fy - iy);
                for (cx, wcx) in [(ix, 1.0 - tx), (ix + 1.0, tx)] {
                    for (cy, wcy) in [(iy, 1.0 - ty), (iy + 1.0, ty)] {
                        if cx < lo[0] as f64 || cx > hi[0] as f64 || cy < lo[1] as f64 || cy > hi[1] as f64 {
                            continue;
                        }
                        let c = &mut moments[(cy as usize - lo[1]) * wx + (cx as usize - lo[0])];
                        let mass = ws * wcx * wcy;
                        c[0] += mass;
                        c[1] += mass * dz;
                        c[2] += mass * dz * dz;
                    }
                }
            }
        }
        let (m, w) = (self.bins, self.width);
        let sys2 = self.opt.sigma_sys * self.opt.sigma_sys;
        let phi = &*NORMAL;
        for (j, c) in moments.iter().enumerate() {
            if c[0] <= 0.0 {
                continue;
            }
            let mean = c[1] / c[0];
            let spread = (c[2] / c[0] - mean * mean).max(0.0) + fp.var;
            // Path length 2z, its deviation twice the depth's.
            let mu = 2.0 * (z0 + mean);
            let sigma = (4.0 * spread + sys2).sqrt();
            let mass = (fp.weight * c[0] / total) as f32;
            let cell = (lo[1] + j / wx) * nx + lo[0] + j % wx;
            let start = out.values.len();
            if sigma < 1e-3 * w {
                let bin = (mu / w).floor();
                if bin >= 0.0 && bin < m as f64 {
                    out.values.push(mass);
                    out.heads.push((cell, bin as usize, start..start + 1));
                }
                continue;
            }
            let reach = self.opt.window_sigmas * sigma;
            let first = ((mu - reach) / w).floor().max(0.0);
            let last = ((mu + reach) / w).ceil().min(m as f64);
            if !(first < last) {
                continue;
            }
            let mut below = phi.cdf((first * w - mu) / sigma);
            for b in first as usize..last as usize {
                let above = phi.cdf(((b + 1) as f64 * w - mu) / sigma);
                out.values.push(mass * (above - below) as f32);
                below = above;
            }
            out.heads.push((cell, first as usize, start..out.values.len()));
        }
    }
}

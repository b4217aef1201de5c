//! One Gaussian primitive seen from one illumination/detection pair: the forward
//! contribution to the transient and its analytic gradient (DESIGN.md §5).
//!
//! Notation follows the paper. With `w = Rᵀu` the direction in the primitive's local
//! frame and `π_j = Π_{m≠j} s_m`, the projected area is written
//! `A⊥(u) = s1 s2 s3 |S⁻¹Rᵀu| = sqrt(Σ_j (π_j w_j)²)`, a form that stays finite as a
//! scale goes to zero. The amplitude is `A = g ρ γi γd A⊥(ui) A⊥(ud) / (di² dd²)`, the
//! mean path length `μ = di + dd`, the spread `σ² = Σ_j (s_j (Rᵀv)_j)² + σ_sys² + σ_floor²`
//! with `v = ui + ud`; bin `b` receives `A (Φ(z_{b+1}) − Φ(z_b))`, `z = (edge − μ)/σ`.
use glam::{DMat3, DVec3};

use crate::simd::exp_scalar;
use crate::simd::{self, Lanes as _, Quad};
use crate::special::{INV_SQRT_2PI, NORMAL};
use crate::transient::{Pair, TimeAxis};

/// A primitive's physical parameters, derived once per optimiser step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Kernel {
    /// Centre, metres.
    pub x: DVec3,
    /// Rotation; columns are the local axes.
    pub r: DMat3,
    /// Scales (standard deviations along the local axes), metres.
    pub s: DVec3,
    /// Products of the other two scales: `(s1 s2, s0 s2, s0 s1)`.
    pub pi: DVec3,
    /// Albedo ρ ≥ 0.
    pub rho: f64,
}

impl Kernel {
    /// A primitive from its centre, rotation, scales and albedo.
    pub fn new(x: DVec3, r: DMat3, s: DVec3, rho: f64) -> Self {
        Self {
            x,
            r,
            s,
            pi: DVec3::new(s.y * s.z, s.x * s.z, s.x * s.y),
            rho,
        }
    }

    /// Its albedo times the square of its largest projected area, as
    /// [`Primitive::weight`](super::model::Primitive::weight): what it adds to a
    /// transient seen face-on.
    pub fn weight(&self) -> f64 {
        let a = self.pi.max_element();
        self.rho * a * a
    }
}

/// Switches and constants of the forward model.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct RenderOptions {
    /// Global gain g.
    pub gain: f64,
    /// Weight by the illumination cosine `max(0, ni·ui)`; off = the paper's ablation.
    pub use_ni: bool,
    /// Weight by the detection cosine `max(0, nd·ud)`; off = the paper's ablation.
    pub use_nd: bool,
    /// Instrument timing jitter as a path-length standard deviation, metres, added in
    /// quadrature to σ_L (the paper omits it; 0 reproduces the paper).
    pub sigma_sys: f64,
    /// Half-width of the evaluated window, in σ_L (mass beyond it is below 6e-5 at 4).
    pub window_sigmas: f64,
    /// Primitives closer than this to a relay point of a pair contribute nothing to it
    /// (the 1/d² model has no meaning on the relay surface), metres.
    pub min_distance: f64,
    /// The data term of the fit's loss ([`crate::gtr::batch_loss`]).
    #[serde(default)]
    pub loss: Loss,
}

/// The data term the fit minimises, per pair p of a mini-batch of B with weight w_p.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(tag = "kind", rename_all = "kebab-case")]
pub enum Loss {
    /// `(1/B) Σ w_p ‖τ̂_p − τ_p‖²`: the paper's.
    #[default]
    L2,
    /// The Poisson deviance of counts (or non-negative intensities) τ against the rate
    /// τ̂ + β, `(2/B) Σ w_p Σ_b [τ ln(τ / (τ̂ + β)) − τ + τ̂ + β]` (0 for a perfect
    /// fit), whose bins weigh by 1/(τ̂ + β) as their variance does. β > 0 is the
    /// background per bin the model has no term for (ambient light, dark counts), and
    /// keeps the rate positive where the model predicts nothing.
    Poisson {
        /// Background counts per bin, β.
        background: f64,
    },
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            gain: 1.0,
            use_ni: true,
            use_nd: true,
            sigma_sys: 0.0,
            window_sigmas: 4.0,
            min_distance: 1e-3,
            loss: Loss::L2,
        }
    }
}

/// A floor on σ_L relative to the bin width, in quadrature, so a primitive seen
/// exactly edge-on (σ_L → 0) still integrates smoothly over bins. At 1e-4 bin widths it
/// changes no rendered value measurably.
pub(crate) const SIGMA_FLOOR_BINS: f64 = 1e-4;

/// The geometry of one primitive against one pair: everything the forward value and
/// the gradient share.
#[derive(Clone, Copy, Debug)]
pub struct Evaluation {
    di: f64,
    dd: f64,
    ui: DVec3,
    ud: DVec3,
    wi: DVec3,
    wd: DVec3,
    wv: DVec3,
    gi: f64,
    gd: f64,
    ai: f64,
    ad: f64,
    /// `g · A⊥i · A⊥d / (di² dd²)`: the amplitude without ρ and the cosines.
    base: f64,
    /// What the per-bin loops read.
    pub window: Window,
}

/// A primitive's pulse in one pair's histogram: what the per-bin loops of the forward
/// and the backward pass read.
#[derive(Clone, Copy, Debug)]
pub struct Window {
    /// Amplitude A.
    pub amplitude: f64,
    /// Mean hidden path length μ_L, metres.
    pub mu: f64,
    /// Path-length spread σ_L, metres.
    pub sigma: f64,
    /// First bin of the evaluated window.
    pub lo: usize,
    /// One past the last bin of the window.
    pub hi: usize,
    /// The midpoint series' start, for kernels at least two bins wide (`None`: the
    /// Φ table integrates the bins). Computed once here, read by the forward and the
    /// backward pass.
    series: Option<WideSeries>,
}

/// Evaluates the geometry; `None` when the primitive cannot contribute (behind either
/// relay point's tangent plane, on the relay, or its window misses the axis).
#[inline(always)]
pub fn evaluate(k: &Kernel, pair: &Pair, axis: &TimeAxis, opt: &RenderOptions) -> Option<Evaluation> {
    let to_i = k.x - pair.xi;
    let to_d = k.x - pair.xd;
    let di = to_i.length();
    let dd = to_d.length();
    if di < opt.min_distance || dd < opt.min_distance {
        return None;
    }
    let (inv_di, inv_dd) = (1.0 / di, 1.0 / dd);
    let ui = to_i * inv_di;
    let ud = to_d * inv_dd;
    let gi = if opt.use_ni { pair.ni.dot(ui) } else { 1.0 };
    let gd = if opt.use_nd { pair.nd.dot(ud) } else { 1.0 };
    if gi <= 0.0 || gd <= 0.0 {
        return None;
    }
    let rt = k.r.transpose();
    let wi = rt * ui;
    let wd = rt * ud;
    let wv = wi + wd;
    let ai = (k.pi * wi).length();
    let ad = (k.pi * wd).length();
    let base = opt.gain * ai * ad * (inv_di * inv_di) * (inv_dd * inv_dd);
    let amplitude = base * k.rho * gi * gd;
    let floor = SIGMA_FLOOR_BINS * axis.width;
    let sigma = ((k.s * wv).length_squared() + opt.sigma_sys * opt.sigma_sys + floor * floor).sqrt();
    let window = Window::new(amplitude, di + dd, sigma, axis, opt)?;
    Some(Evaluation {
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
        window,
    })
}

impl Evaluation {
    /// The gradient of the hidden path length `|x − xi| + |x − xd|` with respect to the
    /// primitive's centre: the sum of the unit vectors from the two relay points. A
    /// pulse locates the centre along it (the adaptive capture's information).
    pub fn path_gradient(&self) -> DVec3 {
        self.ui + self.ud
    }
}

impl Window {
    /// The pulse of amplitude `amplitude`, mean `mu` and spread `sigma` (with the floor
    /// and the instrument's jitter in it); `None` when its window misses the axis.
    #[inline(always)]
    pub(crate) fn new(
        amplitude: f64,
        mu: f64,
        sigma: f64,
        axis: &TimeAxis,
        opt: &RenderOptions,
    ) -> Option<Self> {
        let reach = opt.window_sigmas * sigma;
        let lo = ((mu - reach - axis.start) / axis.width).floor().max(0.0);
        let hi = ((mu + reach - axis.start) / axis.width)
            .ceil()
            .min(axis.bins as f64);
        if lo.partial_cmp(&hi) != Some(std::cmp::Ordering::Less) {
            return None;
        }
        let inv = 1.0 / sigma;
        let series = WideSeries::new((axis.edge(lo as isize) - mu) * inv, axis.width * inv);
        Some(Self {
            amplitude,
            mu,
            sigma,
            lo: lo as usize,
            hi: hi as usize,
            series,
        })
    }

    /// [`Window::new`] for `N` pulses at once (four or eight), lane by lane the same
    /// bits, lane j written into `out[j / 4][j % 4]` (the callers' slots, so the pulses
    /// are not built aside and copied).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(crate) fn lanes_into<const N: usize, Q: simd::Lanes<N>, const S: usize>(
        q: Q,
        amplitude: Q::V,
        mu: Q::V,
        sigma: Q::V,
        axis: &TimeAxis,
        opt: &RenderOptions,
        out: &mut [&mut [Option<Self>; 4]; S],
    ) {
        debug_assert_eq!(4 * S, N);
        let reach = q.mul(q.splat(opt.window_sigmas), sigma);
        let (start, width) = (q.splat(axis.start), q.splat(axis.width));
        let lo = q.max(
            q.floor(q.div(q.sub(q.sub(mu, reach), start), width)),
            q.splat(0.0),
        );
        let hi = q.min(
            q.ceil(q.div(q.sub(q.add(mu, reach), start), width)),
            q.splat(axis.bins as f64),
        );
        let inv = q.div(q.splat(1.0), sigma);
        let z0 = q.mul(q.sub(q.add(start, q.mul(lo, width)), mu), inv);
        let dz = q.mul(width, inv);
        let m = q.add(z0, q.mul(q.splat(0.5), dz));
        let dz2 = q.mul(dz, dz);
        let minus_one = q.splat(-1.0);
        let phi = q.mul(
            q.splat(INV_SQRT_2PI),
            crate::simd::exp(q, q.mul(q.mul(q.splat(-0.5), m), m)),
        );
        let rho = crate::simd::exp(q, q.sub(q.mul(q.mul(minus_one, m), dz), q.mul(q.splat(0.5), dz2)));
        let ratio = crate::simd::exp(q, q.mul(minus_one, dz2));
        let (lo, hi, m, dz) = (q.store(lo), q.store(hi), q.store(m), q.store(dz));
        let (phi, rho, ratio) = (q.store(phi), q.store(rho), q.store(ratio));
        let (amplitude, mu, sigma) = (q.store(amplitude), q.store(mu), q.store(sigma));
        for j in 0..N {
            let w = &mut out[j / 4][j % 4];
            if !(lo[j] < hi[j]) {
                *w = None;
                continue;
            }
            let series = if WideSeries::applies(m[j], dz[j]) {
                Some(WideSeries::from_exps(m[j], dz[j], phi[j], rho[j], ratio[j]))
            } else {
                None
            };
            *w = Some(Self {
                amplitude: amplitude[j],
                mu: mu[j],
                sigma: sigma[j],
                lo: lo[j] as usize,
                hi: hi[j] as usize,
                series,
            });
        }
    }

    /// Where the series' loops end in a histogram of `n` bins: past the window's last,
    /// partial group of bins where the histogram holds that group whole (it is then
    /// read whole, its lanes past the window weighted zero: x + 0 = x, so the bits are
    /// those of the window's lanes alone, with no lane handled by itself), else at the
    /// window's end.
    #[inline(always)]
    fn series_end(&self, n: usize) -> usize {
        let whole = self.lo + (self.hi - self.lo).next_multiple_of(LANES);
        if whole <= n { whole } else { self.hi }
    }

    /// The midpoint series' state as bits, for tests that compare two paths.
    #[cfg(test)]
    pub(crate) fn series_bits(&self) -> Option<[u64; 7]> {
        self.series
            .map(|s| [s.m, s.dz, s.phi, s.rho, s.q, s.a, s.b].map(f64::to_bits))
    }

    /// Adds the pulse to `out` (the full histogram of the pair).
    ///
    /// On the midpoint series the bins go eight (`LANES`) at a time, lane j taking bins
    /// j, j + 8, …, so the per-bin arithmetic compiles to vector instructions.
    #[inline(always)]
    pub fn accumulate(&self, axis: &TimeAxis, out: &mut [f64]) {
        self.accumulate_with(crate::simd::Portable, axis, out);
    }

    /// [`Window::accumulate`] with the vector arithmetic `quad`.
    #[inline(always)]
    pub(crate) fn accumulate_with<Q: Quad>(&self, quad: Q, axis: &TimeAxis, out: &mut [f64]) {
        if let Some(series) = &self.series {
            let o = quad.oct();
            let scale = o.splat(self.amplitude * series.dz);
            let poly = series.poly_consts(o);
            let mut lanes = series.lanes(o);
            let end = self.series_end(out.len());
            let mut chunks = out[self.lo..end].chunks_exact_mut(LANES);
            let mut left = self.hi - self.lo;
            for chunk in &mut chunks {
                let chunk: &mut [f64; LANES] = chunk.try_into().expect("a chunk of LANES");
                let p = poly.value(o, o.mul(lanes.m, lanes.m));
                let a = o.mul(o.mul(scale, lanes.phi), o.load(TAIL_MASK[left.min(LANES)]));
                *chunk = o.store(o.mul_add(a, p, o.load(*chunk)));
                lanes.advance(o);
                left = left.saturating_sub(LANES);
            }
            // The last, partial group of bins, at the histogram's end.
            let rest = chunks.into_remainder();
            if !rest.is_empty() {
                let p = poly.value(o, o.mul(lanes.m, lanes.m));
                let tail = o.store(o.mul_add(o.mul(scale, lanes.phi), p, o.load(load_tail(rest))));
                store_tail(&tail, rest);
            }
            return;
        }
        let out = &mut out[self.lo..self.hi];
        let inv = 1.0 / self.sigma;
        let z0 = (axis.edge(self.lo as isize) - self.mu) * inv;
        let dz = axis.width * inv;
        let table = &*NORMAL;
        let mut prev = table.cdf(z0);
        for (i, o) in out.iter_mut().enumerate() {
            let next = table.cdf(z0 + (i + 1) as f64 * dz);
            *o = self.amplitude.mul_add(next - prev, *o);
            prev = next;
        }
    }

    /// [`Window::accumulate_with`], keeping the series' lanes as built for
    /// [`Window::sums`] to read (the same values, so the same bits).
    #[inline(always)]
    pub(crate) fn accumulate_keeping<Q: Quad>(&mut self, quad: Q, axis: &TimeAxis, out: &mut [f64]) {
        if let Some(series) = &mut self.series
            && series.kept.is_none()
        {
            series.kept = Some(series.starts());
        }
        self.accumulate_with(quad, axis, out);
    }

    /// `Σ_b dl_b ΔΦ_b`, `Σ_b dl_b ∂ΔΦ_b/∂m_b` and `Σ_b dl_b (m ∂/∂m + dz ∂/∂dz) ΔΦ_b`
    /// over the window, where `ΔΦ_b` is the rendered bin mass (a function of the bin's
    /// centre `m_b = (centre_b − μ)/σ` and width `dz = width/σ`). The second and third
    /// are `−σ ∂/∂μ` and `−σ ∂/∂σ` of the first, so the gradient is that of the values
    /// [`Evaluation::accumulate`] renders, on either path.
    #[inline(always)]
    pub(crate) fn sums<Q: Quad>(&self, quad: Q, axis: &TimeAxis, dl: &[f64]) -> (f64, f64, f64) {
        if let Some(series) = &self.series {
            let dl = &dl[self.lo..self.series_end(dl.len())];
            let o = quad.oct();
            // Per lane, without the common factor dz (applied to the lanes' totals).
            let zero = o.splat(0.0);
            let mut sums = SeriesSums {
                cdf: zero,
                pdf: zero,
                zpdf: zero,
            };
            let poly = series.poly_consts(o);
            let mut lanes = series.lanes(o);
            let mut chunks = dl.chunks_exact(LANES);
            let mut left = self.hi - self.lo;
            for chunk in &mut chunks {
                let chunk: &[f64; LANES] = chunk.try_into().expect("a chunk of LANES");
                let r = o.mul(o.load(*chunk), o.load(TAIL_MASK[left.min(LANES)]));
                sums.add(o, &poly, &lanes, r);
                lanes.advance(o);
                left = left.saturating_sub(LANES);
            }
            // The last, partial group of bins: the missing lanes weigh zero.
            let rest = chunks.remainder();
            if !rest.is_empty() {
                sums.add(o, &poly, &lanes, o.load(load_tail(rest)));
            }
            let total = |v: <Q::Oct as simd::Lanes<8>>::V| series.dz * o.total(v);
            return (total(sums.cdf), total(sums.pdf), total(sums.zpdf));
        }
        let dl = &dl[self.lo..self.hi];
        // Table path: ΔΦ_b = Φ(z_{b+1}) − Φ(z_b); shifting every z by m gives the
        // differences of φ at the edges, and −σ ∂/∂σ those of zφ (φ the slope of the
        // tabulated Φ).
        let inv = 1.0 / self.sigma;
        let z0 = (axis.edge(self.lo as isize) - self.mu) * inv;
        let dz = axis.width * inv;
        let (mut s_cdf, mut s_pdf, mut s_zpdf) = (0.0, 0.0, 0.0);
        let table = &*NORMAL;
        let (mut c0, mut p0) = table.cdf_and_slope(z0);
        let mut zp0 = z0 * p0;
        for (i, &r) in dl.iter().enumerate() {
            let z1 = z0 + (i + 1) as f64 * dz;
            let (c1, p1) = table.cdf_and_slope(z1);
            let zp1 = z1 * p1;
            s_cdf = r.mul_add(c1 - c0, s_cdf);
            s_pdf = r.mul_add(p1 - p0, s_pdf);
            s_zpdf = r.mul_add(zp1 - zp0, s_zpdf);
            (c0, p0, zp0) = (c1, p1, zp1);
        }
        (s_cdf, s_pdf, s_zpdf)
    }
}

/// `TAIL_MASK[r]`: 1 in the first `r` lanes, 0 after (every lane 1 at `r = LANES`).
/// The per-bin loops multiply by it, where a branch on the last group would be
/// mispredicted once a window.
const TAIL_MASK: [[f64; LANES]; LANES + 1] = {
    let mut m = [[0.0; LANES]; LANES + 1];
    let mut r = 0;
    while r <= LANES {
        let mut j = 0;
        while j < r {
            m[r][j] = 1.0;
            j += 1;
        }
        r += 1;
    }
    m
};

/// The last, partial group of a window's bins (1 to 7 of them) as a vector's lanes,
/// zeros after. Lane by lane rather than `copy_from_slice`: a copy of a variable
/// length compiles to a call of `memcpy`, twice a window, which took 6 % of a synthesis.
#[inline(always)]
fn load_tail(rest: &[f64]) -> [f64; LANES] {
    debug_assert!(rest.len() < LANES);
    std::array::from_fn(|j| rest.get(j).copied().unwrap_or(0.0))
}

/// Writes the first `rest.len()` lanes of `tail` back to `rest` (see [`load_tail`]).
#[inline(always)]
fn store_tail(tail: &[f64; LANES], rest: &mut [f64]) {
    debug_assert!(rest.len() < LANES);
    for (r, &t) in rest.iter_mut().zip(tail) {
        *r = t;
    }
}

/// Timing probes for `benches/gtr.rs`: the pulses' per-bin loops alone, on the vector
/// path a training step takes (AVX-512, or AVX2 + FMA, where the CPU has them), so the bench
/// can tell their cost from the rest of a step's. Not an interface to build on.
#[doc(hidden)]
pub mod probe {
    use super::Window;
    use crate::simd::{Quad, Work, dispatch};
    use crate::transient::TimeAxis;

    /// The backward pass's three sums over each of `windows` with residuals `dl` (a
    /// whole histogram), added up so nothing is optimised away.
    pub fn sums(windows: &[Window], axis: &TimeAxis, dl: &[f64]) -> f64 {
        struct Sums<'a>(&'a [Window], &'a TimeAxis, &'a [f64]);
        impl Work for Sums<'_> {
            type Output = f64;
            #[inline(always)]
            fn run<Q: Quad>(self, quad: Q) -> f64 {
                let mut total = 0.0;
                for w in self.0 {
                    let (a, b, c) = w.sums(quad, self.1, self.2);
                    total += a + b + c;
                }
                total
            }
        }
        dispatch(Sums(windows, axis, dl))
    }

    /// The forward pass's adds of each of `windows` into `out` (a whole histogram).
    pub fn accumulate(windows: &[Window], axis: &TimeAxis, out: &mut [f64]) {
        struct Adds<'a>(&'a [Window], &'a TimeAxis, &'a mut [f64]);
        impl Work for Adds<'_> {
            type Output = ();
            #[inline(always)]
            fn run<Q: Quad>(self, quad: Q) {
                for w in self.0 {
                    w.accumulate_with(quad, self.1, self.2);
                }
            }
        }
        dispatch(Adds(windows, axis, out))
    }
}

impl Evaluation {
    /// Adds the primitive's contribution to `out` (the full histogram of the pair).
    #[inline(always)]
    pub fn accumulate(&self, axis: &TimeAxis, out: &mut [f64]) {
        self.window.accumulate(axis, out);
    }

    /// Given `dl = ∂loss/∂τ̂` for the pair's bins, adds the gradient with respect to the
    /// primitive's physical parameters to `grad`.
    #[inline(always)]
    pub fn backward(
        &self,
        k: &Kernel,
        pair: &Pair,
        axis: &TimeAxis,
        opt: &RenderOptions,
        dl: &[f64],
        grad: &mut PhysicalGrad,
    ) {
        self.backward_with(crate::simd::Portable, k, pair, axis, opt, dl, grad);
    }

    /// [`Evaluation::backward`] with the vector arithmetic `quad`.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    pub(crate) fn backward_with<Q: Quad>(
        &self,
        quad: Q,
        k: &Kernel,
        pair: &Pair,
        axis: &TimeAxis,
        opt: &RenderOptions,
        dl: &[f64],
        grad: &mut PhysicalGrad,
    ) {
        let inv = 1.0 / self.window.sigma;
        let (s_cdf, s_pdf, s_zpdf) = self.window.sums(quad, axis, dl);
        let amp = self.window.amplitude;
        let g_amp = s_cdf; // ∂L/∂A
        let g_mu = -amp * s_pdf * inv; // ∂L/∂μ
        let g_sigma = -amp * s_zpdf * inv; // ∂L/∂σ

        // Albedo and the relay cosines.
        grad.rho += g_amp * self.base * self.gi * self.gd;
        let g_gi = if opt.use_ni {
            g_amp * self.base * k.rho * self.gd
        } else {
            0.0
        };
        let g_gd = if opt.use_nd {
            g_amp * self.base * k.rho * self.gi
        } else {
            0.0
        };

        // Projected areas: ∂A⊥/∂w = (w ⊙ π²)/A⊥, and ∂L/∂A⊥ = g_amp A / A⊥.
        let pi2 = k.pi * k.pi;
        let g_wi = (g_amp * amp / (self.ai * self.ai)) * (self.wi * pi2);
        let g_wd = (g_amp * amp / (self.ad * self.ad)) * (self.wd * pi2);
        // Spread: σ² = Σ (s_j wv_j)² → ∂σ/∂wv = (s² ⊙ wv)/σ.
        let s2 = k.s * k.s;
        let g_wv = (g_sigma * inv) * (s2 * self.wv);

        // Scales, through A⊥(ui), A⊥(ud) and σ.
        let s = k.s;
        let area_ds = |w: DVec3, a: f64| {
            let q = w * w * k.pi;
            DVec3::new(
                q.y * s.z + q.z * s.y,
                q.x * s.z + q.z * s.x,
                q.x * s.y + q.y * s.x,
            ) / a
        };
        grad.s += (g_amp * amp / self.ai) * area_ds(self.wi, self.ai)
            + (g_amp * amp / self.ad) * area_ds(self.wd, self.ad)
            + (g_sigma * inv) * (s * self.wv * self.wv);

        // Rotation: w = Rᵀu, so ∂L/∂R_mj = Σ u_m ∂L/∂w_j over the three directions.
        let v = self.ui + self.ud;
        grad.r += outer(self.ui, g_wi) + outer(self.ud, g_wd) + outer(v, g_wv);

        // Centre, through the distances and the unit directions.
        let rg_v = k.r * g_wv;
        let g_ui = k.r * g_wi + rg_v + g_gi * pair.ni;
        let g_ud = k.r * g_wd + rg_v + g_gd * pair.nd;
        let g_di = -2.0 * g_amp * amp / self.di + g_mu;
        let g_dd = -2.0 * g_amp * amp / self.dd + g_mu;
        grad.x += g_di * self.ui + (g_ui - self.ui.dot(g_ui) * self.ui) / self.di;
        grad.x += g_dd * self.ud + (g_ud - self.ud.dot(g_ud) * self.ud) / self.dd;
    }
}

/// Below this bin width in σ (a kernel at least two bins wide), bins are integrated by
/// the midpoint series instead of differences of the tabulated Φ.
pub const WIDE_DZ: f64 = 0.5;

/// The bin masses of a Gaussian at least two bins wide, without a table: the integral
/// of φ over a bin of width `dz` centred on `m` is
/// `dz φ(m) [1 + dz² He₂(m)/24 + dz⁴ He₄(m)/1920 + …]` (He the Hermite polynomials),
/// kept to the `dz⁴` term; φ at consecutive centres follows the recurrence
/// `φ(m + dz) = φ(m) ρ`, `ρ ← ρ e^{−dz²}`, two multiplies a bin.
///
/// The first dropped term is `dz⁶ He₆(m)/322560`: for `dz ≤ 0.5` and `|m| ≤ 4` it is
/// below 5e-5 of the bin's own mass in the outermost bins and 1e-6 at the peak, and
/// the bins' total stays within 2e-7 of the exact Φ differences (tested against
/// `erfc`). The recurrence adds about one rounding a step (1e-14 over a window).
#[derive(Clone, Copy, Debug)]
struct WideSeries {
    /// The first bin's centre, in σ.
    m: f64,
    /// The bin width, in σ.
    dz: f64,
    /// φ(m), the ratio to the next bin's φ, and the ratio between consecutive ratios.
    phi: f64,
    rho: f64,
    q: f64,
    /// `dz²/24` and `dz⁴/1920`.
    a: f64,
    b: f64,
    /// The lanes' starts ([`WideSeries::lanes`]) as the forward pass built them, for
    /// the backward pass to read instead of building them again (they had taken 3.5 %
    /// of a fit each time).
    kept: Option<KeptLanes>,
}

/// Where [`Lanes`] start: φ and each lane's ratio, and the ratio between ratios
/// ([`WideSeries::starts`]).
#[derive(Clone, Copy, Debug)]
struct KeptLanes {
    phi: [f64; LANES],
    ratio: [f64; LANES],
    q: f64,
}

/// Bins a step of the per-bin loops takes at once (one AVX-512 vector of f64, two of
/// AVX2).
const LANES: usize = 8;

/// The midpoint series spread over [`LANES`] interleaved recurrences: lane j holds
/// bin `j + LANES t` at step t. Each lane steps `LANES` bins at once,
/// `φ(m + 8dz) = φ(m) R`, `R ← R e^{−64 dz²}`, so the lanes are independent and
/// advance as one vector.
struct Lanes<V> {
    /// Bin centres, in σ.
    m: V,
    /// φ at the centres.
    phi: V,
    /// Each lane's ratio to its next bin's φ.
    ratio: V,
    /// The ratio between consecutive ratios, `e^{−64 dz²}`.
    q: V,
    /// `LANES dz`.
    step: V,
}

/// The constants of [`WideSeries::poly`] and its slopes, as vectors.
struct PolyConsts<V> {
    one: V,
    three: V,
    six: V,
    four: V,
    minus_twelve: V,
    a: V,
    b: V,
    two_a: V,
    four_b: V,
}

impl<V: Copy> PolyConsts<V> {
    /// `P(m) = 1 + a He₂ + b He₄` from `m²`, with `He₂ = m² − 1`,
    /// `He₄ = m⁴ − 6m² + 3`.
    #[inline(always)]
    fn value<O: simd::Lanes<8, V = V>>(&self, quad: O, m2: V) -> V {
        let he2 = quad.sub(m2, self.one);
        let he4 = quad.mul_add(m2, quad.sub(m2, self.six), self.three);
        quad.mul_add(self.b, he4, quad.mul_add(self.a, he2, self.one))
    }
}

impl WideSeries {
    /// The series from the first edge `z0`, or `None` when the bins are too wide for
    /// it (or the window reaches beyond where φ is representable: |m| > 30).
    #[inline(always)]
    fn new(z0: f64, dz: f64) -> Option<Self> {
        let m = z0 + 0.5 * dz;
        if !Self::applies(m, dz) {
            return None;
        }
        let dz2 = dz * dz;
        let phi = INV_SQRT_2PI * exp_scalar(-0.5 * m * m);
        Some(Self::from_exps(
            m,
            dz,
            phi,
            exp_scalar(-m * dz - 0.5 * dz2),
            exp_scalar(-dz2),
        ))
    }

    /// Whether the series serves a window whose first bin's centre is `m` and whose
    /// bins are `dz` wide, in σ.
    #[inline(always)]
    fn applies(m: f64, dz: f64) -> bool {
        dz <= WIDE_DZ && m.abs() < 30.0
    }

    /// The series from its first centre `m`, the bin width `dz`, and `φ(m)`,
    /// `ρ = e^{−m dz − dz²/2}` and `q = e^{−dz²}` (`exp` from [`crate::simd`], whose
    /// lanes give the same bits).
    #[inline(always)]
    fn from_exps(m: f64, dz: f64, phi: f64, rho: f64, q: f64) -> Self {
        let dz2 = dz * dz;
        Self {
            m,
            dz,
            phi,
            rho,
            q,
            a: dz2 / 24.0,
            b: dz2 * dz2 / 1920.0,
            kept: None,
        }
    }

    /// The first [`LANES`] bins and each lane's recurrence, from the starts the forward
    /// pass kept, or built here.
    #[inline(always)]
    fn lanes<O: simd::Lanes<8>>(&self, quad: O) -> Lanes<O::V> {
        let m: [f64; LANES] = std::array::from_fn(|j| (j as f64).mul_add(self.dz, self.m));
        let starts = self.kept.unwrap_or_else(|| self.starts());
        Lanes {
            m: quad.load(m),
            phi: quad.load(starts.phi),
            ratio: quad.load(starts.ratio),
            q: quad.splat(starts.q),
            step: quad.splat(LANES as f64 * self.dz),
        }
    }

    /// Where the lanes start. The first bins come from the one-bin recurrence; lane j's
    /// ratio `φ(m_j + 8dz)/φ(m_j)` is `ρ⁸ q^{8j+28}`.
    #[inline(always)]
    fn starts(&self) -> KeptLanes {
        let (q, rho) = (self.q, self.rho);
        // The first four bins by the one-bin recurrence, the next four from them by the
        // four-bin ratios f_j = ρ⁴ q^{4j+6}, and the lanes' eight-bin ratios as
        // f_j² q¹⁶ (and that times q³² for lanes 4–7): short chains of multiplies,
        // where eight steps of the one-bin recurrence were one long one.
        let r1 = rho * q;
        let r2 = r1 * q;
        let p0 = self.phi;
        let p1 = p0 * rho;
        let p2 = p1 * r1;
        let p3 = p2 * r2;
        let q2 = q * q;
        let q4 = q2 * q2;
        let q8 = q4 * q4;
        let q16 = q8 * q8;
        let q32 = q16 * q16;
        let rho2 = rho * rho;
        let rho4 = rho2 * rho2;
        let f0 = rho4 * (q4 * q2);
        let f1 = f0 * q4;
        let f2 = f0 * q8;
        let f3 = f1 * q8;
        let g = [f0 * (f0 * q16), f1 * (f1 * q16), f2 * (f2 * q16), f3 * (f3 * q16)];
        KeptLanes {
            phi: [p0, p1, p2, p3, p0 * f0, p1 * f1, p2 * f2, p3 * f3],
            ratio: [
                g[0],
                g[1],
                g[2],
                g[3],
                g[0] * q32,
                g[1] * q32,
                g[2] * q32,
                g[3] * q32,
            ],
            q: q32 * q32,
        }
    }

    /// The polynomial's constants for `quad`.
    #[inline(always)]
    fn poly_consts<O: simd::Lanes<8>>(&self, quad: O) -> PolyConsts<O::V> {
        PolyConsts {
            one: quad.splat(1.0),
            three: quad.splat(3.0),
            six: quad.splat(6.0),
            four: quad.splat(4.0),
            minus_twelve: quad.splat(-12.0),
            a: quad.splat(self.a),
            b: quad.splat(self.b),
            two_a: quad.splat(2.0 * self.a),
            four_b: quad.splat(4.0 * self.b),
        }
    }
}

impl<V: Copy> Lanes<V> {
    /// Every lane on to its next bin.
    #[inline(always)]
    fn advance<O: simd::Lanes<8, V = V>>(&mut self, quad: O) {
        self.phi = quad.mul(self.phi, self.ratio);
        self.ratio = quad.mul(self.ratio, self.q);
        self.m = quad.add(self.m, self.step);
    }
}

/// The backward pass's three sums on the midpoint series, per lane and without the
/// common factor dz.
struct SeriesSums<V> {
    cdf: V,
    pdf: V,
    zpdf: V,
}

impl<V: Copy> SeriesSums<V> {
    /// Adds one group of bins with residuals `dl`: per bin, with `f = dl φ(m)`,
    /// `ΔΦ/dz = φ P`, `(∂ΔΦ/∂m)/dz = φ (P' − m P)` and
    /// `(m ∂/∂m + dz ∂/∂dz) ΔΦ / dz = φ (m (P' − m P) + P + dz ∂P/∂dz)`, with
    /// `P' = m (2a + b (4m² − 12))` and `dz ∂P/∂dz = 2a He₂ + 4b He₄`.
    #[inline(always)]
    fn add<O: simd::Lanes<8, V = V>>(&mut self, quad: O, c: &PolyConsts<V>, lanes: &Lanes<V>, dl: V) {
        let m = lanes.m;
        let m2 = quad.mul(m, m);
        let he2 = quad.sub(m2, c.one);
        let he4 = quad.mul_add(m2, quad.sub(m2, c.six), c.three);
        let p = quad.mul_add(c.b, he4, quad.mul_add(c.a, he2, c.one));
        let dp_dm = quad.mul(
            m,
            quad.mul_add(c.b, quad.mul_add(c.four, m2, c.minus_twelve), c.two_a),
        );
        let dz_dp_ddz = quad.mul_add(c.two_a, he2, quad.mul(c.four_b, he4));
        let f = quad.mul(dl, lanes.phi);
        self.cdf = quad.mul_add(f, p, self.cdf);
        let d_m = quad.sub(dp_dm, quad.mul(m, p));
        self.pdf = quad.mul_add(f, d_m, self.pdf);
        let z = quad.mul_add(m, d_m, quad.add(p, dz_dp_ddz));
        self.zpdf = quad.mul_add(f, z, self.zpdf);
    }
}

/// `a bᵀ` as a matrix (column j is `a · b_j`).
#[inline]
fn outer(a: DVec3, b: DVec3) -> DMat3 {
    DMat3::from_cols(a * b.x, a * b.y, a * b.z)
}

/// Gradient of the loss with respect to one primitive's physical parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhysicalGrad {
    /// ∂L/∂x.
    pub x: DVec3,
    /// ∂L/∂R (entry (m, j) is column j, row m).
    pub r: DMat3,
    /// ∂L/∂s.
    pub s: DVec3,
    /// ∂L/∂ρ.
    pub rho: f64,
}

impl Default for PhysicalGrad {
    fn default() -> Self {
        Self {
            x: DVec3::ZERO,
            r: DMat3::ZERO,
            s: DVec3::ZERO,
            rho: 0.0,
        }
    }
}

/// Renders one pair's transient from all primitives into `out` (overwritten), as
/// [`render_pairs`](super::render_pairs) does.
pub fn render_pair(kernels: &[Kernel], pair: &Pair, axis: &TimeAxis, opt: &RenderOptions, out: &mut [f64]) {
    super::render_pairs(kernels, std::slice::from_ref(pair), axis, opt, out);
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::special::norm_cdf;

    /// A unit-amplitude pulse of mean `mu` and spread `sigma`, window ±`reach` σ on
    /// `axis`.
    fn window(axis: &TimeAxis, mu: f64, sigma: f64, reach: f64) -> Window {
        let lo = ((mu - reach * sigma - axis.start) / axis.width).floor().max(0.0) as usize;
        let hi = (((mu + reach * sigma - axis.start) / axis.width).ceil() as usize).min(axis.bins);
        Window {
            amplitude: 1.0,
            mu,
            sigma,
            lo,
            hi,
            series: WideSeries::new((axis.edge(lo as isize) - mu) / sigma, axis.width / sigma),
        }
    }

    /// The series as one recurrence, a bin at a time (the loops before they were laid
    /// out in lanes): the rendered masses and the backward pass's three sums.
    fn one_lane(e: &Window, dl: &[f64]) -> (Vec<f64>, [f64; 3]) {
        let s = e.series.expect("a wide kernel");
        let (mut m, mut phi, mut rho) = (s.m, s.phi, s.rho);
        let (mut out, mut sums) = (Vec::new(), [0.0; 3]);
        for &r in &dl[e.lo..e.hi] {
            let m2 = m * m;
            let (he2, he4) = (m2 - 1.0, m2 * m2 - 6.0 * m2 + 3.0);
            let p = 1.0 + s.a * he2 + s.b * he4;
            let dp_dm = m * (2.0 * s.a + s.b * (4.0 * m2 - 12.0));
            let dz_dp_ddz = 2.0 * s.a * he2 + 4.0 * s.b * he4;
            out.push(e.amplitude * s.dz * phi * p);
            let d_m = dp_dm - m * p;
            sums[0] += r * s.dz * phi * p;
            sums[1] += r * s.dz * phi * d_m;
            sums[2] += r * s.dz * phi * (m * d_m + p + dz_dp_ddz);
            phi *= rho;
            rho *= s.q;
            m += s.dz;
        }
        (out, sums)
    }

    /// The lanes render and sum what one recurrence a bin at a time does, within a few
    /// roundings a bin, for windows of every length modulo the lane count; and this
    /// CPU's vectors give the same bits as the portable arrays.
    #[test]
    fn the_lanes_match_one_recurrence_and_the_vectors_match_the_arrays() {
        let axis = TimeAxis {
            start: 0.0,
            width: 0.005,
            bins: 512,
        };
        let (mut checked, mut vectors_compared) = (0, 0);
        let mut tails = std::collections::BTreeSet::new();
        for (i, sigma) in [0.0101, 0.013, 0.021, 0.05, 0.11].into_iter().enumerate() {
            for (j, reach) in [0.9, 1.7, 2.3, 3.1, 4.0, 4.7, 5.5].into_iter().enumerate() {
                // Inside the histogram, and cut by its end (no whole group after).
                for base in [1.0, 2.54] {
                    let mu = base + 0.0013 * (i * 7 + j) as f64;
                    let e = window(&axis, mu, sigma, reach);
                    let dl: Vec<f64> = (0..axis.bins)
                        .map(|b| ((b * 37 % 11) as f64 - 5.0) * 0.1)
                        .collect();
                    tails.insert((e.hi - e.lo) % LANES);
                    let (reference, ref_sums) = one_lane(&e, &dl);
                    let mut out = vec![0.0; axis.bins];
                    e.accumulate(&axis, &mut out);
                    let peak = reference.iter().fold(0.0f64, |m, v| m.max(*v));
                    // Both recurrences round about once a bin; their drift apart grows with
                    // the window's length.
                    let tol = 2e-15 * (e.hi - e.lo) as f64;
                    for (b, r) in (e.lo..e.hi).zip(&reference) {
                        assert!(
                            (out[b] - r).abs() <= tol * peak,
                            "σ {sigma}, bin {b}: {} vs {r}",
                            out[b]
                        );
                    }
                    let sums = e.sums(crate::simd::Portable, &axis, &dl);
                    // A histogram that ends with the window (no whole group after it) gets
                    // the same bits as one whose last group is read whole and masked, and
                    // the bins past the window stay untouched.
                    let mut cut = vec![0.0; e.hi];
                    e.accumulate(&axis, &mut cut);
                    assert_eq!(
                        cut.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                        out[..e.hi].iter().map(|x| x.to_bits()).collect::<Vec<_>>()
                    );
                    assert!(out[e.hi..].iter().all(|&v| v.to_bits() == 0));
                    let c = e.sums(crate::simd::Portable, &axis, &dl[..e.hi]);
                    assert_eq!(
                        [c.0, c.1, c.2].map(f64::to_bits),
                        [sums.0, sums.1, sums.2].map(f64::to_bits)
                    );
                    let scale = dl.iter().map(|r| r.abs()).sum::<f64>() * peak;
                    for (got, want) in [sums.0, sums.1, sums.2].into_iter().zip(ref_sums) {
                        assert!((got - want).abs() <= tol * scale, "σ {sigma}: {got} vs {want}");
                    }
                    // This CPU's vectors (AVX2's pairs, AVX-512's eights) give the arrays' bits.
                    fn same_bits<Q: Quad>(
                        q: Q,
                        e: &Window,
                        axis: &TimeAxis,
                        dl: &[f64],
                        out: &[f64],
                        sums: (f64, f64, f64),
                    ) {
                        let mut fast = vec![0.0; axis.bins];
                        e.accumulate_with(q, axis, &mut fast);
                        assert_eq!(
                            fast.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                            out.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
                        );
                        let f = e.sums(q, axis, dl);
                        assert_eq!(
                            [f.0, f.1, f.2].map(f64::to_bits),
                            [sums.0, sums.1, sums.2].map(f64::to_bits)
                        );
                        // The forward pass keeping its lanes for the backward pass.
                        let mut kept = *e;
                        let mut again = vec![0.0; axis.bins];
                        kept.accumulate_keeping(q, axis, &mut again);
                        assert_eq!(
                            again.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
                            out.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
                        );
                        assert_eq!(
                            kept.series.is_some(),
                            kept.series.is_some_and(|s| s.kept.is_some())
                        );
                        let f = kept.sums(q, axis, dl);
                        assert_eq!(
                            [f.0, f.1, f.2].map(f64::to_bits),
                            [sums.0, sums.1, sums.2].map(f64::to_bits)
                        );
                    }
                    #[cfg(target_arch = "x86_64")]
                    if let Some(v3) = crate::simd::v3() {
                        same_bits(v3, &e, &axis, &dl, &out, sums);
                        vectors_compared += 1;
                    }
                    #[cfg(target_arch = "x86_64")]
                    if let Some(v4) = crate::simd::v4() {
                        same_bits(v4, &e, &axis, &dl, &out, sums);
                        vectors_compared += 1;
                    }
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 70);
        assert_eq!(tails.len(), LANES, "window lengths modulo {LANES}: {tails:?}");
        if vectors_compared < 2 * checked {
            eprintln!(
                "skipped in part: this CPU lacks AVX2 + FMA or AVX-512, {vectors_compared} vector runs of {}",
                2 * checked
            );
        }
    }

    /// The midpoint series renders every bin within its stated bound of the exact
    /// Φ differences (from `erfc`), for kernels from 2 to 100 bins wide at several
    /// sub-bin offsets; the table path holds 1e-9 just above the switch-over.
    #[test]
    fn wide_kernels_match_the_exact_bin_masses() {
        let axis = TimeAxis {
            start: 0.0,
            width: 0.01,
            bins: 4000,
        };
        let mut worst_rel_peak: f64 = 0.0;
        let mut worst_total: f64 = 0.0;
        for dz in [0.01, 0.05, 0.2, 0.35, 0.5, 0.500001, 0.8] {
            for offset in [0.0, 0.13, 0.5, 0.77] {
                let sigma = axis.width / dz;
                let mu = 20.0 + offset * axis.width;
                let e = window(&axis, mu, sigma, 4.0);
                let mut out = vec![0.0; axis.bins];
                e.accumulate(&axis, &mut out);
                let peak = out.iter().fold(0.0f64, |m, v| m.max(*v));
                let mut total = 0.0;
                for b in e.lo..e.hi {
                    let exact = norm_cdf((axis.edge(b as isize + 1) - mu) / sigma)
                        - norm_cdf((axis.edge(b as isize) - mu) / sigma);
                    let err = (out[b] - exact).abs();
                    total += out[b] - exact;
                    let bound = if dz <= WIDE_DZ {
                        // 5e-5 of the bin's own mass in the tails, 1e-6 of the peak.
                        5e-5 * exact + 1e-6 * peak
                    } else {
                        1e-9
                    };
                    assert!(
                        err <= bound,
                        "dz {dz}, offset {offset}, bin {b}: {} vs exact {exact} (error {err:e}, bound {bound:e})",
                        out[b]
                    );
                    worst_rel_peak = worst_rel_peak.max(err / peak);
                }
                worst_total = worst_total.max(total.abs());
            }
        }
        assert!(worst_total < 2e-7, "total mass off by {worst_total:e}");
        assert!(worst_rel_peak > 0.0);
    }
}

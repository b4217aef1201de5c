//! Filtered backprojection for arbitrary pairs on any relay.
//!
//! Every voxel x collects, from every pair, the histogram value at its path length
//! ℓ = |x − x_i| + |x − x_d| (linearly interpolated between bin centres), times the
//! falloff weight (d_i·d_d)^p that undoes the radiometric falloff, and times the
//! pair's share of the relay ([`super::pair_weights`]: 1 on a full grid, the Voronoi
//! cells of scattered points), so the sum is a quadrature of the integral over the
//! relay. The falloff weight is split in two: (ℓ/2)^2p, a function of path length,
//! multiplies each histogram bin before filtering (for the phasor filter, once the
//! histogram's slow part is taken off), and the rest, (4·d_i·d_d/ℓ²)^p ≤ 1
//! (exactly 1 for a confocal pair), multiplies at the voxel. Weighed at the voxel
//! alone, the weight grew across the filtered pulse's envelope and pushed every peak
//! deeper (by σ²·∂ln w/∂ℓ, millimetres for the phasor filter). Two filters:
//! - **Phasor** (the default; Liu et al. 2019's phasor-field virtual wave, as y-tal's
//!   `fbp`): each histogram is first convolved along path length with a complex
//!   Gaussian wavelet of wavelength λ, exp(−t²/2σ²)·exp(2πi·t/λ), i.e. band-passed
//!   around the spatial frequency 1/λ and made analytic; the real and imaginary parts
//!   are backprojected and the volume is the magnitude. λ follows the relay's sampling
//!   pitch Δ (λ = 2.5·Δ, the finest wave the aperture samples without aliasing, with
//!   σ = λ/√2), and no less than 2.5 lateral voxel pitches (the finest detail the
//!   volume holds), so the filter keeps what the relay can resolve and drops the DC,
//!   ambient light and shot noise outside that band. Robust on sparse, non-confocal
//!   and noisy captures. On photon counts the background's noise floor, which the
//!   falloff weight lifts with the distance from the relay, is then taken off every
//!   voxel (`noise.rs`, `[fbp] noise-floor`).
//! - **Laplacian** (Velten et al. 2012): the backprojection sharpened with the
//!   negative 3-D Laplacian on the voxel grid, negative lobes clipped. Sharp on a
//!   dense, noise-free confocal grid, fragile elsewhere: its cut-off is the voxel
//!   size, not the data's bandwidth.
//!
//! Work is split by z slices (each thread owns whole slices and loops over all pairs,
//! so a slice stays in cache); the inner loop runs in f32 along x. A confocal scan on a
//! regular grid whose pitch divides the voxel pitch (the 3D-GTR virtual scan) takes a
//! faster path that shares each lateral offset's path length among all the voxel–point
//! pairs at that offset ([`grid`]).
use std::sync::Arc;

use rayon::prelude::*;
use rustfft::num_complex::Complex;
use rustfft::{Fft, FftPlanner};

use super::SolverError;
use crate::gpu::Compute;
use crate::transient::{TimeAxis, TransientSet};
use crate::volume::{Volume, VolumeGrid};

mod grid;
mod noise;
mod tree;

/// Pairs whose histograms are swept together over a slice (32 pairs of 512 bins, two
/// channels, each bin with the next: 32 × 8 KiB fits in L2).
const PAIR_TILE: usize = 32;

/// The filter.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FbpFilter {
    /// Plain backprojection.
    None,
    /// Negative Laplacian after backprojection, negatives clipped to zero.
    Laplacian,
    /// Complex Gaussian wavelet along path length before backprojection, magnitude
    /// after (the phasor-field virtual wave).
    Phasor,
}

/// How the pairs reach the voxels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FbpBackprojection {
    /// Every voxel reads every pair's histogram at its own path length: the reference.
    Exact,
    /// On each small box of the volume, the pairs whose path lengths change alike
    /// across it, to within [`FbpSettings::path_error`], merged into one before they
    /// are backprojected (fast factorised backprojection's idea; the phasor filter
    /// only; docs/recon.md, "A hierarchical backprojection").
    Hierarchical,
    /// The hierarchy where a sample of its leaves says it pays (each leaf predicted to
    /// take at most [`AUTO_MAX_COST`] of the exact path's time), with merges only where
    /// they promise as much against the leaves without them (whose arithmetic is the
    /// exact path's to within the legs' quadratic models); the exact path elsewhere,
    /// and for any filter but the phasor one: the default.
    #[default]
    Auto,
}

/// The most of the exact path's time the hierarchy may be predicted to take for
/// [`FbpBackprojection::Auto`] to take it: its cost model (a sample of its leaves'
/// merges, weighed by the measured costs of planning them and of backprojecting what
/// is left) has to promise a third off, more than this machine's speed wanders
/// (docs/recon.md, "A hierarchical backprojection").
pub const AUTO_MAX_COST: f64 = 0.67;

/// The hierarchical backprojection's default bound on a merged pair's path-length
/// error, in phasor wavelengths: at most a quarter-turn of phase for the worst member.
/// On 8,000 pairs lit at one point into 128 × 128 × 64 voxels it ran 4.9 times faster
/// than the exact path at a relative L2 of 0.049 from it; at 1/8, 1.3 times at 0.022
/// (docs/recon.md, "A hierarchical backprojection").
pub const PATH_ERROR_WAVELENGTHS: f64 = 0.25;

/// The phasor wavelength per sampling pitch: y-tal's published settings (0.08 m for a
/// 3.1 cm grid, 0.15 m for 300 points on 1 m², i.e. 5.8 cm apart) are 2.5–2.6 pitches.
pub const PHASOR_PITCHES: f64 = 2.5;

/// The phasor envelope's width σ per wavelength on measured data: y-tal's `fbp` and
/// Liu et al.'s, 1/√2. The wavelet's gain at zero frequency is then e^{−(2πσ/λ)²/2} =
/// 5·10⁻⁵ of its peak, so the backprojection's positive blob, ambient light and the
/// shot noise of the bright bins stay out.
pub const SIGMA_PER_WAVELENGTH: f64 = std::f64::consts::FRAC_1_SQRT_2;

/// The phasor envelope's width σ per wavelength on the virtual confocal scan after
/// 3D-GTR, when `[fbp] sigma-per-wavelength` is not set. That scan has no shot noise
/// or ambient light to keep out, so a shorter envelope (a wider band, gain 8·10⁻⁴ at
/// zero frequency) buys depth resolution: on the validation captures it raised the
/// IoU of all six, by 0.01 to 0.06 over three seeds, where 0.5 (gain 7·10⁻³) lost
/// confocal_planar and 0.35 (9·10⁻²) brought back the blob (docs/recon.md, "Which
/// solver after 3D-GTR"). On measured captures the same 0.6 lowered FBP's IoU.
pub const VIRTUAL_SCAN_SIGMA_PER_WAVELENGTH: f64 = 0.6;

/// The width of the low-pass that takes a histogram's slow part (ambient light) off
/// before the falloff weight, in phasor wavelengths: its gain is e^{−18π²} at 1/λ and
/// 0.17 at 0.1/λ, where the band-pass's is 3·10⁻³ (σ = λ/√2), so what it takes off is
/// what the band-pass drops anyway. At one wavelength it reached into the band: the
/// virtual scan's images after 3D-GTR moved by 3–4 % of their peak.
const LOW_PASS_WAVELENGTHS: f64 = 3.0;

/// FBP settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct FbpSettings {
    /// The filter.
    pub filter: FbpFilter,
    /// Weight each contribution by (d_i·d_d)^falloff: 2 undoes the 1/r² intensity
    /// falloff of both legs, 1 the 1/r amplitude of two spherical waves, 0 none.
    /// Applied as (ℓ/2)^(2·falloff) on each histogram bin at path length ℓ before the
    /// filter, times (4·d_i·d_d/ℓ²)^falloff at the voxel (see the module comment).
    pub falloff: f64,
    /// Phasor wavelength λ, metres of path length; `None`: 2.5 × the coarser of the
    /// detection points' sampling pitch and the volume's lateral voxel pitch (and at
    /// least 4 bins; [`phasor_wavelength`]).
    pub wavelength: Option<f64>,
    /// Phasor envelope width σ as a fraction of λ; `None`: [`SIGMA_PER_WAVELENGTH`]
    /// (y-tal's 1/√2), or [`VIRTUAL_SCAN_SIGMA_PER_WAVELENGTH`] on the virtual scan
    /// after 3D-GTR.
    pub sigma_per_wavelength: Option<f64>,
    /// Weigh each pair by its share of the relay ([`super::pair_weights`]: 1 on a full
    /// grid, Voronoi cells of scattered or perforated samples); `false`: every pair
    /// alike.
    pub relay_weights: bool,
    /// How the pairs reach the voxels: `auto` (the default) takes the hierarchy where
    /// it pays and the exact path elsewhere; `hierarchical` needs the phasor filter. A
    /// confocal scan on a grid that fits the voxels, and a GPU, take their own exact
    /// paths either way.
    pub backprojection: FbpBackprojection,
    /// The hierarchical backprojection's bound on the path-length error a merge may
    /// leave at any voxel, in phasor wavelengths ([`PATH_ERROR_WAVELENGTHS`]: a
    /// quarter).
    pub path_error: f64,
    /// On photon counts with the phasor filter, take the background's noise floor
    /// off every voxel (the noise power the background's counts put there, times
    /// the logarithm of the voxels along the relay's normal, off the squared
    /// magnitude, which keeps at least 1/16 of itself), so that the falloff weight
    /// cannot lift noise far behind a dim target over it; `false`: the magnitude as
    /// backprojected.
    pub noise_floor: bool,
}

impl Default for FbpSettings {
    fn default() -> Self {
        Self {
            filter: FbpFilter::Phasor,
            falloff: 1.0,
            wavelength: None,
            sigma_per_wavelength: None,
            relay_weights: true,
            backprojection: FbpBackprojection::Auto,
            path_error: PATH_ERROR_WAVELENGTHS,
            noise_floor: true,
        }
    }
}

impl FbpSettings {
    /// Checks every setting is in range.
    pub fn validate(&self) -> Result<(), SolverError> {
        if let Some(w) = self.wavelength
            && !(w.is_finite() && w > 0.0)
        {
            return Err(SolverError::Setting {
                name: "wavelength",
                value: w.to_string(),
                expected: "a positive length in metres",
            });
        }
        if !(self.falloff.is_finite() && (0.0..=4.0).contains(&self.falloff)) {
            return Err(SolverError::Setting {
                name: "falloff",
                value: self.falloff.to_string(),
                expected: "between 0 and 4",
            });
        }
        if let Some(s) = self.sigma_per_wavelength
            && !(s.is_finite() && (0.05..=10.0).contains(&s))
        {
            return Err(SolverError::Setting {
                name: "sigma-per-wavelength",
                value: s.to_string(),
                expected: "between 0.05 and 10",
            });
        }
        if !(self.path_error.is_finite() && self.path_error > 0.0 && self.path_error <= 0.5) {
            return Err(SolverError::Setting {
                name: "path-error",
                value: self.path_error.to_string(),
                expected: "between 0 and 0.5 wavelengths (above 0)",
            });
        }
        if self.backprojection == FbpBackprojection::Hierarchical && self.filter != FbpFilter::Phasor {
            return Err(SolverError::Setting {
                name: "backprojection",
                value: "hierarchical".into(),
                expected: "\"exact\" unless filter = \"phasor\" (the hierarchy bounds its error in phasor wavelengths)",
            });
        }
        Ok(())
    }
}

/// The sampling pitch of a set of relay points: the spacing `p` of a regular grid
/// whose bounding rectangle (in the points' best-fit plane), widened by one `p` along
/// each side, holds one cell of `p²` per point: `(W + p)(H + p) = n·p²`. A regular
/// grid of any aspect whose rows run along world x (the rectangle's frame, as
/// [`crate::relay::VirtualRelay::fitted`] lays it) gives exactly its spacing; one turned
/// from it, somewhat more; scattered points their mean spacing.
/// A point listed k times counts k times (FBP's wavelength: see
/// [`phasor_wavelength`]). `None` for fewer than 3 points or a degenerate set.
pub fn sampling_pitch(points: &[glam::DVec3]) -> Option<f64> {
    if points.len() < 3 {
        return None;
    }
    let centre = points.iter().copied().sum::<glam::DVec3>() / points.len() as f64;
    let relay = crate::relay::VirtualRelay::fitted(points, centre + glam::DVec3::Z, None, [2, 2]).ok()?;
    // (n − 1)p² − (W + H)p − WH = 0, its positive root.
    let (w, h, n) = (relay.size[0], relay.size[1], points.len() as f64);
    let pitch = ((w + h) + ((w + h).powi(2) + 4.0 * (n - 1.0) * w * h).sqrt()) / (2.0 * (n - 1.0));
    (pitch.is_finite() && pitch > 0.0).then_some(pitch)
}

/// The volume's voxel pitch across a relay facing `normal`: the coarser of the voxel's
/// two sides along the world axes other than the one nearest the normal (x and y for a
/// relay facing ±z). An image is sampled at this pitch laterally.
pub fn lateral_voxel_pitch(grid: &VolumeGrid, normal: glam::DVec3) -> f64 {
    let voxel = grid.voxel().to_array();
    let n = normal.abs().to_array();
    let along = (0..3).fold(2, |best, a| if n[a] > n[best] { a } else { best });
    (0..3)
        .filter(|&a| a != along)
        .map(|a| voxel[a])
        .fold(0.0, f64::max)
}

/// The phasor filter's wavelength for `set` on `grid`: the setting, or 2.5 × the
/// coarser of the detection points' pitch and the volume's lateral voxel pitch
/// ([`lateral_voxel_pitch`]), at least 4 bins.
///
/// The relay's pitch bounds what the data resolve (a shorter wave aliases across the
/// relay); the voxel pitch bounds what the volume can hold. Every pair's detection
/// point counts, so k lasers sharing a detection grid shorten the wave √k-fold: the
/// lasers sample the aperture too, and on y-tal's exhaustive fixture the detection
/// grid's own pitch (each point once) blurred the silhouette from IoU 0.82 to 0.56. A wave shorter than 2.5
/// voxels builds detail finer than the voxels, which sampling at their centres turns
/// into speckle: on the virtual scan after 3D-GTR, whose pitch is half a voxel, the
/// fitted primitives' scatter in depth (a few millimetres to centimetres where the
/// relay saw a surface obliquely) then interferes within a pixel and dims whole
/// surfaces (docs/recon.md, "The phasor wavelength after 3D-GTR").
pub fn phasor_wavelength(set: &TransientSet, grid: &VolumeGrid, settings: &FbpSettings) -> f64 {
    wavelength_of(set.pairs(), set.axis(), grid, settings)
}

/// [`phasor_wavelength`] of `pairs` on `axis`.
fn wavelength_of(pairs: &[crate::Pair], axis: &TimeAxis, grid: &VolumeGrid, settings: &FbpSettings) -> f64 {
    let floor = 4.0 * axis.width;
    settings
        .wavelength
        .unwrap_or_else(|| {
            let points: Vec<glam::DVec3> = pairs.iter().map(|p| p.xd).collect();
            let normal: glam::DVec3 = pairs.iter().map(|p| p.nd).sum();
            let image = lateral_voxel_pitch(grid, normal);
            PHASOR_PITCHES * sampling_pitch(&points).map_or(image, |d| d.max(image))
        })
        .max(floor)
}

/// The phasor filter for histograms of one length: the band-pass of wavelength
/// `lambda` and envelope `sigma` on bins of `width` metres, with `lead` bins of
/// padding before and after, and the path-length part of the falloff weight. The FFT
/// plans are made once and shared by every histogram (making one costs more than
/// using it).
///
/// The FFT runs over the padded histogram and a further `2·lead` bins after it
/// ([`PhasorFilter::join`]) that are not returned: a raised cosine from the last value
/// back to the first. The FFT is circular, and without them the padding's last bin
/// met its first in a step of the histogram's two ends, whose wavelet the bins
/// outside the recorded window read (until 2026-12-07).
struct PhasorFilter {
    fwd: Arc<dyn Fft<f32>>,
    inv: Arc<dyn Fft<f32>>,
    /// The band-pass gain per frequency bin, already divided by the FFT length.
    gain: Vec<f32>,
    /// With a falloff: the weight (ℓ/2)^2p of every padded bin, and the gain of the
    /// low-pass whose output is taken off before weighing (already divided by the
    /// FFT length).
    falloff: Option<(Vec<f32>, Vec<f32>)>,
    lead: usize,
    /// Bins returned: the histogram and its padding, `bins + 2·lead`.
    padded: usize,
}

impl PhasorFilter {
    fn new(axis: &crate::transient::TimeAxis, lambda: f64, sigma: f64, lead: usize, falloff: f64) -> Self {
        let (bins, width) = (axis.bins, axis.width);
        let padded = bins + 2 * lead;
        let n = padded + Self::join(lead);
        let mut planner = FftPlanner::<f32>::new();
        // exp(−t²/2σ²)·exp(2πi t/λ) ⇒ a Gaussian of std 1/(2πσ) around f = 1/λ, positive
        // frequencies only (an analytic signal); normalised to unit gain at 1/λ.
        let (f0, sf) = (1.0 / lambda, 1.0 / (2.0 * std::f64::consts::PI * sigma));
        let scale = 1.0 / n as f64;
        let freq = |k: usize| k.min(n - k) as f64 / (n as f64 * width);
        let gain = (0..n)
            .map(|k| {
                let g = if k <= n / 2 {
                    2.0 * (-0.5 * ((freq(k) - f0) / sf).powi(2)).exp() * scale
                } else {
                    0.0
                };
                g as f32
            })
            .collect();
        // The low-pass: a Gaussian of σ = 3λ along path length (LOW_PASS_WAVELENGTHS),
        // which holds the histogram's slow part (ambient light) and nothing of the band.
        let falloff = (falloff != 0.0).then(|| {
            let mut weights = path_falloff(axis, falloff, lead);
            // Across the join, the weights go back as the values do.
            let (first, last) = (weights[0], weights[padded - 1]);
            weights.extend((0..Self::join(lead)).map(|i| Self::joined(last, first, i, Self::join(lead))));
            let sl = 1.0 / (2.0 * std::f64::consts::PI * LOW_PASS_WAVELENGTHS * lambda);
            let low = (0..n)
                .map(|k| ((-0.5 * (freq(k) / sl).powi(2)).exp() * scale) as f32)
                .collect();
            (weights, low)
        });
        Self {
            fwd: planner.plan_fft_forward(n),
            inv: planner.plan_fft_inverse(n),
            gain,
            falloff,
            lead,
            padded,
        }
    }

    /// Bins after the padding, not returned, over which the FFT's circular buffer goes
    /// from the last value back to the first: two envelopes' worth of three widths
    /// (the padding's own length twice), so neither end's wavelet reaches the other
    /// end's change and the change is smooth on the band's scale (its spectrum at the
    /// band's centre is under 1 % of a step's).
    fn join(lead: usize) -> usize {
        2 * lead
    }

    /// The `i`-th of `len` bins of a raised cosine from `from` to `to`, both ends left
    /// out (they are the neighbouring bins' values).
    fn joined(from: f32, to: f32, i: usize, len: usize) -> f32 {
        super::fft::raised_cosine(f64::from(from), f64::from(to), i, len) as f32
    }

    /// The power white noise of unit variance a bin has after the band-pass, as the
    /// backprojection reads it between bin centres: the wavelet's energy `‖h‖²` (the
    /// sum over bins of its impulse response's squared magnitude; by Parseval the FFT
    /// length times the sum of the squared gains, which carry the inverse FFT's 1/n),
    /// times `2/3 + ρ/3`, the mean over the fraction `t` of `(1 − t)² + t² + 2t(1 − t)ρ`
    /// with `ρ` the filtered noise's correlation from one bin to the next (about
    /// `cos(2π·width/λ)`: 0.96 of the energy at 12 bins a wavelength).
    fn noise_power(&self) -> f64 {
        let n = self.gain.len();
        let (mut energy, mut next) = (0.0f64, 0.0f64);
        for (k, &g) in self.gain.iter().enumerate() {
            let g2 = f64::from(g) * f64::from(g);
            energy += g2;
            next += g2 * (2.0 * std::f64::consts::PI * k as f64 / n as f64).cos();
        }
        let rho = if energy > 0.0 { next / energy } else { 0.0 };
        n as f64 * energy * (2.0 + rho) / 3.0
    }

    /// Band-passes `h`; returns its real and imaginary parts interleaved, with `lead`
    /// bins before and after (so the wavelet does not wrap around). The padding
    /// repeats the first and last values: a level that runs off either end of the
    /// histogram (ambient light, a cropped axis) is no edge for the band-pass to ring at.
    ///
    /// With a falloff, the histogram's slow part (its low-pass) is taken off and the
    /// rest weighed by (ℓ/2)^2p before the band-pass: weighed whole, a constant
    /// ambient level would become a ramp that the padding ends in a kink, and the
    /// band-pass would ring there. The band-pass drops the slow part anyway.
    fn apply(&self, h: &[f32]) -> Vec<f32> {
        let lead = self.lead;
        let (first, last) = (
            h.first().copied().unwrap_or(0.0),
            h.last().copied().unwrap_or(0.0),
        );
        let n = self.gain.len();
        let mut buf = vec![Complex::<f32>::default(); n];
        for (i, b) in buf.iter_mut().enumerate() {
            b.re = if i < lead {
                first
            } else if i < self.padded {
                h.get(i - lead).copied().unwrap_or(last)
            } else {
                Self::joined(last, first, i - self.padded, n - self.padded)
            };
        }
        if let Some((weights, low)) = &self.falloff {
            let mut slow = buf.clone();
            self.fwd.process(&mut slow);
            for (b, &g) in slow.iter_mut().zip(low) {
                *b *= g;
            }
            self.inv.process(&mut slow);
            for ((b, s), &w) in buf.iter_mut().zip(&slow).zip(weights) {
                b.re = (b.re - s.re) * w;
            }
        }
        self.fwd.process(&mut buf);
        for (b, &g) in buf.iter_mut().zip(&self.gain) {
            *b *= g;
        }
        self.inv.process(&mut buf);
        buf[..self.padded].iter().flat_map(|c| [c.re, c.im]).collect()
    }
}

/// Filtered backprojection of `set` onto `grid`, on the CPU.
pub fn fbp(set: &TransientSet, grid: &VolumeGrid, settings: &FbpSettings) -> Result<Volume, SolverError> {
    fbp_on(set, grid, settings, &Compute::Cpu)
}

/// [`fbp`] with its backprojection on `compute` (the filter runs on the CPU either
/// way: it is a per-pair FFT, a few percent of the work).
pub fn fbp_on(
    set: &TransientSet,
    grid: &VolumeGrid,
    settings: &FbpSettings,
    compute: &Compute,
) -> Result<Volume, SolverError> {
    settings.validate()?;
    if set.is_empty() {
        return Err(SolverError::Empty);
    }
    // Until 2026-12-06 FBP imaged such a volume without a word (the scene mirrored,
    // or every column at its far end), where RSD and 3D-GTR refuse it.
    super::refuse_a_volume_behind(set.pairs(), grid)?;
    // Each pair's share of the relay integral: 1 on full grids, the Voronoi cells of
    // scattered or perforated samples.
    let quadrature = settings
        .relay_weights
        .then(|| super::quadrature::pair_weights(set.pairs()))
        .flatten();
    if let Some(q) = &quadrature {
        let (lo, hi) = q
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(lo, hi), &w| (lo.min(w), hi.max(w)));
        tracing::info!(
            pairs = q.len(),
            smallest = lo,
            largest = hi,
            "FBP weighs each pair by its share of the relay (mean 1; [fbp] relay-weights = false turns this off)"
        );
    }
    let weight = |p: usize| set.weight(p) * quadrature.as_ref().map_or(1.0, |q| q[p] as f32);
    if settings.filter == FbpFilter::Phasor {
        let (lambda, sigma) = phasor_envelope(set.pairs(), set.axis(), grid, settings)?;
        tracing::info!(
            wavelength = lambda,
            "FBP phasor wavelength (2.5 x the coarser of the relay's sampling pitch and the voxels' lateral pitch; [fbp] wavelength sets it)"
        );
        // Three envelope widths each side: the wavelet's support.
        let lead = (3.0 * sigma / set.axis().width).ceil() as usize + 1;
        // Real and imaginary parts interleaved, so one backprojection pass computes
        // each voxel's path length once and gathers both from one place.
        let filter = PhasorFilter::new(set.axis(), lambda, sigma, lead, settings.falloff);
        let hists: Vec<Vec<f32>> = (0..set.len())
            .into_par_iter()
            .map(|p| {
                let w = weight(p);
                let h: Vec<f32> = set.measured(p).iter().map(|v| v * w).collect();
                filter.apply(&h)
            })
            .collect();
        let tolerance = settings.path_error * lambda;
        let own_fast_form = || compute.gpu().is_some() || grid::ConfocalGrid::detect(set, grid).is_some();
        let hierarchical = match settings.backprojection {
            FbpBackprojection::Exact => None,
            FbpBackprojection::Hierarchical if own_fast_form() => {
                tracing::info!(
                    "FBP takes its exact path despite [fbp] backprojection = \"hierarchical\": on a GPU, or for a confocal grid that fits the voxels, the exact path has its own fast form"
                );
                None
            }
            FbpBackprojection::Hierarchical => Some(tree::choose(set, grid, lambda, tolerance).merged),
            FbpBackprojection::Auto if own_fast_form() => None,
            FbpBackprojection::Auto => {
                // Merges trade accuracy for time: taken only where they promise a third
                // off the leaves without them, as the hierarchy must promise a third
                // off the exact path.
                let choices = tree::choose(set, grid, lambda, tolerance);
                let choice = if choices.merged.cost <= AUTO_MAX_COST * choices.unmerged.cost {
                    choices.merged
                } else {
                    choices.unmerged
                };
                let pays = choice.cost <= AUTO_MAX_COST;
                tracing::info!(
                    leaf = ?choice.shape,
                    merges = choice.merges,
                    share = choice.share,
                    predicted_cost = choice.cost,
                    merged_cost = choices.merged.cost,
                    at_most = AUTO_MAX_COST,
                    "FBP {}: a sample of the hierarchy's leaves predicts this time against the exact path's ([fbp] backprojection = \"auto\")",
                    if pays {
                        "takes the hierarchy"
                    } else {
                        "takes its exact path"
                    }
                );
                pays.then_some(choice)
            }
        };
        let sums = if let Some(choice) = hierarchical {
            // Without merges the leaves' tolerance is none.
            let tolerance = if choice.merges { tolerance } else { 0.0 };
            let (sums, stats) = tree::backproject_tree(
                set,
                grid,
                settings.falloff,
                hists,
                lead,
                lambda,
                tolerance,
                choice.shape,
            );
            tracing::info!(
                pairs = set.len(),
                leaf = ?choice.shape,
                merges = choice.merges,
                leaves = stats.leaves,
                sources_per_leaf = stats.leaf_sources as f64 / stats.leaves.max(1) as f64,
                path_error_m = tolerance,
                "FBP backprojected through the hierarchy ([fbp] backprojection = \"exact\" reads every pair at every voxel)"
            );
            sums
        } else {
            backproject::<2, 4>(set, grid, settings.falloff, hists, lead, compute)?
        };
        let data = sums.iter().map(|[a, b]| a.hypot(*b)).collect();
        let mut volume = Volume { grid: *grid, data };
        if settings.noise_floor && set.is_photon_counts() {
            let roi = crate::roi::RoiBox::from_bounds(grid.min(), grid.max()).ok();
            let background = crate::gtr::estimate_background(set, roi.as_ref());
            let power = noise::power(
                set,
                grid,
                &weight,
                settings.falloff,
                filter.noise_power(),
                background,
            );
            let normal = noise::mean_normal(set);
            noise::remove(&mut volume, &power, normal);
            tracing::info!(
                background,
                threshold = noise::threshold(grid, normal),
                "FBP took the background's noise floor off the volume: the noise power its counts put in each voxel, times the threshold ([fbp] noise-floor = false keeps it)"
            );
        }
        return Ok(volume);
    }
    let by_path = path_falloff(set.axis(), settings.falloff, 0);
    let hists: Vec<Vec<f32>> = (0..set.len())
        .map(|p| {
            let w = weight(p);
            set.measured(p)
                .iter()
                .zip(&by_path)
                .map(|(v, g)| v * w * g)
                .collect()
        })
        .collect();
    let data = backproject::<1, 2>(set, grid, settings.falloff, hists, 0, compute)?
        .into_iter()
        .map(|[v]| v)
        .collect();
    let mut volume = Volume { grid: *grid, data };
    if settings.filter == FbpFilter::Laplacian {
        volume = negative_laplacian(&volume);
    }
    Ok(volume)
}

/// The phasor filter's wavelength and envelope sigma for `pairs` on `axis`, once the
/// two are known to suit it: a wave set at least 4 bins long, an envelope at most
/// [`super::MAX_ENVELOPE_SPANS`] time axes.
pub(super) fn phasor_envelope(
    pairs: &[crate::Pair],
    axis: &TimeAxis,
    grid: &VolumeGrid,
    settings: &FbpSettings,
) -> Result<(f64, f64), SolverError> {
    // A wave set shorter than the axis resolves is refused, not quietly lengthened
    // (as RSD refuses one): the image would not be the one asked for.
    let floor = 4.0 * axis.width;
    if let Some(w) = settings.wavelength
        && w < floor
    {
        return Err(SolverError::Setting {
            name: "wavelength",
            value: format!("{w} m"),
            expected: "at least 4 bins of the capture's time axis (a shorter wave aliases between bins): leave it out for the default, or give a longer one",
        });
    }
    let lambda = wavelength_of(pairs, axis, grid, settings);
    let sigma = settings.sigma_per_wavelength.unwrap_or(SIGMA_PER_WAVELENGTH) * lambda;
    // The wavelet's support is padded each side of every histogram, all held at
    // once: one many times longer than the time axis filters nothing the axis holds,
    // and its padding would not fit in memory (`wavelength = 10.0`, a typo for 0.10,
    // asked for 4.8 GB on a 128 × 128 capture of 4 ps bins).
    let span = axis.bins as f64 * axis.width;
    if !(6.0 * sigma <= super::MAX_ENVELOPE_SPANS * span) {
        return Err(SolverError::Setting {
            name: "wavelength",
            value: format!(
                "{lambda} (an envelope of {} m with sigma-per-wavelength {}, against a time axis of {span} m)",
                6.0 * sigma,
                sigma / lambda
            ),
            expected: "an envelope (6 sigma) at most 8 times the time axis's length: a shorter [fbp] wavelength (recon.fbp.wavelength in a plan), or, where it is left to the default (2.5 times the coarser of the relay's sampling pitch and the voxels' lateral pitch), finer voxels across ([volume] shape, recon.volume.shape in a plan); a run's capture is kept, and `periscope recon RUN_DIR --config RECON.toml` reconstructs it again",
        });
    }
    Ok((lambda, sigma))
}

/// The part of the falloff weight (d_i·d_d)^`falloff` that depends on path length
/// alone, (ℓ/2)^(2·falloff), at each bin's centre ℓ (0 before path length 0), for the
/// axis' bins with `lead` more before and after.
fn path_falloff(axis: &crate::transient::TimeAxis, falloff: f64, lead: usize) -> Vec<f32> {
    (0..axis.bins + 2 * lead)
        .map(|b| {
            let half = (0.5 * axis.centre(b as f64 - lead as f64)).max(0.0);
            match falloff {
                0.0 => 1.0,
                1.0 => (half * half) as f32,
                2.0 => (half * half * half * half) as f32,
                p => half.powf(2.0 * p) as f32,
            }
        })
        .collect()
}

/// Backprojects `hists` onto `grid`. Each holds `C` interleaved channels per bin (the
/// phasor filter's real and imaginary parts, or one plain histogram) on the set's axis
/// shifted by `lead` bins (bin `lead` is the axis' bin 0). Returns the `C` sums per
/// voxel. A confocal scan on a grid that fits the voxels takes [`grid`]'s path, any
/// other set [`backproject_pairs`], which reads each bin and the next as one `[f32; D]`
/// (`D = 2C`). The histograms carry the path-length part of the falloff weight
/// ([`path_falloff`]); the general path multiplies the rest, (4·d_i·d_d/ℓ²)^`falloff`,
/// which is 1 on the grid path's confocal pairs. On a GPU every set takes the general
/// path's arithmetic ([`crate::gpu::backproject`]).
fn backproject<const C: usize, const D: usize>(
    set: &TransientSet,
    grid: &VolumeGrid,
    falloff: f64,
    hists: Vec<Vec<f32>>,
    lead: usize,
    compute: &Compute,
) -> Result<Vec<[f32; C]>, SolverError> {
    if let Some(gpu) = compute.gpu() {
        let points: Vec<([f32; 3], [f32; 3])> = set
            .pairs()
            .iter()
            .map(|p| (p.xi.as_vec3().to_array(), p.xd.as_vec3().to_array()))
            .collect();
        let sums = crate::gpu::backproject(gpu, &points, &hists, C, grid, set.axis(), lead, falloff)?;
        return Ok(sums
            .chunks_exact(C)
            .map(|c| std::array::from_fn(|i| c[i]))
            .collect());
    }
    // Each path's layout replaces the histograms, which are dropped before the sums.
    Ok(match grid::ConfocalGrid::detect(set, grid) {
        Some(scan) => {
            let padded = pad::<C>(&hists);
            drop(hists);
            backproject_grid(&scan, set, grid, &padded, lead)
        }
        None => {
            let doubled = doubled::<C, D>(&hists);
            drop(hists);
            backproject_pairs(set, grid, falloff, &doubled, lead)
        }
    })
}

/// The histograms padded with one zero bin before and two after, so the interpolation
/// needs no bounds checks: indices are clamped into the padding instead.
fn pad<const C: usize>(hists: &[Vec<f32>]) -> Vec<Vec<f32>> {
    hists
        .iter()
        .map(|h| {
            let mut p = Vec::with_capacity(h.len() + 3 * C);
            p.extend([0.0; C]);
            p.extend_from_slice(h);
            p.extend([0.0; C]);
            p.extend([0.0; C]);
            p
        })
        .collect()
}

/// The padded index of path length 0, negated: path length L falls at padded index
/// `L / width − offset` (bin b's centre is at `start + (b + ½)·width`, and the padding
/// adds `lead + 1` bins before bin 0).
fn index_offset(set: &TransientSet, lead: usize) -> f64 {
    let axis = set.axis();
    axis.start / axis.width + 0.5 - lead as f64 - 1.0
}

/// [`backproject`] for a confocal scan on a grid that fits the voxels.
fn backproject_grid<const C: usize>(
    scan: &grid::ConfocalGrid,
    set: &TransientSet,
    grid: &VolumeGrid,
    padded: &[Vec<f32>],
    lead: usize,
) -> Vec<[f32; C]> {
    let inv_w = 1.0 / set.axis().width;
    let runs = grid::Runs::<C>::new(scan, grid, padded, inv_w, index_offset(set, lead));
    // Split by depth slices: every voxel sums the relay rows in their order, whatever
    // the split, so the volume has the same bits on any number of threads (bands of
    // relay rows summed afterwards, as until 2026-12-04, rounded differently with
    // the thread count, and held a volume a thread).
    let [nx, ny, nz] = grid.shape;
    let slice = nx * ny * C;
    let per_task = nz.div_ceil(rayon::current_num_threads().max(1)).max(1);
    let mut data = vec![[0.0f32; C]; grid.len()];
    data.as_flattened_mut()
        .par_chunks_mut(per_task * slice)
        .enumerate()
        .for_each(|(t, out)| {
            crate::simd::dispatch(GridSlices {
                out,
                first: t * per_task,
                runs: &runs,
            })
        });
    data
}

/// Depth slices `first..` of [`backproject_grid`], every relay row.
struct GridSlices<'a, 'b, const C: usize> {
    out: &'b mut [f32],
    first: usize,
    runs: &'b grid::Runs<'a, C>,
}

impl<const C: usize> crate::simd::Work for GridSlices<'_, '_, C> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) {
        self.runs.slices(self.out, self.first);
    }
}

/// [`backproject`] for any pairs.
///
/// Per voxel and pair the work is two square roots, the fractional bin, the falloff
/// gain and a linear interpolation of each channel. The first three run as one loop
/// along x that the compiler vectorises (eight voxels at a time with AVX2), the gather
/// as a second; both run inside [`crate::simd::dispatch`]. The falloff gain is the
/// voxel's part of the weight, `q^p` with `q = 4·d_i·d_d/(d_i + d_d)²` (the
/// histograms carry the rest), the common exponents done without `powf`: 1 is `q`, 2
/// is `q²`, 0 is 1.
fn backproject_pairs<const C: usize, const D: usize>(
    set: &TransientSet,
    grid: &VolumeGrid,
    falloff: f64,
    doubled: &[Vec<[f32; D]>],
    lead: usize,
) -> Vec<[f32; C]> {
    let axis = *set.axis();
    let [nx, ny, _] = grid.shape;
    let voxel = grid.voxel();
    let min = grid.min();
    let xs: Vec<f32> = (0..nx)
        .map(|i| (min.x + (i as f64 + 0.5) * voxel.x) as f32)
        .collect();
    let ys: Vec<f32> = (0..ny)
        .map(|i| (min.y + (i as f64 + 0.5) * voxel.y) as f32)
        .collect();
    let inv_w = (1.0 / axis.width) as f32;
    let offset = (axis.start / axis.width + 0.5) as f32 - lead as f32 - 1.0;
    let top = doubled.first().map_or(1, |p| p.len() - 1) as f32;
    let pairs: Vec<([f32; 3], [f32; 3])> = set
        .pairs()
        .iter()
        .map(|p| (p.xi.as_vec3().to_array(), p.xd.as_vec3().to_array()))
        .collect();
    let mut data = vec![[0.0f32; C]; grid.len()];
    data.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
        let z = (min.z + (iz as f64 + 0.5) * voxel.z) as f32;
        let rows = Rows {
            pairs: &pairs,
            hists: doubled,
            xs: &xs,
            ys: &ys,
            inv_w,
            offset,
            top,
            falloff,
        };
        crate::simd::dispatch(Slice { out: slice, z, rows });
    });
    data
}

/// What every slice of a backprojection shares.
#[derive(Clone, Copy)]
struct Rows<'a, const D: usize> {
    /// Illumination and detection points.
    pairs: &'a [([f32; 3], [f32; 3])],
    /// Padded histograms, one per pair, each bin with the next ([`doubled`]).
    hists: &'a [Vec<[f32; D]>],
    /// Voxel centres along x and y.
    xs: &'a [f32],
    ys: &'a [f32],
    /// 1 / bin width; the padded index of path length 0 (negated); the last index.
    inv_w: f32,
    offset: f32,
    top: f32,
    falloff: f64,
}

/// One z slice of [`backproject`]: every pair, every row.
struct Slice<'a, 'b, const C: usize, const D: usize> {
    out: &'b mut [[f32; C]],
    z: f32,
    rows: Rows<'a, D>,
}

impl<const C: usize, const D: usize> crate::simd::Work for Slice<'_, '_, C, D> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) {
        backproject_slice(self.out, self.z, self.rows);
    }
}

#[inline(always)]
fn backproject_slice<const C: usize, const D: usize>(slice: &mut [[f32; C]], z: f32, rows: Rows<'_, D>) {
    let Rows {
        pairs,
        hists,
        xs,
        ys,
        inv_w,
        offset,
        top,
        falloff,
    } = rows;
    let nx = xs.len();
    let mut index = vec![0.0f32; nx];
    let mut gain = vec![1.0f32; nx];
    let mut bin = vec![0i32; nx];
    let (mut w0, mut w1) = (vec![0.0f32; nx], vec![0.0f32; nx]);
    // Pairs in tiles whose histograms stay in L2 while every row of the slice visits
    // them; the row being summed stays in L1.
    for (tile, hists) in pairs.chunks(PAIR_TILE).zip(hists.chunks(PAIR_TILE)) {
        for (row, &y) in slice.chunks_exact_mut(nx).zip(ys) {
            for (&(xi, xd), h) in tile.iter().zip(hists) {
                let byi = (z - xi[2]) * (z - xi[2]) + (y - xi[1]) * (y - xi[1]);
                let byd = (z - xd[2]) * (z - xd[2]) + (y - xd[1]) * (y - xd[1]);
                path_row(
                    xs, byi, byd, xi[0], xd[0], inv_w, offset, top, falloff, &mut index, &mut gain,
                );
                weights_row(&index, &gain, &mut bin, (&mut w0, &mut w1));
                gather_row(row, &bin, (&w0, &w1), h);
            }
        }
    }
}

/// The fractional bin (into the padded histogram) and the falloff gain of every voxel
/// of a row, for one pair.
#[inline(always)]
fn path_row(
    xs: &[f32],
    byi: f32,
    byd: f32,
    xi: f32,
    xd: f32,
    inv_w: f32,
    offset: f32,
    top: f32,
    falloff: f64,
    index: &mut [f32],
    gain: &mut [f32],
) {
    let lanes = index.iter_mut().zip(gain.iter_mut()).zip(xs);
    for ((f, g), &x) in lanes {
        let ri = (byi + (x - xi) * (x - xi)).sqrt();
        let rd = (byd + (x - xd) * (x - xd)).sqrt();
        let path = ri + rd;
        *f = (path * inv_w - offset).max(0.0).min(top);
        // 0, not NaN, for a voxel on a confocal relay point.
        *g = (4.0 * ri * rd) / (path * path).max(f32::MIN_POSITIVE);
    }
    falloff_power(gain, falloff);
}

/// Raises each voxel's part of the falloff weight to the falloff's power.
#[inline(always)]
fn falloff_power(gain: &mut [f32], falloff: f64) {
    match falloff {
        1.0 => {}
        2.0 => gain.iter_mut().for_each(|g| *g *= *g),
        0.0 => gain.fill(1.0),
        p => {
            let p = p as f32;
            gain.iter_mut().for_each(|g| *g = g.powf(p));
        }
    }
}

/// Each voxel's bin below its fractional index and the weights of that bin and the
/// next, `g·(1 − t)` and `g·t` for gain `g` and fraction `t`: the linear interpolation
/// with the gain folded in, computed eight voxels an instruction so that the gather
/// below is only loads and multiply-adds.
#[inline(always)]
fn weights_row(index: &[f32], gain: &[f32], bin: &mut [i32], (w0, w1): (&mut [f32], &mut [f32])) {
    // `index` is clamped to [0, top]; below 2²³, adding 2²³ puts the whole number
    // `below` in the mantissa's low bits, a bit pattern the compiler vectorises, where
    // `as` (saturating, NaN to 0) compiles to a branchy scalar loop. A histogram of
    // 2²³ bins or more (no instrument's) would get a wrong bin, clamped into the
    // histogram by `gather_row`, never an out-of-bounds read.
    const TWO_23: f32 = 8_388_608.0;
    let weights = w0.iter_mut().zip(w1.iter_mut());
    for (((&f, &g), b), (w0, w1)) in index.iter().zip(gain).zip(bin.iter_mut()).zip(weights) {
        let below = f.floor();
        *b = ((below + TWO_23).to_bits() - TWO_23.to_bits()) as i32;
        let upper = g * (f - below);
        (*w0, *w1) = (g - upper, upper);
    }
}

/// The histograms padded as [`pad`] pads them, each padded bin followed by the next
/// one's channels: `[h_b, h_{b+1}]` as `D = 2C` values, so the two values a linear
/// interpolation needs are one load with one bounds check, which the compiler drops
/// (the bin is clamped to the last entry) and the gather vectorises. Twice the padded
/// histograms' memory.
fn doubled<const C: usize, const D: usize>(hists: &[Vec<f32>]) -> Vec<Vec<[f32; D]>> {
    const { assert!(D == 2 * C, "a doubled bin holds two bins of C channels") };
    hists
        .par_iter()
        .map(|h| {
            let bins = h.len() / C;
            // Padded bin b: zero before the histogram and after it.
            let at = |b: usize| match b {
                1.. if b <= bins => &h[(b - 1) * C..b * C],
                _ => &[0.0; C][..],
            };
            (0..bins + 2)
                .map(|b| {
                    let mut v = [0.0f32; D];
                    v[..C].copy_from_slice(at(b));
                    v[C..].copy_from_slice(at(b + 1));
                    v
                })
                .collect()
        })
        .collect()
}

/// Adds each voxel's interpolated, gain-weighted histogram value to the row.
#[inline(always)]
fn gather_row<const C: usize, const D: usize>(
    row: &mut [[f32; C]],
    bin: &[i32],
    (w0, w1): (&[f32], &[f32]),
    h: &[[f32; D]],
) {
    // The bin is already clamped to the padding, so every voxel finds its two bins;
    // `min` keeps a bin from reading beyond the histogram all the same, and lets the
    // compiler drop the bounds check.
    let Some(last) = h.len().checked_sub(1) else {
        return;
    };
    for ((out, &b), (&w0, &w1)) in row.iter_mut().zip(bin).zip(w0.iter().zip(w1)) {
        let v = &h[(b as usize).min(last)];
        for c in 0..C {
            out[c] += w0 * v[c] + w1 * v[C + c];
        }
    }
}

/// −∇² with edge replication, negatives clipped.
fn negative_laplacian(v: &Volume) -> Volume {
    let [nx, ny, nz] = v.grid.shape;
    let h = v.grid.voxel();
    let inv = [1.0 / (h.x * h.x), 1.0 / (h.y * h.y), 1.0 / (h.z * h.z)].map(|x| x as f32);
    let mut out = vec![0.0f32; v.data.len()];
    out.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
        for iy in 0..ny {
            for ix in 0..nx {
                let c = v.at(ix, iy, iz);
                let pair = |a: f32, b: f32, w: f32| (2.0 * c - a - b) * w;
                let lap = pair(
                    v.at(ix.saturating_sub(1), iy, iz),
                    v.at((ix + 1).min(nx - 1), iy, iz),
                    inv[0],
                ) + pair(
                    v.at(ix, iy.saturating_sub(1), iz),
                    v.at(ix, (iy + 1).min(ny - 1), iz),
                    inv[1],
                ) + pair(
                    v.at(ix, iy, iz.saturating_sub(1)),
                    v.at(ix, iy, (iz + 1).min(nz - 1)),
                    inv[2],
                );
                // Negatives clipped, a NaN kept for the caller's finite check (`max`
                // would turn it into 0, and an overflowed region would be written as
                // zeros), as LCT keeps it.
                slice[iy * nx + ix] = if lap < 0.0 { 0.0 } else { lap };
            }
        }
    });
    Volume {
        grid: v.grid,
        data: out,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transient::{Pair, TimeAxis};
    use glam::DVec3;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    /// Backprojection written the obvious way, in f64: every voxel, every pair, the
    /// histogram weighed by the path-length part of the falloff and linearly
    /// interpolated between bin centres (zero outside the axis), times the voxel's
    /// part.
    fn reference(set: &TransientSet, grid: &VolumeGrid, falloff: f64) -> Vec<f64> {
        let axis = set.axis();
        let mut out = vec![0.0; grid.len()];
        let [nx, ny, nz] = grid.shape;
        for iz in 0..nz {
            for iy in 0..ny {
                for ix in 0..nx {
                    let x = grid.centre(ix, iy, iz);
                    let mut sum = 0.0;
                    for (p, pair) in set.pairs().iter().enumerate() {
                        let (ri, rd) = (x.distance(pair.xi), x.distance(pair.xd));
                        let u = (ri + rd - axis.start) / axis.width - 0.5;
                        let h = set.measured(p);
                        // Each bin weighed by (ℓ/2)^2p at its centre ℓ, the voxel by
                        // the rest of (d_i·d_d)^p.
                        let at = |b: f64| {
                            if b < 0.0 || b >= h.len() as f64 {
                                0.0
                            } else {
                                let half = (0.5 * axis.centre(b)).max(0.0);
                                h[b as usize] as f64 * half.powf(2.0 * falloff)
                            }
                        };
                        let b = u.floor();
                        let t = u - b;
                        let q = 4.0 * ri * rd / ((ri + rd) * (ri + rd));
                        sum += q.powf(falloff) * ((1.0 - t) * at(b) + t * at(b + 1.0));
                    }
                    out[(iz * ny + iy) * nx + ix] = sum;
                }
            }
        }
        out
    }

    /// The phasor filter's FFT is circular. Until 2026-12-07 the padding's last bin
    /// (the histogram's last value) met its first bin (the first value) there, and a
    /// histogram whose ends differ (ambient light rising over the window, a cropped
    /// return) put the wavelet of that step on the bins outside the recorded window,
    /// which voxels nearer or farther than the window read. Here the histogram is zero
    /// for its first three quarters and one after (a level that runs off its end): the
    /// filtered bins a padding's width before the window hold only the far tail of the
    /// wavelet of the step inside it, under 1 % of that wavelet's peak, with and without
    /// the falloff weight.
    #[test]
    fn the_filters_padding_does_not_wrap_one_end_onto_the_other() {
        let axis = TimeAxis {
            start: 1.0,
            width: 0.01,
            bins: 256,
        };
        let lambda = 0.2;
        let sigma = SIGMA_PER_WAVELENGTH * lambda;
        let lead = (3.0 * sigma / axis.width).ceil() as usize + 1;
        let h: Vec<f32> = (0..axis.bins).map(|b| if b < 192 { 0.0 } else { 1.0 }).collect();
        for falloff in [0.0, 1.0] {
            let filter = PhasorFilter::new(&axis, lambda, sigma, lead, falloff);
            let out = filter.apply(&h);
            assert_eq!(out.len(), 2 * (axis.bins + 2 * lead));
            let magnitude = |i: usize| f64::from(out[2 * i]).hypot(f64::from(out[2 * i + 1]));
            // The step inside the window, at padded bin lead + 192.
            let peak = (lead + 150..lead + 240).map(magnitude).fold(0.0, f64::max);
            assert!(
                peak > 0.1,
                "falloff {falloff}: the step's wavelet peaks at {peak}"
            );
            // The padding before the window's zeros: 192 bins (over 13 σ) from the step.
            let before = (0..lead).map(magnitude).fold(0.0, f64::max);
            assert!(
                before < 0.01 * peak,
                "falloff {falloff}: {before} before the window against the step's {peak}"
            );
        }
    }

    /// The largest difference between `got` and `want`, and `want`'s largest magnitude.
    fn worst_and_peak(got: &[f64], want: &[f64]) -> (f64, f64) {
        let peak = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let worst = got
            .iter()
            .zip(want)
            .fold(0.0f64, |m, (g, w)| m.max((g - w).abs()));
        (worst, peak)
    }

    /// The plain backprojection of `set` agrees with the f64 reference to single
    /// precision (2e-5 of the volume's peak) for each falloff path: the root product
    /// (1), the squares (2), none (0) and `powf` (1.5). Every pair weighs alike here
    /// (the quadrature weights have tests of their own).
    fn agrees_with_the_reference(set: &TransientSet, grid: &VolumeGrid) {
        for falloff in [1.0, 2.0, 0.0, 1.5] {
            let settings = FbpSettings {
                filter: FbpFilter::None,
                falloff,
                relay_weights: false,
                ..FbpSettings::default()
            };
            let got = fbp(set, grid, &settings).unwrap();
            let got: Vec<f64> = got.data.iter().map(|&v| v as f64).collect();
            let want = reference(set, grid, falloff);
            let (worst, peak) = worst_and_peak(&got, &want);
            assert!(
                worst < 2e-5 * peak,
                "falloff {falloff}: worst error {worst:e} against peak {peak:e}"
            );
            // The GPU's backprojection (every set takes its one path there), to 1e-4
            // of the peak: its square roots need not be correctly rounded.
            if let Some(gpu) = crate::gpu::testing::gpu("fbp on the GPU against the f64 reference") {
                let got = fbp_on(set, grid, &settings, &Compute::Gpu(gpu)).unwrap();
                let got: Vec<f64> = got.data.iter().map(|&v| v as f64).collect();
                let (worst, peak) = worst_and_peak(&got, &want);
                assert!(
                    worst < 1e-4 * peak,
                    "GPU, falloff {falloff}: worst error {worst:e} against peak {peak:e}"
                );
            }
        }
        // The default filter (the phasor field's two channels) and relay weights: the
        // GPU's volume is the CPU's to 1e-4 of the peak.
        if let Some(gpu) = crate::gpu::testing::gpu("phasor fbp on the GPU against the CPU") {
            // The exact path on the CPU as well (its default, `auto`, may take the
            // hierarchy, which a GPU never does).
            let settings = FbpSettings {
                backprojection: FbpBackprojection::Exact,
                ..FbpSettings::default()
            };
            let cpu = fbp(set, grid, &settings).unwrap();
            let on_gpu = fbp_on(set, grid, &settings, &Compute::Gpu(gpu)).unwrap();
            let f = |v: &Volume| v.data.iter().map(|&x| x as f64).collect::<Vec<_>>();
            let (worst, peak) = worst_and_peak(&f(&on_gpu), &f(&cpu));
            assert!(peak > 0.0, "the volume is not empty");
            assert!(
                worst < 1e-4 * peak,
                "GPU phasor: worst error {worst:e} against peak {peak:e}"
            );
        }
    }

    /// `n` pairs on the plane z = 0, both points drawn within `half` of the origin in x
    /// and y, with random histograms.
    fn free_pairs(n: usize, axis: TimeAxis, half: [f64; 2], rng: &mut ChaCha8Rng) -> TransientSet {
        let mut set = TransientSet::new(axis).unwrap();
        for _ in 0..n {
            let mut at = || {
                DVec3::new(
                    rng.random_range(-half[0]..half[0]),
                    rng.random_range(-half[1]..half[1]),
                    0.0,
                )
            };
            let (xi, xd) = (at(), at());
            let h: Vec<f32> = (0..axis.bins).map(|_| rng.random::<f32>()).collect();
            set.push(
                Pair {
                    xi,
                    ni: DVec3::Z,
                    xd,
                    nd: DVec3::Z,
                },
                &h,
            )
            .unwrap();
        }
        set
    }

    /// The vectorised f32 backprojection agrees with the f64 reference to single
    /// precision (relative to the volume's peak), for each falloff path: the root
    /// product (1), the squares (2), none (0) and `powf` (1.5).
    #[test]
    fn backprojection_matches_the_f64_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let axis = TimeAxis {
            start: 0.4,
            width: 0.01,
            bins: 160,
        };
        let set = free_pairs(40, axis, [0.5, 0.5], &mut rng);
        // 19 voxels per row: not a multiple of any vector width.
        let grid = VolumeGrid::new([-0.4, 0.4], [-0.3, 0.3], [0.3, 0.7], [19, 7, 5]).unwrap();
        agrees_with_the_reference(&set, &grid);
    }

    /// A confocal scan of `nx × ny` points at height `z`, columns `pitch` apart from
    /// x = −0.3, rows 0.07 m apart, pushed in a shuffled order, random histograms.
    fn grid_scan(nx: usize, ny: usize, pitch: f64, z: f64, rng: &mut ChaCha8Rng) -> TransientSet {
        use rand::seq::SliceRandom;
        let axis = TimeAxis {
            start: 0.5,
            width: 0.01,
            bins: 160,
        };
        let mut cells: Vec<(usize, usize)> = (0..ny).flat_map(|jy| (0..nx).map(move |jx| (jx, jy))).collect();
        cells.shuffle(rng);
        let mut set = TransientSet::new(axis).unwrap();
        for (jx, jy) in cells {
            let x = DVec3::new(-0.3 + jx as f64 * pitch, -0.2 + jy as f64 * 0.07, z);
            let h: Vec<f32> = (0..axis.bins).map(|_| rng.random::<f32>()).collect();
            set.push(Pair::confocal(x, DVec3::Z), &h).unwrap();
        }
        set
    }

    /// The grid path (a confocal scan whose column pitch is half the voxel pitch, its
    /// origin off the voxel grid, rows at a pitch of their own) agrees with the f64
    /// reference to the same bound as the general path, for every falloff; with two
    /// channels (the phasor filter's) it agrees with the general path.
    #[test]
    fn a_confocal_grid_backprojects_as_the_reference() {
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let set = grid_scan(13, 7, 0.05, 0.02, &mut rng);
        let grid = VolumeGrid::new([-0.45, 0.45], [-0.3, 0.3], [0.3, 0.7], [9, 5, 5]).unwrap();
        assert!(
            grid::ConfocalGrid::detect(&set, &grid).is_some(),
            "the grid path applies"
        );
        agrees_with_the_reference(&set, &grid);
        let lead = 3;
        let hists: Vec<Vec<f32>> = (0..set.len())
            .map(|p| {
                let mut h = vec![0.0f32; 2 * lead];
                h.extend(set.histogram(p).iter().flat_map(|&v| [v, 1.0 - v]));
                h.extend(vec![0.0f32; 2 * lead]);
                h
            })
            .collect();
        let padded = pad::<2>(&hists);
        let scan = grid::ConfocalGrid::detect(&set, &grid).unwrap();
        let fast = backproject_grid::<2>(&scan, &set, &grid, &padded, lead);
        let general = backproject_pairs(&set, &grid, 1.0, &doubled::<2, 4>(&hists), lead);
        let flat = |v: &[[f32; 2]]| v.iter().flatten().map(|&x| x as f64).collect::<Vec<_>>();
        let (worst, peak) = worst_and_peak(&flat(&fast), &flat(&general));
        assert!(
            worst < 4e-5 * peak,
            "two channels: {worst:e} against peak {peak:e}"
        );
    }

    /// Every path gives the same bits on one thread as on several: each voxel sums
    /// its pairs in one order however the work is split (the grid path's bands of
    /// relay rows, summed per thread, had not).
    #[test]
    fn the_volume_has_the_same_bits_on_any_number_of_threads() {
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let scan = grid_scan(13, 7, 0.05, 0.02, &mut rng);
        let grid = VolumeGrid::new([-0.45, 0.45], [-0.3, 0.3], [0.3, 0.7], [9, 5, 17]).unwrap();
        assert!(
            grid::ConfocalGrid::detect(&scan, &grid).is_some(),
            "the grid path applies"
        );
        let free = free_pairs(300, *scan.axis(), [0.4, 0.3], &mut rng);
        let on = |threads: usize, set: &TransientSet, how: FbpBackprojection| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| {
                    let settings = FbpSettings {
                        backprojection: how,
                        ..FbpSettings::default()
                    };
                    fbp(set, &grid, &settings).unwrap().data
                })
        };
        for (set, how, what) in [
            (&scan, FbpBackprojection::Auto, "the grid path"),
            (&free, FbpBackprojection::Exact, "the exact path"),
            (&free, FbpBackprojection::Hierarchical, "the hierarchy"),
        ] {
            let one = on(1, set, how);
            assert!(one.iter().any(|v| *v != 0.0), "{what}: an empty volume");
            for threads in [2, 3] {
                assert!(
                    one == on(threads, set, how),
                    "{what}: one thread and {threads} give different volumes"
                );
            }
        }
    }

    /// The grid path is taken only where its arithmetic holds: confocal pairs, one
    /// plane of constant z, every cell of a regular grid once, and a voxel pitch that
    /// is a whole multiple of the column pitch.
    #[test]
    fn only_a_fitting_confocal_grid_takes_the_grid_path() {
        let mut rng = ChaCha8Rng::seed_from_u64(8);
        let grid = VolumeGrid::new([-0.45, 0.45], [-0.3, 0.3], [0.3, 0.7], [9, 5, 5]).unwrap();
        let fits = |set: &TransientSet| grid::ConfocalGrid::detect(set, &grid).is_some();
        assert!(fits(&grid_scan(6, 4, 0.1, 0.0, &mut rng)), "a pitch of one voxel");
        assert!(
            fits(&grid_scan(19, 4, 0.1 / 3.0, 0.0, &mut rng)),
            "a third of a voxel"
        );
        assert!(
            !fits(&grid_scan(10, 4, 0.03, 0.0, &mut rng)),
            "0.1 / 0.03 is no whole number"
        );
        assert!(
            !fits(&grid_scan(6, 4, 0.2, 0.0, &mut rng)),
            "a pitch of two voxels"
        );
        // More column phases than columns: the layout would be mostly empty (a ratio
        // of 10⁶ asked for 30 GB until 2026-12-06).
        assert!(
            !fits(&grid_scan(6, 4, 0.1 / 7.0, 0.0, &mut rng)),
            "a seventh of a voxel over six columns"
        );
        assert!(
            fits(&grid_scan(7, 4, 0.1 / 7.0, 0.0, &mut rng)),
            "a seventh of a voxel over seven columns"
        );
        let axis = *grid_scan(2, 2, 0.1, 0.0, &mut rng).axis();
        let h = vec![1.0f32; axis.bins];
        let rebuilt = |edit: &dyn Fn(usize, Pair) -> Option<Pair>| {
            let base = grid_scan(6, 4, 0.05, 0.0, &mut ChaCha8Rng::seed_from_u64(1));
            let mut set = TransientSet::new(axis).unwrap();
            for (i, p) in base.pairs().iter().enumerate() {
                if let Some(p) = edit(i, *p) {
                    set.push(p, &h).unwrap();
                }
            }
            set
        };
        assert!(fits(&rebuilt(&|_, p| Some(p))), "the unedited scan");
        assert!(!fits(&rebuilt(&|i, p| (i != 5).then_some(p))), "a missing point");
        let moved = |i: usize, mut p: Pair| {
            if i == 5 {
                p.xd.x += 0.01;
            }
            Some(p)
        };
        assert!(!fits(&rebuilt(&moved)), "one pair not confocal");
        let tilted = |i: usize, mut p: Pair| {
            p.xi.z += 1e-3 * i as f64;
            p.xd = p.xi;
            Some(p)
        };
        assert!(!fits(&rebuilt(&tilted)), "a tilted relay");
        let doubled = |i: usize, p: Pair| {
            Some(if i == 5 {
                rebuilt(&|_, p| Some(p)).pairs()[6]
            } else {
                p
            })
        };
        assert!(!fits(&rebuilt(&doubled)), "a point twice");
    }
}

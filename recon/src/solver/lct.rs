//! The light-cone transform (O'Toole, Lindell and Wetzstein 2018) for confocal scans
//! on a planar grid.
//!
//! A confocal measurement at relay point (x', y') of a scatterer at (x, y, z) arrives at
//! path length ℓ = 2·sqrt((x−x')² + (y−y')² + z²). In the squared coordinates
//! s = (ℓ/ℓmax)² and q = (2z/ℓmax)², s = q + 4·((x−x')² + (y−y')²)/ℓmax²: a shift-invariant
//! 3-D convolution, inverted with a Wiener filter in the Fourier domain. Steps:
//! radiometric weighting ℓ⁴, resampling ℓ → s (with its Jacobian), FFT convolution with
//! the Wiener-filtered light cone, resampling q → z, clamping negatives.
//!
//! Memory: the padded spectrum holds (M + 1)·(2nx)·(2ny) complex f32 values (M bins),
//! 270 MiB for a 128 × 128 × 512 scan. It is processed slice by slice in parallel.
use std::f64::consts::PI;

use rayon::prelude::*;
use realfft::RealFftPlanner;
use rustfft::num_complex::{Complex, Complex32};

use super::fft::Fft2;
use super::{FrameVolume, PlanarScan, SolverError, check_memory, confocal};
use crate::gtr::estimate_background;
use crate::transient::{Pair, TimeAxis, TransientSet};
use crate::volume::{Volume, VolumeGrid};

/// LCT settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct LctSettings {
    /// Signal-to-noise ratio of the Wiener filter; larger is sharper and noisier.
    /// `None`: derived from the capture by [`default_snr`].
    pub snr: Option<f64>,
    /// Exponent of the radiometric weight ℓ^n: 4 for diffuse surfaces, 2 for
    /// retroreflective ones.
    pub falloff: f64,
    /// Distance within which points count as the same grid line, and largest rms
    /// distance from the fitted plane, metres.
    pub grid_tolerance: f64,
    /// Weigh each measured cell by its share of the grid (its Voronoi cell) when some
    /// cells are missing, so the sums over cells stay quadratures of the whole
    /// aperture; `false`: missing cells are zeros and nothing else changes.
    pub relay_weights: bool,
}

impl Default for LctSettings {
    fn default() -> Self {
        Self {
            snr: None,
            falloff: 4.0,
            grid_tolerance: 2e-3,
            relay_weights: true,
        }
    }
}

impl LctSettings {
    /// Checks every setting is in range.
    pub fn validate(&self) -> Result<(), SolverError> {
        // Bounded above too: past f32's range (3.4e38) the filter's 1/snr became 0
        // and the Wiener filter lost its regularisation (a zero of |H|² then NaN).
        if let Some(snr) = self.snr
            && !(snr.is_finite() && snr > 0.0 && snr <= MAX_SNR)
        {
            return Err(SolverError::Setting {
                name: "snr",
                value: snr.to_string(),
                expected: "a positive number, at most 1e12",
            });
        }
        confocal::check_settings(self.falloff, self.grid_tolerance)
    }
}

/// The largest `snr` taken: a Wiener filter at 1e12 is already the plain inverse
/// wherever |H|² is above 1e-12 of its peak.
const MAX_SNR: f64 = 1e12;

/// LCT of a confocal capture on a planar grid, resampled onto `grid`.
pub fn lct(set: &TransientSet, grid: &VolumeGrid, settings: &LctSettings) -> Result<Volume, SolverError> {
    settings.validate()?;
    // As FBP, RSD and 3D-GTR refuse it: LCT resamples positive depths only, and wrote
    // an all-zero volume for it until 2026-12-06.
    super::refuse_a_volume_behind(set.pairs(), grid)?;
    let scan = confocal_scan(set, settings.grid_tolerance)?.reaching(grid);
    Ok(lct_frame(set, &scan, settings)?.to_world(grid))
}

/// LCT's `snr` on the virtual confocal scan after 3D-GTR when `[lct] snr` is not set:
/// the reference code's 0.8. The scan is noise-free but carries the fit's error,
/// which is neither white nor small where the fit is poor: on the two-torso simulator
/// scene (thin limbs, the plan's `solver = "lct"`) 100 cut the median silhouette IoU
/// of three seeds from 0.54 to 0.48, while on the validation captures it raised IoU
/// by 0.01 to 0.07 (docs/recon.md). FBP, the default solver after 3D-GTR, has no such
/// setting.
pub const VIRTUAL_SCAN_SNR: f64 = 0.8;

/// The Wiener filter's signal-to-noise ratio when `[lct] snr` is not set.
///
/// Photon counts ([`TransientSet::is_photon_counts`]): 10·R within [0.8, 100], with
/// R = Σ((c − b)² − c)/Σc, b the background a bin ([`estimate_background`]): an
/// unbiased estimate of Σs²/Σ(s + b) over the bins' signals s, each bin's squared
/// signal-to-noise ratio s²/(s + b) weighted by the photons it holds. Without
/// background it is the photon-weighted mean count of a bin, Σc²/Σc − 1 (the expected
/// count of the bin a photon lands in; its square root is that bin's signal-to-noise
/// ratio). Ambient and dark counts count as noise: taken as signal (until 2026-12-08)
/// they made the filter trust the data more the more ambient light it held, up to
/// the cap on background alone.
/// Anything else (rendered or processed transients): 100, about the level of the
/// cone's own discretisation error, which bounds how far the filter should trust the
/// model. Measured on the validation capture confocal_planar with Poisson noise drawn
/// at a peak of 5, 50 and 500 counts (R 0.24, 5.1, 62): the best fixed snr was ≤ 0.8,
/// 30–300 and ≥ 100, about 10·R each time; without noise 100 scores IoU 0.90 where the
/// reference code's 0.8 scores 0.83.
pub fn default_snr(set: &TransientSet) -> f64 {
    const MODEL_SNR: f64 = 100.0;
    if !set.is_photon_counts() {
        return MODEL_SNR;
    }
    let background = estimate_background(set, None);
    let (mut sum, mut signal) = (0.0f64, 0.0f64);
    for i in 0..set.len() {
        for &c in set.measured(i).iter() {
            let c = f64::from(c.max(0.0));
            sum += c;
            signal += (c - background).powi(2) - c;
        }
    }
    if sum <= 0.0 {
        return MODEL_SNR;
    }
    (10.0 * signal / sum).clamp(0.8, MODEL_SNR)
}

/// Checks every pair is confocal and finds the grid (LCT and f-k migration) of
/// `set`'s pairs.
pub(super) fn confocal_scan(set: &TransientSet, tolerance: f64) -> Result<PlanarScan, SolverError> {
    confocal_grid(set.pairs(), set.left_out_empty(), tolerance)
}

/// [`confocal_scan`] of `pairs`, of which a reader left `left_out` more out as empty.
pub(super) fn confocal_grid(
    pairs: &[Pair],
    left_out: usize,
    tolerance: f64,
) -> Result<PlanarScan, SolverError> {
    if pairs.is_empty() {
        return Err(SolverError::Empty);
    }
    for (i, p) in pairs.iter().enumerate() {
        let d = p.xi.distance(p.xd);
        if d > tolerance {
            return Err(SolverError::NotConfocal {
                pair: i,
                distance_mm: d * 1e3,
            });
        }
    }
    let points: Vec<_> = pairs.iter().map(|p| p.xd).collect();
    let hint = pairs.iter().map(|p| p.nd).sum();
    PlanarScan::detect("confocal scan", &points, hint, tolerance).map_err(|e| match e {
        // The grid is the capture's; what is left of it may be too little to show it.
        SolverError::NotGrid { what, detail } if left_out > 0 => SolverError::NotGrid {
            what,
            detail: format!(
                "{detail}; only {} of the capture's {} transients hold counts inside the volume's time range \
                 (the rest are empty there and were left out): check the volume's depth, or the capture's \
                 t_start and delta_t",
                pairs.len(),
                pairs.len() + left_out
            ),
        },
        e => e,
    })
}

/// LCT's bins from path length 0 over `axis` on `scan`'s grid, once its memory is
/// known to fit.
pub(super) fn lct_bins(scan: &PlanarScan, axis: &TimeAxis) -> Result<usize, SolverError> {
    let [nx, ny] = scan.relay.resolution;
    let m = confocal::bins_from_zero(axis, "LCT")?;
    check_memory("LCT", lct_work_bytes(nx * ny, m))?;
    Ok(m)
}

/// LCT on the scan's own grid: a volume with one slice per bin, depth `(t + ½)·w/2`.
pub fn lct_frame(
    set: &TransientSet,
    scan: &PlanarScan,
    settings: &LctSettings,
) -> Result<FrameVolume, SolverError> {
    settings.validate()?;
    let w = set.axis().width;
    let m = lct_bins(scan, set.axis())?;
    let mut cube = confocal::cube(set, scan, m, settings.relay_weights);

    // Radiometric weight and ℓ → s resampling.
    let resample = Resampling::new(m);
    cube.par_chunks_mut(m).for_each(|line| {
        for (t, v) in line.iter_mut().enumerate() {
            *v *= ((t as f64 + 0.5) / m as f64).powf(settings.falloff) as f32;
        }
        let s = resample.forward(line);
        line.copy_from_slice(&s);
    });

    let snr = settings.snr.unwrap_or_else(|| {
        let snr = default_snr(set);
        tracing::info!(
            snr,
            photon_counts = set.is_photon_counts(),
            "LCT Wiener snr derived from the capture"
        );
        snr
    });
    Ok(filter_cube(cube, scan, m, w, snr, Filter::Wiener))
}

/// LCT of the confocal scan that a volume would cast on `scan`'s grid, computed
/// without the scan: one convolution instead of the scan's rendering and its
/// deconvolution.
///
/// `apexes` holds, for each cell of the grid (`[cell][m]`, row by row), the path-length
/// profile (`m` bins of `w` from path length 0) of what lies under the cell, as the
/// cell itself would measure it after LCT's radiometric weight: a scatterer at depth z
/// of weighted brightness A adds mass A at path length 2z. The light cone each
/// scatterer would cast on every cell is then the same for all of them, so LCT's
/// result, the measured cones' spectrum D times H*/(|H|² + 1/snr), is the apexes'
/// spectrum S times |H|²/(|H|² + 1/snr) (scaled by the cone's norm): the cones are
/// never formed. Unlike a scan's, these cones do not stop at the grid's edge: they
/// wrap around the padded grid, as the filter's model assumes.
pub fn lct_of_apexes(
    mut apexes: Vec<f32>,
    scan: &PlanarScan,
    m: usize,
    w: f64,
    snr: f64,
) -> Result<FrameVolume, SolverError> {
    let [nx, ny] = scan.relay.resolution;
    if !(snr.is_finite() && snr > 0.0) {
        return Err(SolverError::Setting {
            name: "snr",
            value: snr.to_string(),
            expected: "a positive number",
        });
    }
    if m == 0 || apexes.len() != m * nx * ny {
        return Err(SolverError::Axis(format!(
            "{} apex samples for a {nx} × {ny} grid of {m} bins",
            apexes.len()
        )));
    }
    if !(w.is_finite() && w > 0.0) {
        return Err(SolverError::Axis(format!(
            "bin width {w} m: it must be a positive length"
        )));
    }
    check_memory("LCT", lct_work_bytes(nx * ny, m))?;
    let resample = Resampling::new(m);
    apexes.par_chunks_mut(m).for_each(|line| {
        let s = resample.forward(line);
        line.copy_from_slice(&s);
    });
    Ok(filter_cube(apexes, scan, m, w, snr, Filter::Blur))
}

/// The memory LCT allocates for a scan of `cells` grid cells and `m` bins from path
/// length zero: the padded spectra (`m + 1` complex slices of the `2ny × 2nx` grid)
/// and the cube twice, in `f32`. Saturating, so a hostile size is never small.
/// `periscope check` and the solver's own cap read the same figure.
pub fn lct_work_bytes(cells: usize, m: usize) -> usize {
    let slices = (m.saturating_add(1))
        .saturating_mul(4)
        .saturating_mul(cells)
        .saturating_mul(8);
    slices.saturating_add(cells.saturating_mul(m).saturating_mul(8))
}

/// What [`filter_cube`] does with a cube's spectrum D and the light cone's H.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Filter {
    /// D·H*/(|H|² + 1/snr): the Wiener deconvolution of measured cones.
    Wiener,
    /// D·c·|H|²/(|H|² + 1/snr), c the norm of the cone of unit mass per cell: what
    /// `Wiener` makes of the cones that apexes of spectrum D would cast.
    Blur,
}

/// The light-cone filter of a cube already weighted and resampled to s (`[cell][m]`
/// on `scan`'s grid, bins of `w`), and the resampling back to depth.
fn filter_cube(cube: Vec<f32>, scan: &PlanarScan, m: usize, w: f64, snr: f64, filter: Filter) -> FrameVolume {
    let [nx, ny] = scan.relay.resolution;
    let resample = Resampling::new(m);
    // Real FFT along s (padded to 2M), scattered into slices [t'][Y][X] of 2ny × 2nx.
    let (px, py, pt) = (2 * nx, 2 * ny, 2 * m);
    let slice_len = px * py;
    let mut slices = confocal::padded_spectra(&cube, m, [nx, ny]);
    drop(cube);
    let c2r = RealFftPlanner::<f32>::new().plan_fft_inverse(pt);

    // The light cone, each lateral offset's cell integrated over its area.
    let [sx, sy] = scan.relay.spacing();
    let cone = LightCone::new([nx, ny], [sx, sy], m, m as f64 * w);
    let inv_snr = 1.0 / snr as f32;
    let mass = cone.mass_norm as f32;

    let fft = Fft2::new(py, px);
    const SLICES_PER_TASK: usize = 8;
    slices
        .par_chunks_mut(slice_len * SLICES_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            let mut scratch = vec![Complex32::default(); fft.scratch_len()];
            let mut psf = vec![Complex32::default(); slice_len];
            let mut phases = Vec::new();
            for (j, slice) in chunk.chunks_mut(slice_len).enumerate() {
                let kt = task * SLICES_PER_TASK + j;
                let omega = 2.0 * PI * kt as f64 / pt as f64;
                cone.spectrum(omega, &mut phases, &mut psf);
                fft.forward_transposed(&mut psf, &mut scratch);
                fft.forward_transposed(slice, &mut scratch);
                match filter {
                    Filter::Wiener => {
                        for (d, h) in slice.iter_mut().zip(&psf) {
                            *d = *d * h.conj() / (h.norm_sqr() + inv_snr);
                        }
                    }
                    Filter::Blur => {
                        for (d, h) in slice.iter_mut().zip(&psf) {
                            let h2 = h.norm_sqr();
                            *d *= mass * h2 / (h2 + inv_snr);
                        }
                    }
                }
                fft.inverse_from_transposed(slice, &mut scratch);
            }
        });

    // Inverse along s for the unpadded quadrant, then q → z and clamping.
    let scale = 1.0 / (pt * slice_len) as f32;
    let lines: Vec<Vec<f32>> = (0..nx * ny)
        .into_par_iter()
        .map(|cell| {
            let (y, x) = (cell / nx, cell % nx);
            let mut spectrum: Vec<Complex32> = (0..=m).map(|k| slices[k * slice_len + y * px + x]).collect();
            spectrum[0].im = 0.0;
            spectrum[m].im = 0.0;
            let mut out = c2r.make_output_vec();
            c2r.process(&mut spectrum, &mut out)
                .expect("buffer lengths match the plan");
            let q: Vec<f32> = out[..m].iter().map(|v| v * scale).collect();
            // Negative values clamped; a NaN kept, for the caller's finite check (`max`
            // would turn it into 0 and an overflowed capture into an empty volume).
            resample
                .inverse(&q)
                .into_iter()
                .map(|v| if v < 0.0 { 0.0 } else { v })
                .collect()
        })
        .collect();
    drop(slices);
    confocal::frame_from_lines(scan, w, m, &lines)
}

/// The sparse resampling from bins in ℓ to bins in s = (ℓ/ℓmax)², with its Jacobian,
/// as in the reference implementation: fine samples x = 1..M² map to bin ⌈√x⌉ − 1 with
/// weight 1/√x, averaged M at a time into s-bins. Its transpose maps back.
struct Resampling {
    m: usize,
    /// (s-bin, ℓ-bin, weight), sorted by s-bin.
    entries: Vec<(u32, u32, f32)>,
}

impl Resampling {
    /// Each (s-bin, ℓ-bin) entry sums 1/(√x·M) over its run of fine samples: the
    /// runs are found from their ends, and each sum is taken in closed form, so the
    /// table costs O(M) however fine the axis (the sum over all M² samples took minutes
    /// at M = 3·10⁵, a plan's 1 ps bins over a 10 m deep volume).
    fn new(m: usize) -> Self {
        let mut entries: Vec<(u32, u32, f32)> = Vec::with_capacity(3 * m);
        let m64 = m as u64;
        for row in 0..m64 {
            // Fine samples x of this s-bin: row·M + 1 ..= (row + 1)·M.
            let (mut a, end) = (row * m64 + 1, (row + 1) * m64);
            while a <= end {
                // ℓ-bin ⌈√x⌉ − 1 = c holds for c² < x ≤ (c + 1)².
                let c = ceil_sqrt(a) - 1;
                let b = end.min((c + 1) * (c + 1));
                let col = c.min(m64 - 1) as u32;
                let w = (inverse_sqrt_sum(a, b) / m as f64) as f32;
                match entries.last_mut() {
                    Some((r, cc, acc)) if u64::from(*r) == row && *cc == col => *acc += w,
                    _ => entries.push((row as u32, col, w)),
                }
                a = b + 1;
            }
        }
        Self { m, entries }
    }

    fn forward(&self, l: &[f32]) -> Vec<f32> {
        let mut s = vec![0.0f32; self.m];
        for &(r, c, w) in &self.entries {
            s[r as usize] += w * l[c as usize];
        }
        s
    }

    fn inverse(&self, q: &[f32]) -> Vec<f32> {
        let mut z = vec![0.0f32; self.m];
        for &(r, c, w) in &self.entries {
            z[c as usize] += w * q[r as usize];
        }
        z
    }
}

/// The light cone, the kernel LCT deconvolves: a scatterer at lateral offset (Δx, Δy)
/// from a relay point appears `M·4(Δx² + Δy²)/ℓmax²` s-bins after its own depth.
///
/// The relay points sample a continuous hidden surface, so each cell of the padded
/// lateral grid (one pitch square around its offset) holds the cone integrated over
/// the cell's area, not the cone at the cell's centre. Far from the apex the cone is
/// steep and one cell spans several s-bins (about 10 at 0.5 m on a 1 m, 32 × 32
/// wall with 512 bins of 5 mm); a centre-sampled cone puts all of it in one bin, which
/// the Wiener filter then reads as a thinner, sparser cone than the data hold and
/// answers with a lateral blur (the reference implementation's choice; on the
/// validation capture confocal_planar it scored IoU 0.64 where the integrated cone
/// scores 0.83 at the same `snr`). The integral is taken by sub-sampling each axis of
/// the cell finely enough that neighbouring samples fall under half an s-bin apart,
/// each sample split linearly between its two nearest bins. Normalised to unit L2
/// norm, as the reference's delta cone, so `snr` keeps its scale.
struct LightCone {
    /// Per cell of the padded `[Y][X]` grid (offsets wrapped): its first s-bin and
    /// its run's range in `weights`.
    cells: Vec<(usize, std::ops::Range<usize>)>,
    /// The runs of consecutive s-bin weights, every cell's in turn.
    weights: Vec<f32>,
    /// One past the last s-bin any run reaches.
    reach: usize,
    /// The L2 norm of the cone before its normalisation: of unit mass in every cell
    /// it reaches.
    mass_norm: f64,
}

impl LightCone {
    /// Largest number of sub-samples along one axis of a cell.
    const MAX_SUBSAMPLES: usize = 1024;

    /// The cone on the `2ny × 2nx` padded grid of a scan with `spacing` (m), over
    /// `2m` s-bins of an axis to path length `lmax`.
    fn new([nx, ny]: [usize; 2], [sx, sy]: [f64; 2], m: usize, lmax: f64) -> Self {
        let bins_per_m2 = m as f64 * 4.0 / (lmax * lmax);
        let last = (2 * m - 1) as f64;
        // Per wrapped offset along one axis: the sample positions' squared distance in
        // s-bins.
        let axis = |n: usize, pitch: f64| -> Vec<Vec<f64>> {
            (0..2 * n)
                .map(|i| {
                    let d = if i < n {
                        i as f64
                    } else {
                        i as f64 - 2.0 * n as f64
                    } * pitch;
                    let (near, far) = ((d.abs() - 0.5 * pitch).max(0.0), d.abs() + 0.5 * pitch);
                    let span = bins_per_m2 * (far * far - near * near);
                    let count = ((2.0 * span).ceil() as usize + 2).min(Self::MAX_SUBSAMPLES);
                    (0..count)
                        .map(|j| {
                            let x = d + ((j as f64 + 0.5) / count as f64 - 0.5) * pitch;
                            bins_per_m2 * x * x
                        })
                        .collect()
                })
                .collect()
        };
        let (xs, ys) = (axis(nx, sx), axis(ny, sy));
        let runs: Vec<(usize, Vec<f64>)> = (0..4 * nx * ny)
            .into_par_iter()
            .map(|cell| {
                let (a, b) = (&ys[cell / (2 * nx)], &xs[cell % (2 * nx)]);
                let lo = a.iter().fold(f64::INFINITY, |m, v| m.min(*v))
                    + b.iter().fold(f64::INFINITY, |m, v| m.min(*v));
                if lo >= last {
                    return (0, Vec::new());
                }
                let first = lo.floor() as usize;
                let share = 1.0 / (a.len() * b.len()) as f64;
                let mut run: Vec<f64> = Vec::new();
                for &ka in a {
                    for &kb in b {
                        let k = ka + kb;
                        if k >= last {
                            continue;
                        }
                        let (k0, f) = (k.floor() as usize - first, k - k.floor());
                        if run.len() < k0 + 2 {
                            run.resize(k0 + 2, 0.0);
                        }
                        run[k0] += (1.0 - f) * share;
                        run[k0 + 1] += f * share;
                    }
                }
                (first, run)
            })
            .collect();
        let norm = runs
            .iter()
            .flat_map(|(_, r)| r)
            .map(|w| w * w)
            .sum::<f64>()
            .sqrt()
            .max(f64::MIN_POSITIVE);
        let mut cells = Vec::with_capacity(runs.len());
        let mut weights = Vec::new();
        for (first, run) in runs {
            let start = weights.len();
            weights.extend(run.iter().map(|w| (w / norm) as f32));
            cells.push((first, start..weights.len()));
        }
        let reach = cells.iter().map(|(first, r)| first + r.len()).max().unwrap_or(0);
        Self {
            cells,
            weights,
            reach,
            mass_norm: norm,
        }
    }

    /// The cone's spectrum along s at angular frequency `omega` (radians per bin),
    /// one value per cell, written into `out`; `phases` is scratch space.
    fn spectrum(&self, omega: f64, phases: &mut Vec<Complex32>, out: &mut [Complex32]) {
        // e^{-iωk} for every bin a run reaches, then a dot product per cell.
        phases.clear();
        phases.extend((0..self.reach).map(|k| {
            let z = Complex::from_polar(1.0, -omega * k as f64);
            Complex32::new(z.re as f32, z.im as f32)
        }));
        for (o, (first, range)) in out.iter_mut().zip(&self.cells) {
            *o = self.weights[range.clone()]
                .iter()
                .zip(&phases[*first..])
                .fold(Complex32::default(), |acc, (w, p)| acc + p * *w);
        }
    }
}

/// ⌈√x⌉ for x ≥ 1, exactly.
fn ceil_sqrt(x: u64) -> u64 {
    let mut r = (x as f64).sqrt() as u64;
    while r * r < x {
        r += 1;
    }
    while r > 0 && (r - 1) * (r - 1) >= x {
        r -= 1;
    }
    r
}

/// Σ 1/√x for x = a..=b (1 ≤ a ≤ b): exactly where the run is short or starts low,
/// else by the Euler–Maclaurin expansion of the partial sums (its next term is below
/// 10⁻¹³ of the sum from x = 64 on), each difference taken without cancellation.
fn inverse_sqrt_sum(a: u64, b: u64) -> f64 {
    const EXACT_BELOW: u64 = 64;
    if b - a < 64 {
        return (a..=b).map(|x| 1.0 / (x as f64).sqrt()).sum();
    }
    if a < EXACT_BELOW {
        return inverse_sqrt_sum(a, EXACT_BELOW - 1) + inverse_sqrt_sum(EXACT_BELOW, b);
    }
    // H(n) = ζ(½) + 2√n + 1/(2√n) − 1/(24 n^{3/2}) + 1/(384 n^{7/2}) + …; the sum is
    // H(b) − H(a − 1).
    let (hi, lo) = (b as f64, (a - 1) as f64);
    let (sh, sl) = (hi.sqrt(), lo.sqrt());
    2.0 * (hi - lo) / (sh + sl) + 0.5 * (1.0 / sh - 1.0 / sl) - (1.0 / (hi * sh) - 1.0 / (lo * sl)) / 24.0
        + (1.0 / (hi.powi(3) * sh) - 1.0 / (lo.powi(3) * sl)) / 384.0
}

#[cfg(test)]
mod tests {
    /// The table in closed form is the sum over every fine sample, to f32's precision.
    #[test]
    fn the_resampling_table_matches_the_sum_over_every_sample() {
        for m in [1usize, 2, 3, 7, 64, 65, 200, 1000] {
            let mut brute: Vec<(u32, u32, f64)> = Vec::new();
            for x in 1..=(m * m) {
                let row = ((x - 1) / m) as u32;
                let col = ((x as f64).sqrt().ceil() as usize - 1).min(m - 1) as u32;
                let w = 1.0 / ((x as f64).sqrt() * m as f64);
                match brute.last_mut() {
                    Some((r, c, acc)) if *r == row && *c == col => *acc += w,
                    _ => brute.push((row, col, w)),
                }
            }
            let table = Resampling::new(m);
            assert_eq!(table.entries.len(), brute.len(), "m = {m}");
            for (got, want) in table.entries.iter().zip(&brute) {
                assert_eq!((got.0, got.1), (want.0, want.1), "m = {m}");
                assert!(
                    (f64::from(got.2) - want.2).abs() <= 1e-6 * want.2,
                    "m = {m}: {got:?} against {want:?}"
                );
            }
        }
        for x in [1u64, 2, 4, 5, 63, 64, 65, 1 << 40, (1 << 40) + 1] {
            let r = ceil_sqrt(x);
            assert!(r * r >= x && (r - 1) * (r - 1) < x, "{x}");
        }
    }
    use super::*;

    /// A cell's weights hold the cone's density over the cell: their mean s-offset is
    /// the mean of 4(x² + y²)/ℓmax² over the cell (in bins), their span the cell's
    /// nearest and farthest corner, and every cell has the same total.
    #[test]
    fn each_cell_holds_the_cone_integrated_over_its_area() {
        let (n, pitch, m, lmax) = (16, 0.05, 256, 2.56);
        let cone = LightCone::new([n, n], [pitch, pitch], m, lmax);
        let bins_per_m2 = m as f64 * 4.0 / (lmax * lmax);
        let totals: Vec<f64> = cone
            .cells
            .iter()
            .map(|(_, r)| cone.weights[r.clone()].iter().map(|w| f64::from(*w)).sum())
            .collect();
        for (ix, iy) in [(0usize, 0usize), (3, 0), (9, 4), (2 * n - 5, 7)] {
            let (first, range) = &cone.cells[iy * 2 * n + ix];
            let run: Vec<f64> = cone.weights[range.clone()]
                .iter()
                .map(|w| f64::from(*w))
                .collect();
            let total: f64 = run.iter().sum();
            assert!(
                (total - totals[0]).abs() < 1e-5 * totals[0],
                "cell ({ix}, {iy}): total {total}"
            );
            let mean = run
                .iter()
                .enumerate()
                .map(|(j, w)| (*first + j) as f64 * w)
                .sum::<f64>()
                / total;
            let d = |i: usize| if i < n { i as f64 } else { i as f64 - 2.0 * n as f64 } * pitch;
            let (dx, dy) = (d(ix), d(iy));
            let expected = bins_per_m2 * (dx * dx + dy * dy + pitch * pitch / 6.0);
            assert!(
                (mean - expected).abs() < 0.05 + 1e-3 * expected,
                "cell ({ix}, {iy}): mean {mean}, expected {expected}"
            );
            let corner = |a: f64| (a.abs() + 0.5 * pitch).powi(2);
            let near = |a: f64| (a.abs() - 0.5 * pitch).max(0.0).powi(2);
            let lo = bins_per_m2 * (near(dx) + near(dy));
            let hi = bins_per_m2 * (corner(dx) + corner(dy));
            assert!(
                *first as f64 >= lo.floor() && ((*first + run.len()) as f64) <= hi.ceil() + 2.0,
                "cell ({ix}, {iy}): bins {first}+{}, cone {lo}..{hi}",
                run.len()
            );
        }
        let norm: f64 = cone.weights.iter().map(|w| f64::from(*w).powi(2)).sum();
        assert!((norm - 1.0).abs() < 1e-5, "unit L2 norm: {norm}");
    }

    /// The spectrum is the DFT of each cell's run.
    #[test]
    fn the_cone_spectrum_is_the_transform_of_its_runs() {
        let cone = LightCone::new([4, 4], [0.1, 0.1], 64, 1.28);
        let omega = 2.0 * PI * 5.0 / 128.0;
        let mut out = vec![Complex32::default(); 64];
        cone.spectrum(omega, &mut Vec::new(), &mut out);
        for (o, (first, range)) in out.iter().zip(&cone.cells) {
            let direct: Complex<f64> = cone.weights[range.clone()]
                .iter()
                .enumerate()
                .map(|(j, w)| Complex::from_polar(f64::from(*w), -omega * (first + j) as f64))
                .sum();
            assert!((o.re as f64 - direct.re).abs() < 1e-6 && (o.im as f64 - direct.im).abs() < 1e-6);
        }
    }

    /// Without the photon-count mark the filter trusts the model; with it, the snr
    /// follows the counts.
    #[test]
    fn the_default_snr_follows_the_photon_counts() {
        let axis = crate::transient::TimeAxis {
            start: 0.0,
            width: 0.01,
            bins: 4,
        };
        let pair = crate::transient::Pair::confocal(glam::DVec3::ZERO, glam::DVec3::Z);
        let mut set = TransientSet::new(axis).unwrap();
        set.push(pair, &[0.0, 3.0, 1.0, 0.0]).unwrap();
        assert_eq!(default_snr(&set), 100.0);
        set.mark_photon_counts();
        // R = (9 + 1)/4 − 1 = 1.5 (less a little: the background is read as at least
        // 1e-3 of the peak).
        assert!((default_snr(&set) - 15.0).abs() < 0.1, "{}", default_snr(&set));
        // Ambient alone, 20 counts a bin over many pairs: no signal, the filter's
        // lowest snr (it was the cap, 100, and the more ambient the higher).
        let mut ambient = TransientSet::new(axis).unwrap();
        ambient.mark_photon_counts();
        for _ in 0..600 {
            ambient.push(pair, &[20.0; 4]).unwrap();
        }
        assert_eq!(default_snr(&ambient), 0.8);
        // The same signal with ambient under it is trusted less, not more.
        let with_ambient = |b: f32| {
            let mut s = TransientSet::new(axis).unwrap();
            s.mark_photon_counts();
            for k in 0..600 {
                let signal = if k % 2 == 0 { 4.0 } else { 3.0 };
                s.push(pair, &[b, signal + b, b, b]).unwrap();
            }
            default_snr(&s)
        };
        let (clean, lit) = (with_ambient(0.0), with_ambient(2.0));
        assert!(lit < clean, "{lit} against {clean}");
        let mut bright = TransientSet::new(axis).unwrap();
        bright.mark_photon_counts();
        bright.push(pair, &[0.0, 3000.0, 10.0, 0.0]).unwrap();
        assert_eq!(default_snr(&bright), 100.0);
        let mut dim = TransientSet::new(axis).unwrap();
        dim.mark_photon_counts();
        dim.push(pair, &[1.0, 0.0, 1.0, 1.0]).unwrap();
        assert_eq!(default_snr(&dim), 0.8);
    }
}

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
use crate::transient::TransientSet;
use crate::volume::{Volume, VolumeGrid};

/// LCT settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct LctSettings {
    /// Signal-to-noise ratio of the Wiener filter (the reference code's 0.8); larger is
    /// sharper and noisier.
    pub snr: f64,
    /// Exponent of the radiometric weight ℓ^n: 4 for diffuse surfaces, 2 for
    /// retroreflective ones.
    pub falloff: f64,
    /// Distance within which points count as the same grid line, and largest rms
    /// distance from the fitted plane, metres.
    pub grid_tolerance: f64,
}

impl Default for LctSettings {
    fn default() -> Self {
        Self {
            snr: 0.8,
            falloff: 4.0,
            grid_tolerance: 2e-3,
        }
    }
}

impl LctSettings {
    /// Checks every setting is in range.
    pub fn validate(&self) -> Result<(), SolverError> {
        if !(self.snr.is_finite() && self.snr > 0.0) {
            return Err(SolverError::Setting {
                name: "snr",
                value: self.snr.to_string(),
                expected: "a positive number",
            });
        }
        confocal::check_settings(self.falloff, self.grid_tolerance)
    }
}

/// LCT of a confocal capture on a planar grid, resampled onto `grid`.
pub fn lct(set: &TransientSet, grid: &VolumeGrid, settings: &LctSettings) -> Result<Volume, SolverError> {
    settings.validate()?;
    let scan = confocal_scan(set, settings.grid_tolerance)?;
    Ok(lct_frame(set, &scan, settings)?.to_world(grid))
}

/// Checks every pair is confocal and finds the grid (LCT and f-k migration).
pub(super) fn confocal_scan(set: &TransientSet, tolerance: f64) -> Result<PlanarScan, SolverError> {
    if set.is_empty() {
        return Err(SolverError::Empty);
    }
    for (i, p) in set.pairs().iter().enumerate() {
        let d = p.xi.distance(p.xd);
        if d > tolerance {
            return Err(SolverError::NotConfocal {
                pair: i,
                distance_mm: d * 1e3,
            });
        }
    }
    let points: Vec<_> = set.pairs().iter().map(|p| p.xd).collect();
    let hint = set.pairs().iter().map(|p| p.nd).sum();
    PlanarScan::detect("confocal scan", &points, hint, tolerance)
}

/// LCT on the scan's own grid: a volume with one slice per bin, depth `(t + ½)·w/2`.
pub fn lct_frame(
    set: &TransientSet,
    scan: &PlanarScan,
    settings: &LctSettings,
) -> Result<FrameVolume, SolverError> {
    settings.validate()?;
    let [nx, ny] = scan.relay.resolution;
    let w = set.axis().width;
    let m = confocal::bins_from_zero(set, "LCT")?;
    check_memory("LCT", (m + 1) * 4 * nx * ny * 8 + 2 * nx * ny * m * 4)?;
    let mut cube = confocal::cube(set, scan, m);

    // Radiometric weight and ℓ → s resampling.
    let resample = Resampling::new(m);
    cube.par_chunks_mut(m).for_each(|line| {
        for (t, v) in line.iter_mut().enumerate() {
            *v *= ((t as f64 + 0.5) / m as f64).powf(settings.falloff) as f32;
        }
        let s = resample.forward(line);
        line.copy_from_slice(&s);
    });

    // Real FFT along s (padded to 2M), scattered into slices [t'][Y][X] of 2ny × 2nx.
    let (px, py, pt) = (2 * nx, 2 * ny, 2 * m);
    let slice_len = px * py;
    let mut slices = confocal::padded_spectra(&cube, m, [nx, ny]);
    drop(cube);
    let c2r = RealFftPlanner::<f32>::new().plan_fft_inverse(pt);

    // The light cone: for each lateral offset, a (linearly split) delta at s-index k*.
    let lmax = m as f64 * w;
    let [sx, sy] = scan.relay.spacing();
    let mut cone = Vec::with_capacity(slice_len);
    for iy in 0..py {
        let dy = if iy < ny { iy as f64 } else { iy as f64 - py as f64 } * sy;
        for ix in 0..px {
            let dx = if ix < nx { ix as f64 } else { ix as f64 - px as f64 } * sx;
            let k = m as f64 * 4.0 * (dx * dx + dy * dy) / (lmax * lmax);
            cone.push((k < (pt - 1) as f64).then(|| (k.floor() as usize, k - k.floor())));
        }
    }
    let norm = 1.0 / (cone.iter().flatten().count().max(1) as f64).sqrt();
    let inv_snr = 1.0 / settings.snr as f32;

    let fft = Fft2::new(py, px);
    const SLICES_PER_TASK: usize = 8;
    slices
        .par_chunks_mut(slice_len * SLICES_PER_TASK)
        .enumerate()
        .for_each(|(task, chunk)| {
            let mut scratch = vec![Complex32::default(); fft.scratch_len()];
            let mut psf = vec![Complex32::default(); slice_len];
            for (j, slice) in chunk.chunks_mut(slice_len).enumerate() {
                let kt = task * SLICES_PER_TASK + j;
                let omega = 2.0 * PI * kt as f64 / pt as f64;
                for (out, c) in psf.iter_mut().zip(&cone) {
                    *out = match c {
                        Some((k0, f)) => {
                            let z = Complex::from_polar(norm, -omega * *k0 as f64);
                            let z = z * ((1.0 - f) + f * Complex::from_polar(1.0, -omega));
                            Complex32::new(z.re as f32, z.im as f32)
                        }
                        None => Complex32::default(),
                    };
                }
                fft.forward_transposed(&mut psf, &mut scratch);
                fft.forward_transposed(slice, &mut scratch);
                for (d, h) in slice.iter_mut().zip(&psf) {
                    *d = *d * h.conj() / (h.norm_sqr() + inv_snr);
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
            resample.inverse(&q).into_iter().map(|v| v.max(0.0)).collect()
        })
        .collect();
    drop(slices);
    Ok(confocal::frame_from_lines(scan, w, m, &lines))
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
    fn new(m: usize) -> Self {
        let mut entries: Vec<(u32, u32, f32)> = Vec::with_capacity(3 * m);
        for x in 1..=(m * m) {
            let row = ((x - 1) / m) as u32;
            let col = ((x as f64).sqrt().ceil() as usize - 1).min(m - 1) as u32;
            let w = (1.0 / ((x as f64).sqrt() * m as f64)) as f32;
            match entries.last_mut() {
                Some((r, c, acc)) if *r == row && *c == col => *acc += w,
                _ => entries.push((row, col, w)),
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

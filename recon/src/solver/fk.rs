//! f-k migration (Lindell, Wetzstein and O'Toole 2019) for confocal scans on a planar
//! grid: the transients are treated as a wave field recorded on the relay plane, and
//! Stolt's change of variables in the Fourier domain migrates it back to the scene.
//!
//! With the field τ(x, y, t) weighted by the path length (the radiometric
//! correction of the reference implementations), zero-padded to twice its size in
//! every dimension and Fourier transformed, the migrated spectrum at (kx, ky, kz > 0)
//! is the data's at (kx, ky, √(kx² + ky² + kz²)) times kz / √(kx² + ky² + kz²), with kz
//! the spatial frequency along depth z = ℓ/2. The inverse transform's squared
//! magnitude is the volume, one slice per bin at depth `(t + ½)·w/2`, as for LCT.
//!
//! The interpolation along kz is linear, as in the reference code. Memory: two padded
//! spectra of (M + 1)·(2nx)·(2ny) complex f32 values (M bins), 540 MiB for a
//! 128 × 128 × 512 scan.
use rayon::prelude::*;
use rustfft::FftPlanner;
use rustfft::num_complex::Complex32;

use super::fft::Fft2;
use super::{FrameVolume, PlanarScan, SolverError, check_memory, confocal};
use crate::transient::{TimeAxis, TransientSet};
use crate::volume::{Volume, VolumeGrid};

/// f-k migration settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct FkSettings {
    /// Exponent of the radiometric weight ℓ^n applied before migration: 1 in the
    /// reference implementations (the field's amplitude falls as 1/ℓ once the
    /// intensity's 1/ℓ² is taken as an amplitude's square).
    pub falloff: f64,
    /// Distance within which points count as the same grid line, and largest rms
    /// distance from the fitted plane, metres.
    pub grid_tolerance: f64,
    /// Weigh each measured cell by its share of the grid (its Voronoi cell) when some
    /// cells are missing, so the sums over cells stay quadratures of the whole
    /// aperture; `false`: missing cells are zeros and nothing else changes.
    pub relay_weights: bool,
}

impl Default for FkSettings {
    fn default() -> Self {
        Self {
            falloff: 1.0,
            grid_tolerance: 2e-3,
            relay_weights: true,
        }
    }
}

impl FkSettings {
    /// Checks every setting is in range.
    pub fn validate(&self) -> Result<(), SolverError> {
        confocal::check_settings(self.falloff, self.grid_tolerance)
    }
}

/// f-k migration of a confocal capture on a planar grid, resampled onto `grid`.
pub fn fk(set: &TransientSet, grid: &VolumeGrid, settings: &FkSettings) -> Result<Volume, SolverError> {
    settings.validate()?;
    // As FBP, RSD and 3D-GTR refuse it (an all-zero volume until 2026-12-06).
    super::refuse_a_volume_behind(set.pairs(), grid)?;
    let scan = super::lct::confocal_scan(set, settings.grid_tolerance)?.reaching(grid);
    Ok(fk_frame(set, &scan, settings)?.to_world(grid))
}

/// The memory f-k migration allocates for a scan of `cells` grid cells and `m` bins
/// from path length zero: two sets of `m + 1` complex slices of the grid padded to
/// `2ny × 2nx`, and the cube in `f32`. Saturating, so a hostile size is never small.
/// `periscope check` and the solver's own cap read the same figure.
pub fn fk_work_bytes(cells: usize, m: usize) -> usize {
    let spectra = (m.saturating_add(1))
        .saturating_mul(8)
        .saturating_mul(cells)
        .saturating_mul(8);
    spectra.saturating_add(cells.saturating_mul(m).saturating_mul(4))
}

/// f-k migration's bins from path length 0 over `axis` on `scan`'s grid, once its
/// memory is known to fit.
pub(super) fn fk_bins(scan: &PlanarScan, axis: &TimeAxis) -> Result<usize, SolverError> {
    let [nx, ny] = scan.relay.resolution;
    let m = confocal::bins_from_zero(axis, "f-k migration")?;
    check_memory("f-k migration", fk_work_bytes(nx * ny, m))?;
    Ok(m)
}

/// f-k migration on the scan's own grid: a volume with one slice per bin, depth
/// `(t + ½)·w/2`.
pub fn fk_frame(
    set: &TransientSet,
    scan: &PlanarScan,
    settings: &FkSettings,
) -> Result<FrameVolume, SolverError> {
    settings.validate()?;
    let [nx, ny] = scan.relay.resolution;
    let w = set.axis().width;
    let m = fk_bins(scan, set.axis())?;
    let (px, py, pt) = (2 * nx, 2 * ny, 2 * m);
    let slice_len = px * py;

    // Weight by path length, then the real FFT along t (padded to 2M), scattered into
    // slices [kt][Y][X] of the laterally padded grid.
    let mut cube = confocal::cube(set, scan, m, settings.relay_weights);
    let weights: Vec<f32> = (0..m)
        .map(|t| ((t as f64 + 0.5) / m as f64).powf(settings.falloff) as f32)
        .collect();
    cube.par_chunks_mut(m).for_each(|line| {
        for (v, wt) in line.iter_mut().zip(&weights) {
            *v *= wt;
        }
    });
    let mut slices = confocal::padded_spectra(&cube, m, [nx, ny]);
    drop(cube);

    // Lateral FFTs: each slice becomes its spectrum, transposed ([kx][ky]).
    let fft = Fft2::new(py, px);
    slices.par_chunks_mut(slice_len).for_each(|slice| {
        let mut scratch = vec![Complex32::default(); fft.scratch_len()];
        fft.forward_transposed(slice, &mut scratch);
    });

    // Stolt: output kz-slice k reads the input along kz at √(k² + (a·kx)² + (b·ky)²)
    // in bin units, a = 2M·Δz / (2nx·sx) with Δz = w/2, and likewise b.
    let [sx, sy] = scan.relay.spacing();
    let dz = 0.5 * w;
    let (a, b) = (
        pt as f64 * dz / (px as f64 * sx),
        pt as f64 * dz / (py as f64 * sy),
    );
    let freq = |i: usize, n: usize| if i < n / 2 { i as f64 } else { i as f64 - n as f64 };
    // The transposed layout: index kx·py + ky.
    let lateral: Vec<f64> = (0..px)
        .flat_map(|ix| {
            let fx = a * freq(ix, px);
            (0..py).map(move |iy| {
                let fy = b * freq(iy, py);
                fx * fx + fy * fy
            })
        })
        .collect();
    let mut migrated = vec![Complex32::default(); (m + 1) * slice_len];
    migrated
        .par_chunks_mut(slice_len)
        .enumerate()
        .for_each(|(k, out)| {
            if k == 0 || k >= m {
                return;
            }
            let kz = k as f64;
            for (c, (o, &l2)) in out.iter_mut().zip(&lateral).enumerate() {
                let src = (kz * kz + l2).sqrt();
                let lo = src.floor() as usize;
                if lo + 1 >= m {
                    continue;
                }
                let f = (src - lo as f64) as f32;
                let v = slices[lo * slice_len + c] * (1.0 - f) + slices[(lo + 1) * slice_len + c] * f;
                *o = v * (kz / src) as f32;
            }
        });
    drop(slices);

    // Inverse lateral FFTs, then the inverse along kz for each cell of the unpadded
    // quadrant: a full complex transform (the migrated spectrum has only kz > 0).
    migrated.par_chunks_mut(slice_len).for_each(|slice| {
        let mut scratch = vec![Complex32::default(); fft.scratch_len()];
        fft.inverse_from_transposed(slice, &mut scratch);
    });
    let inverse = FftPlanner::<f32>::new().plan_fft_inverse(pt);
    let scale = 1.0 / (pt * slice_len) as f32;
    let lines: Vec<Vec<f32>> = (0..nx * ny)
        .into_par_iter()
        .map(|cell| {
            let (y, x) = (cell / nx, cell % nx);
            let mut line = vec![Complex32::default(); pt];
            for (k, v) in line.iter_mut().enumerate().take(m) {
                *v = migrated[k * slice_len + y * px + x] * scale;
            }
            inverse.process(&mut line);
            line[..m].iter().map(|v| v.norm_sqr()).collect()
        })
        .collect();
    drop(migrated);
    Ok(confocal::frame_from_lines(scan, w, m, &lines))
}

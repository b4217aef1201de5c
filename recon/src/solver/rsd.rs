//! Rayleigh–Sommerfeld diffraction of phasor fields (Liu et al. 2019, 2020).
//!
//! The transients are filtered by a virtual wave (a Gaussian-windowed carrier of
//! wavelength λ): in the Fourier domain that is a weight W(k) on the spectral lines
//! k near 2π/λ. For each line the detection side is propagated to every depth slice by
//! a 2-D convolution with the RSD kernel e^{ikr}/r (an FFT convolution on the padded
//! detection grid), the illumination side by the phase e^{ik|x − x_i|} of each
//! illumination point, and the complex fields are summed over lines and illumination
//! points before taking the magnitude. Confocal data use ℓ = 2r: the kernel e^{2ikr}
//! and no illumination term. Each leg's amplitude is r^`falloff` (as FBP's weight
//! (d_i·d_d)^`falloff`): 1 by default, which undoes the 1/r amplitude of the two
//! spherical waves; −1 is the RSD integral as written (y-tal's `pf`), 0 the phase alone.
//! For confocal data the two legs' weight r^(2·falloff) is put on each bin of the
//! transients, at r = ℓ/2, before the wave filter: on the kernel it multiplied each
//! depth slice by z^(2·falloff) after the filter, which moves the peak of a wide
//! envelope deeper (a 12.5 cm pitch: 40 mm of depth error on bars at 0.5 m, 14 mm
//! now). Non-confocal data keep the weight in the kernel and the illumination phase.
//!
//! Detection points must lie on a planar grid; illumination points may be anywhere,
//! and any number (each distinct one costs one more set of propagations). A scan whose
//! laser and SPAD spots are at most [`RSD_CONFOCAL_OFFSET`] apart (an offset confocal scan,
//! against pile-up) is confocal at the spots' midpoints.
use std::f64::consts::PI;

use glam::DVec3;
use rayon::prelude::*;
use realfft::RealFftPlanner;
use rustfft::num_complex::{Complex, Complex32};

use super::fft::{Fft2, raised_cosine};
use super::scan::gather_cube;
use super::{FrameVolume, PlanarScan, SolverError, check_memory};
use crate::transient::{Pair, TimeAxis, TransientSet};
use crate::volume::{Volume, VolumeGrid};

/// RSD settings.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields, rename_all = "kebab-case")]
pub struct RsdSettings {
    /// Virtual wavelength in path length, metres; `None`: [`super::PHASOR_PITCHES`]
    /// (2.5) × the coarser grid spacing, confocal or not (y-tal's published
    /// settings), at least 4 bins.
    pub wavelength: Option<f64>,
    /// Cycles of the virtual wave within its Gaussian window (the envelope's standard
    /// deviation is cycles·λ/6).
    pub cycles: f64,
    /// Spectral lines whose weight is below this fraction of the peak are skipped.
    pub spectral_cutoff: f64,
    /// Grid/plane tolerance and illumination grouping distance, metres.
    pub grid_tolerance: f64,
    /// Each leg's amplitude is r^falloff, r its length (for confocal data the kernel's
    /// amplitude is r^(2·falloff)): 1 undoes the 1/r amplitude of the two spherical
    /// waves, as FBP's default; −1 is the RSD integral as written (y-tal's `pf`, on
    /// confocal data); 0 the phase alone (y-tal's `pf_dev` on non-confocal data).
    pub falloff: f64,
    /// Replaced by `falloff` (`spherical-amplitude = true` was `falloff = -1` on the
    /// detection side only); kept so a RECON.toml that sets it gets a message saying
    /// so rather than an unknown key.
    #[serde(skip_serializing)]
    #[doc(hidden)]
    pub spherical_amplitude: Option<bool>,
    /// Weigh each measured cell by its share of the grid (its Voronoi cell) when some
    /// cells are missing, so the sums over cells stay quadratures of the whole
    /// aperture; `false`: missing cells are zeros and nothing else changes.
    pub relay_weights: bool,
}

impl Default for RsdSettings {
    fn default() -> Self {
        Self {
            wavelength: None,
            cycles: 4.0,
            spectral_cutoff: 1e-3,
            grid_tolerance: 2e-3,
            falloff: 1.0,
            spherical_amplitude: None,
            relay_weights: true,
        }
    }
}

impl RsdSettings {
    /// Checks every setting is in range.
    pub fn validate(&self) -> Result<(), SolverError> {
        let bad = |name, value: f64, expected| SolverError::Setting {
            name,
            value: value.to_string(),
            expected,
        };
        if let Some(l) = self.wavelength
            && !(l.is_finite() && l > 0.0)
        {
            return Err(bad("wavelength", l, "a positive length in metres"));
        }
        if let Some(v) = self.spherical_amplitude {
            return Err(SolverError::Setting {
                name: "spherical-amplitude",
                value: v.to_string(),
                expected: "a setting that was removed; use `falloff` instead (-1 weighs each leg by \
                           1/r, the RSD integral as written; 0 is the phase alone; the default, 1, \
                           undoes the 1/r)",
            });
        }
        if !(self.falloff.is_finite() && (-2.0..=4.0).contains(&self.falloff)) {
            return Err(bad("falloff", self.falloff, "a number from -2 to 4"));
        }
        if !(self.cycles.is_finite() && self.cycles >= 1.0) {
            return Err(bad("cycles", self.cycles, "at least 1"));
        }
        if !(self.spectral_cutoff > 0.0 && self.spectral_cutoff < 1.0) {
            return Err(bad(
                "spectral-cutoff",
                self.spectral_cutoff,
                "between 0 and 1, exclusive",
            ));
        }
        if !(self.grid_tolerance.is_finite() && self.grid_tolerance > 0.0) {
            return Err(bad(
                "grid-tolerance",
                self.grid_tolerance,
                "a positive length in metres",
            ));
        }
        Ok(())
    }
}

/// Laser and SPAD spots at most this far apart, metres, make a confocal pair at their
/// midpoint `m`. For a scatterer `r` from `m` the two legs differ from `2|x − m|` by
/// at most `δ²/(4r)` (δ the spots' distance): 0.02 mm at 5 mm apart and 0.3 m, a
/// four-thousandth of the default wave on a 33 mm grid. Taken as non-confocal instead,
/// every pair of such a scan was its own illumination group: one set of propagations
/// per pair (576 for the demo's grid), each cube holding one occupied cell, which the
/// cell weights then counted 4 to 9 times over.
pub const RSD_CONFOCAL_OFFSET: f64 = 0.01;

/// Whether `pairs` are a confocal scan for RSD: every pair's spots within
/// [`RSD_CONFOCAL_OFFSET`] (or `tolerance`, if larger) of each other.
fn confocal_scan(pairs: &[Pair], tolerance: f64) -> bool {
    let within = tolerance.max(RSD_CONFOCAL_OFFSET);
    pairs.iter().all(|p| p.xi.distance(p.xd) <= within)
}

/// RSD reconstruction resampled onto `grid` (depth slices spaced by the grid's
/// smallest voxel edge, covering the grid's extent along the relay normal).
pub fn rsd(set: &TransientSet, grid: &VolumeGrid, settings: &RsdSettings) -> Result<Volume, SolverError> {
    let (scan, start, step, depths) = rsd_depths(set.pairs(), grid, settings)?;
    Ok(rsd_frame(set, &scan, start, step, depths, settings)?.to_world(grid))
}

/// [`rsd`]'s grid and depths for `pairs` and `grid`: the scan, the first depth, the
/// step and the count.
pub(super) fn rsd_depths(
    pairs: &[Pair],
    grid: &VolumeGrid,
    settings: &RsdSettings,
) -> Result<(PlanarScan, f64, f64, usize), SolverError> {
    settings.validate()?;
    if pairs.is_empty() {
        return Err(SolverError::Empty);
    }
    // A confocal scan's grid is its spots' midpoints; any other's, its detection points.
    let confocal = confocal_scan(pairs, settings.grid_tolerance);
    let points: Vec<DVec3> = pairs
        .iter()
        .map(|p| if confocal { 0.5 * (p.xi + p.xd) } else { p.xd })
        .collect();
    let hint = pairs.iter().map(|p| p.nd).sum();
    let scan = PlanarScan::detect("detection", &points, hint, settings.grid_tolerance)?.reaching(grid);
    let (mut lo, mut hi) = (f64::INFINITY, f64::NEG_INFINITY);
    for corner in 0..8 {
        let c = DVec3::new(
            grid.x[corner & 1],
            grid.y[(corner >> 1) & 1],
            grid.z[(corner >> 2) & 1],
        );
        let d = (c - scan.relay.centre).dot(scan.relay.normal);
        lo = lo.min(d);
        hi = hi.max(d);
    }
    let step = grid.voxel().min_element();
    if hi <= 0.0 {
        return Err(SolverError::Axis(
            "the volume lies behind the relay plane (against its normal); move it in front".into(),
        ));
    }
    let start = lo.max(0.5 * step);
    // Counted in f64 first: a volume axis far thinner than the others (1e-300 m) gave
    // a count past usize, which wrapped to 0 (or overflowed in a debug build).
    let count = ((hi - start) / step).ceil() + 1.0;
    if !(count.is_finite() && count <= MAX_DEPTHS as f64) {
        return Err(SolverError::Axis(format!(
            "the volume's depth along the relay's normal ({:.3} m) over its finest voxel ({step:.3e} m) gives {count:.3e} depth planes, more than {MAX_DEPTHS}: widen the volume's thinnest axis or give it fewer voxels",
            hi - start
        )));
    }
    Ok((scan, start, step, count as usize))
}

/// [`rsd`]'s checks of `pairs`, `axis` and `grid` before it reads a count
/// ([`super::SolverKind::check_layout`]).
pub(super) fn rsd_layout(
    pairs: &[Pair],
    axis: &TimeAxis,
    grid: &VolumeGrid,
    settings: &RsdSettings,
) -> Result<(), SolverError> {
    let (scan, _, _, depths) = rsd_depths(pairs, grid, settings)?;
    spectral(pairs, axis, &scan, depths, settings).map(|_| ())
}

/// Most depth planes RSD counts before its memory check judges them (any count past
/// this is a volume axis far thinner than the others).
const MAX_DEPTHS: usize = 1 << 32;

/// RSD on the scan's grid at depths `start + k·step`, `k < depths`. The scan of a set
/// whose spots lie within [`RSD_CONFOCAL_OFFSET`] of each other is the grid of their
/// midpoints, as [`rsd`] detects it.
pub fn rsd_frame(
    set: &TransientSet,
    scan: &PlanarScan,
    start: f64,
    step: f64,
    depths: usize,
    settings: &RsdSettings,
) -> Result<FrameVolume, SolverError> {
    settings.validate()?;
    if set.is_empty() {
        return Err(SolverError::Empty);
    }
    if !(start > 0.0 && step > 0.0 && depths > 0 && start.is_finite() && step.is_finite()) {
        return Err(SolverError::Setting {
            name: "depths",
            value: format!("start {start}, step {step}, count {depths}"),
            expected: "positive start and step, at least one slice",
        });
    }
    let axis = *set.axis();
    let relay = scan.relay;
    let [nx, ny] = relay.resolution;
    let [sx, sy] = relay.spacing();
    let Spectral {
        confocal,
        pad,
        join,
        padded_bins,
        lines,
        groups,
    } = spectral(set.pairs(), &axis, scan, depths, settings)?;
    let bins = axis.bins;
    let (px, py) = (2 * nx, 2 * ny);
    let plane = px * py;
    let fft = Fft2::new(py, px);
    let mut planner = RealFftPlanner::<f64>::new();
    let r2c = planner.plan_fft_forward(padded_bins);
    // Phase of padded bin centres: ℓ_i = start + (i − pad + ½)·w.
    let centre0 = axis.start + (0.5 - pad as f64) * axis.width;
    let wave_factor = if confocal { 2.0 } else { 1.0 };
    let mut field = vec![Complex::<f64>::default(); depths * nx * ny];

    for (xi, members) in &groups {
        let cube = gather_cube(set, members, scan, axis.start, bins, settings.relay_weights);
        // Spectra of every cell's transient at the selected lines, as padded planes.
        let per_cell: Vec<Vec<Complex<f64>>> = cube
            .par_chunks(bins)
            .map(|h| {
                // Confocal: each leg's r^falloff weighs the data by its path length
                // (ℓ/2 = r for the voxel a return comes from) before the wave filter,
                // not the kernel after it: a weight on the kernel multiplies each depth
                // slice by z^(2·falloff), which moves the peak of a wide envelope
                // deeper (by about 2·falloff·σ²/z: 4 cm at a 12.5 cm pitch).
                let weighted: Vec<f64> = h
                    .iter()
                    .enumerate()
                    .map(|(t, &v)| {
                        let l = axis.start + (t as f64 + 0.5) * axis.width;
                        if confocal {
                            v as f64 * leg_gain((0.5 * l).max(0.5 * axis.width), 2.0 * settings.falloff)
                        } else {
                            v as f64
                        }
                    })
                    .collect();
                let (first, last) = (weighted[0], weighted[bins - 1]);
                let back = (0..join).map(|i| raised_cosine(last, first, i, join));
                let mut input: Vec<f64> = std::iter::repeat_n(first, pad)
                    .chain(weighted.iter().copied())
                    .chain(std::iter::repeat_n(last, pad))
                    .chain(back)
                    .collect();
                let mut out = r2c.make_output_vec();
                r2c.process(&mut input, &mut out)
                    .expect("buffer lengths match the plan");
                lines
                    .iter()
                    .map(|&(j, k, _)| out[j] * Complex::from_polar(1.0, -k * centre0))
                    .collect()
            })
            .collect();
        let spectra: Vec<Vec<Complex32>> = (0..lines.len())
            .into_par_iter()
            .map(|l| {
                let mut buf = vec![Complex32::default(); plane];
                for cell in 0..nx * ny {
                    let v = per_cell[cell][l];
                    buf[(cell / nx) * px + cell % nx] = Complex32::new(v.re as f32, v.im as f32);
                }
                let mut scratch = vec![Complex32::default(); fft.scratch_len()];
                fft.forward_transposed(&mut buf, &mut scratch);
                buf
            })
            .collect();
        drop(per_cell);

        field.par_chunks_mut(nx * ny).enumerate().for_each(|(iz, slice)| {
            let z = start + iz as f64 * step;
            // The kernel's radii and amplitudes, and the illumination leg's length and
            // amplitude at each voxel, are the same for every spectral line.
            // Confocal data carry their legs' weight already (above).
            let leg_power = if confocal { 0.0 } else { settings.falloff };
            let radii: Vec<(f64, f64)> = (0..plane)
                .map(|i| {
                    let (iy, ix) = (i / px, i % px);
                    let dy = if iy < ny { iy as f64 } else { iy as f64 - py as f64 } * sy;
                    let dx = if ix < nx { ix as f64 } else { ix as f64 - px as f64 } * sx;
                    let r = (dx * dx + dy * dy + z * z).sqrt();
                    (r, leg_gain(r, leg_power))
                })
                .collect();
            let lit: Vec<(f64, f64)> = if confocal {
                Vec::new()
            } else {
                (0..nx * ny)
                    .map(|i| {
                        let (u, w) = relay.coords(i % nx, i / nx);
                        let x = relay.centre + relay.u * u + relay.v * w + relay.normal * z;
                        let d = x.distance(*xi);
                        (d, leg_gain(d, settings.falloff))
                    })
                    .collect()
            };
            let mut kernel = vec![Complex32::default(); plane];
            let mut scratch = vec![Complex32::default(); fft.scratch_len()];
            let norm = 1.0 / plane as f64;
            for (l, &(_, k, weight)) in lines.iter().enumerate() {
                let kk = wave_factor * k;
                for (g, &(r, amp)) in kernel.iter_mut().zip(&radii) {
                    let (s, c) = (kk * r).sin_cos();
                    *g = Complex32::new((amp * c) as f32, (amp * s) as f32);
                }
                fft.forward_transposed(&mut kernel, &mut scratch);
                for (g, h) in kernel.iter_mut().zip(&spectra[l]) {
                    *g *= *h;
                }
                fft.inverse_from_transposed(&mut kernel, &mut scratch);
                for iy in 0..ny {
                    for ix in 0..nx {
                        let v = kernel[iy * px + ix];
                        let mut v = Complex::new(v.re as f64, v.im as f64) * (weight * norm);
                        if !confocal {
                            let (d, amp) = lit[iy * nx + ix];
                            v *= Complex::from_polar(amp, k * d);
                        }
                        slice[iy * nx + ix] += v;
                    }
                }
            }
        });
    }
    Ok(FrameVolume {
        relay,
        depth_start: start,
        depth_step: step,
        depths,
        data: field.iter().map(|v| v.norm() as f32).collect(),
    })
}

/// What [`rsd_frame`] works with before it reads a count: whether the scan is
/// confocal, the padding, the spectral lines and the illumination groups.
struct Spectral {
    confocal: bool,
    /// Bins repeated at either end of a transient.
    pad: usize,
    /// Bins over which the padding's end returns to its start.
    join: usize,
    padded_bins: usize,
    /// Each line's FFT index, wavenumber and weight.
    lines: Vec<(usize, f64, f64)>,
    /// Each illumination spot (zero for a confocal scan) and its pairs.
    groups: Vec<(DVec3, Vec<usize>)>,
}

/// [`rsd_frame`]'s spectral plan for `pairs` on `axis` and `scan`, once its memory is
/// known to fit.
fn spectral(
    pairs: &[Pair],
    axis: &TimeAxis,
    scan: &PlanarScan,
    depths: usize,
    settings: &RsdSettings,
) -> Result<Spectral, SolverError> {
    let relay = scan.relay;
    let [nx, ny] = relay.resolution;
    let [sx, sy] = relay.spacing();
    let confocal = confocal_scan(pairs, settings.grid_tolerance);
    // λ is a wavelength in path length for confocal data too, whose kernel's phase is
    // 2kr: its wave across the relay is λ/2, 1.25 pitches, which aliases beyond about
    // 40° off the normal. Twice the wavelength (no aliasing up to grazing angles) was
    // the default until measured: on the validation confocal grid it scored IoU 0.70
    // against 0.87 at 2.5 pitches, y-tal `pf`'s setting and figure (docs/recon.md).
    let lambda = settings
        .wavelength
        .unwrap_or((super::PHASOR_PITCHES * sx.max(sy)).max(4.0 * axis.width));

    // Spectral lines of the virtual wave, over the transients padded with three
    // envelope widths each side (repeating their end values) so the wave does not
    // wrap around the time axis, and twice that after them over which a raised cosine
    // takes the last value back to the first: the FFT is circular, and without it the
    // two ends met in a step whose wave the depths outside the window read (FBP's
    // phasor filter joins its padding the same way).
    let bins = axis.bins;
    let sigma = settings.cycles * lambda / 6.0;
    // The envelope (cycles wavelengths, 6σ) pads the transients by half its length
    // each side: one many times longer than the time axis filters nothing the axis
    // holds, and its padding (10⁹ cycles asked for 64 GB) would not fit in memory.
    let span = axis.bins as f64 * axis.width;
    if !(6.0 * sigma <= super::MAX_ENVELOPE_SPANS * span) {
        return Err(SolverError::Setting {
            name: "cycles",
            value: format!(
                "{} (with a wavelength of {lambda} m, an envelope of {} m against a time axis of {span} m)",
                settings.cycles,
                6.0 * sigma
            ),
            expected: "an envelope (cycles × wavelength) at most 8 times the time axis's length: fewer [rsd] cycles or a shorter [rsd] wavelength (recon.rsd.* in a plan); a run's capture is kept, and `periscope recon RUN_DIR --config RECON.toml` reconstructs it again",
        });
    }
    let pad = (3.0 * sigma / axis.width).ceil() as usize + 1;
    let join = 2 * pad;
    let padded_bins = bins + 2 * pad + join;
    let kc = 2.0 * PI / lambda;
    let lines: Vec<(usize, f64, f64)> = (0..=padded_bins / 2)
        .map(|j| (j, 2.0 * PI * j as f64 / (padded_bins as f64 * axis.width)))
        .map(|(j, k)| (j, k, (-(k - kc).powi(2) * sigma * sigma / 2.0).exp()))
        .filter(|(_, _, w)| *w >= settings.spectral_cutoff)
        .collect();
    if lines.is_empty() {
        return Err(SolverError::Setting {
            name: "wavelength",
            value: lambda.to_string(),
            expected: "a wavelength the time axis resolves (longer than two bins, shorter than the axis)",
        });
    }

    // Illumination groups (one for confocal data: its phase lives in the kernel).
    let mut groups: Vec<(DVec3, Vec<usize>)> = Vec::new();
    for (i, p) in pairs.iter().enumerate() {
        let key = if confocal { DVec3::ZERO } else { p.xi };
        match groups
            .iter_mut()
            .find(|(x, _)| x.distance(key) <= settings.grid_tolerance)
        {
            Some((_, members)) => members.push(i),
            None => groups.push((key, vec![i])),
        }
    }

    let (px, py) = (2 * nx, 2 * ny);
    let plane = px * py;
    // The kernels' planes, the field (complex f64 at every depth and cell), each
    // group's spectra (complex f64 per cell and line) and each thread's work planes.
    let bytes = [
        [lines.len(), plane, 8],
        [depths, nx * ny, 16],
        [nx * ny, lines.len(), 16],
        [plane, 32, rayon::current_num_threads()],
    ]
    .iter()
    .map(|f| f.iter().fold(1usize, |a, &b| a.saturating_mul(b)))
    .fold(0usize, usize::saturating_add);
    check_memory("RSD", bytes)?;
    Ok(Spectral {
        confocal,
        pad,
        join,
        padded_bins,
        lines,
        groups,
    })
}

/// `r^power`, with the common powers written out (`powf` per kernel sample cost more
/// than the rest of the kernel).
fn leg_gain(r: f64, power: f64) -> f64 {
    match power {
        0.0 => 1.0,
        1.0 => r,
        2.0 => r * r,
        -1.0 => 1.0 / r,
        -2.0 => 1.0 / (r * r),
        p => r.powf(p),
    }
}

//! What LCT and f-k migration share: the confocal transients as a `[cell][bin]` cube on
//! an axis from path length 0, its real spectra along time scattered into slices of
//! the laterally padded grid, and the frame volume built back from per-cell lines.
use rayon::prelude::*;
use realfft::RealFftPlanner;
use rustfft::num_complex::Complex32;

use super::scan::gather_cube;
use super::{FrameVolume, PlanarScan, SolverError};
use crate::transient::{TimeAxis, TransientSet};

/// Checks the settings LCT and f-k migration share: the radiometric exponent (0 to 8)
/// and the grid tolerance (a positive length).
pub(super) fn check_settings(falloff: f64, grid_tolerance: f64) -> Result<(), SolverError> {
    if !(falloff.is_finite() && (0.0..=8.0).contains(&falloff)) {
        return Err(SolverError::Setting {
            name: "falloff",
            value: falloff.to_string(),
            expected: "between 0 and 8",
        });
    }
    if !(grid_tolerance.is_finite() && grid_tolerance > 0.0) {
        return Err(SolverError::Setting {
            name: "grid-tolerance",
            value: grid_tolerance.to_string(),
            expected: "a positive length in metres",
        });
    }
    Ok(())
}

/// Bins from path length 0 to the end of `axis`; an error naming `solver` when
/// the data end at or before path length 0.
pub(super) fn bins_from_zero(axis: &TimeAxis, solver: &str) -> Result<usize, SolverError> {
    if axis.end() <= 0.0 {
        return Err(SolverError::Axis(format!(
            "the histograms end at path length {:.3} m; {solver} needs positive path lengths",
            axis.end()
        )));
    }
    Ok((axis.end() / axis.width - 1e-9).ceil() as usize)
}

/// Every pair of `set` in its cell of `scan`, on `m` bins from path length 0, the
/// cells weighted by their share of the grid where `relay_weights` says.
pub(super) fn cube(set: &TransientSet, scan: &PlanarScan, m: usize, relay_weights: bool) -> Vec<f32> {
    let members: Vec<usize> = (0..set.len()).collect();
    gather_cube(set, &members, scan, 0.0, m, relay_weights)
}

/// The real FFT (length 2m) of each cell's line of `cube` (`[cell][m]`, cells of an
/// `nx × ny` grid), scattered into `m + 1` slices `[k][Y][X]` of the `2ny × 2nx`
/// padded grid, zero outside the measured quadrant.
pub(super) fn padded_spectra(cube: &[f32], m: usize, [nx, ny]: [usize; 2]) -> Vec<Complex32> {
    let (px, pt) = (2 * nx, 2 * m);
    let slice_len = px * 2 * ny;
    let r2c = RealFftPlanner::<f32>::new().plan_fft_forward(pt);
    let spectra: Vec<Vec<Complex32>> = cube
        .par_chunks(m)
        .map(|line| {
            let mut input = vec![0.0f32; pt];
            input[..m].copy_from_slice(line);
            let mut out = r2c.make_output_vec();
            r2c.process(&mut input, &mut out)
                .expect("buffer lengths match the plan");
            out
        })
        .collect();
    let mut slices = vec![Complex32::default(); (m + 1) * slice_len];
    for (cell, spectrum) in spectra.iter().enumerate() {
        let (y, x) = (cell / nx, cell % nx);
        for (k, v) in spectrum.iter().enumerate() {
            slices[k * slice_len + y * px + x] = *v;
        }
    }
    slices
}

/// The frame volume on `scan`'s grid from one line of `m` depth samples per cell
/// (`lines[cell][t]`, depth `(t + ½)·w/2` for bin width `w`).
pub(super) fn frame_from_lines(scan: &PlanarScan, w: f64, m: usize, lines: &[Vec<f32>]) -> FrameVolume {
    let [nx, ny] = scan.relay.resolution;
    let mut data = vec![0.0f32; m * nx * ny];
    for (cell, line) in lines.iter().enumerate() {
        for (t, v) in line.iter().enumerate() {
            data[t * nx * ny + cell] = *v;
        }
    }
    FrameVolume {
        relay: scan.relay,
        depth_start: 0.25 * w,
        depth_step: 0.5 * w,
        depths: m,
        data,
    }
}

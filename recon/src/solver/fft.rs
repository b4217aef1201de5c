//! Two-dimensional complex FFTs on row-major buffers, built from rustfft's 1-D plans.
//!
//! The forward transform leaves its result transposed (`[x][y]`) and the inverse takes
//! it back: the solvers only multiply spectra pointwise between the two, so the
//! transpose in the middle is never undone, which saves a pass over memory.
use std::sync::Arc;

use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};

/// Plans for a `ny × nx` transform.
pub(crate) struct Fft2 {
    nx: usize,
    ny: usize,
    fx: Arc<dyn Fft<f32>>,
    fy: Arc<dyn Fft<f32>>,
    ix: Arc<dyn Fft<f32>>,
    iy: Arc<dyn Fft<f32>>,
}

impl Fft2 {
    pub(crate) fn new(ny: usize, nx: usize) -> Self {
        let mut planner = FftPlanner::new();
        Self {
            nx,
            ny,
            fx: planner.plan_fft_forward(nx),
            fy: planner.plan_fft_forward(ny),
            ix: planner.plan_fft_inverse(nx),
            iy: planner.plan_fft_inverse(ny),
        }
    }

    /// Scratch length the transforms need.
    pub(crate) fn scratch_len(&self) -> usize {
        self.nx * self.ny
            + [&self.fx, &self.fy, &self.ix, &self.iy]
                .iter()
                .map(|f| f.get_inplace_scratch_len())
                .max()
                .unwrap_or(0)
    }

    /// `buf` (`[y][x]`) → its spectrum, transposed (`[kx][ky]`).
    pub(crate) fn forward_transposed(&self, buf: &mut [Complex32], scratch: &mut [Complex32]) {
        let (tmp, fft_scratch) = scratch.split_at_mut(self.nx * self.ny);
        self.fx.process_with_scratch(buf, fft_scratch);
        transpose(buf, tmp, self.ny, self.nx);
        self.fy.process_with_scratch(tmp, fft_scratch);
        buf.copy_from_slice(tmp);
    }

    /// A transposed spectrum → `[y][x]` values, unnormalised (times `nx·ny`).
    pub(crate) fn inverse_from_transposed(&self, buf: &mut [Complex32], scratch: &mut [Complex32]) {
        let (tmp, fft_scratch) = scratch.split_at_mut(self.nx * self.ny);
        self.iy.process_with_scratch(buf, fft_scratch);
        transpose(buf, tmp, self.nx, self.ny);
        self.ix.process_with_scratch(tmp, fft_scratch);
        buf.copy_from_slice(tmp);
    }
}

/// `out[c][r] = input[r][c]` for a `rows × cols` input.
fn transpose(input: &[Complex32], out: &mut [Complex32], rows: usize, cols: usize) {
    const TILE: usize = 16;
    for r0 in (0..rows).step_by(TILE) {
        for c0 in (0..cols).step_by(TILE) {
            for r in r0..(r0 + TILE).min(rows) {
                for c in c0..(c0 + TILE).min(cols) {
                    out[c * rows + r] = input[r * cols + c];
                }
            }
        }
    }
}

/// The `i`-th of `len` values of a raised cosine from `from` to `to`, both ends left
/// out (they are the neighbouring bins' values): what a padded transient's circular
/// FFT buffer holds after its last bin, so that it comes back to its first smoothly
/// instead of in a step (FBP's phasor filter and RSD's propagation both pad so).
pub(crate) fn raised_cosine(from: f64, to: f64, i: usize, len: usize) -> f64 {
    let t = (i + 1) as f64 / (len + 1) as f64;
    let up = 0.5 * (1.0 - (std::f64::consts::PI * t).cos());
    from + (to - from) * up
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_delta_spectrum() {
        let (ny, nx) = (6, 10);
        let fft = Fft2::new(ny, nx);
        let mut scratch = vec![Complex32::default(); fft.scratch_len()];
        let original: Vec<Complex32> = (0..ny * nx)
            .map(|i| Complex32::new(i as f32, -(i as f32) * 0.5))
            .collect();
        let mut buf = original.clone();
        fft.forward_transposed(&mut buf, &mut scratch);
        fft.inverse_from_transposed(&mut buf, &mut scratch);
        for (a, b) in buf.iter().zip(&original) {
            assert!((a / (nx * ny) as f32 - b).norm() < 1e-4, "{a} vs {b}");
        }
        // A delta at (y, x) = (1, 2): spectrum [kx][ky] = exp(−2πi(kx·2/nx + ky·1/ny)).
        let mut delta = vec![Complex32::default(); ny * nx];
        delta[nx + 2] = Complex32::new(1.0, 0.0);
        fft.forward_transposed(&mut delta, &mut scratch);
        let (kx, ky) = (3usize, 4usize);
        let phase = -2.0 * std::f32::consts::PI * (kx as f32 * 2.0 / nx as f32 + ky as f32 / ny as f32);
        assert!((delta[kx * ny + ky] - Complex32::from_polar(1.0, phase)).norm() < 1e-5);
    }
}

//! Backprojection of a confocal scan on a regular grid: the 3D-GTR virtual scan.
//!
//! When every pair is confocal, the points lie in one plane of constant z on a regular
//! lateral grid of pitch P along x, and the voxel pitch along x is a whole multiple r of
//! P, voxel column i and relay column j are `c + (r·i − j)·P` apart: the lateral
//! offset takes one of `r·nᵢ + nⱼ` values, each shared by many voxel–point pairs. So
//! are the path length `2·√(dx² + dy² + dz²)` and its bin, for a given voxel row and
//! relay row (any spacing along y will do). The falloff weight of a confocal pair is a
//! function of path length alone, already applied to the histograms.
//! This path computes them once per offset, slice and row pair, and adds a contiguous
//! run of histogram values to a contiguous run of voxels: no square roots per voxel,
//! no gathers. The histograms are laid out anew for it, per relay row and x phase
//! (`j mod r`), as `[row][phase][bin][j / r][channel]`, so each run is contiguous.
//!
//! The sum is the general path's (the same interpolation between the same padded
//! bins); only the rounding differs: path lengths are computed in f64 from the grid
//! coordinates instead of in f32 from each voxel's, and the terms are added in another
//! order. The test against the f64 reference holds both paths to the same bound.
use crate::transient::TransientSet;
use crate::volume::VolumeGrid;

/// A confocal scan found to lie on a regular grid that fits the volume's voxels.
#[derive(Clone, Debug, PartialEq)]
pub(super) struct ConfocalGrid {
    /// Height of the relay plane.
    z: f64,
    /// x of column 0 and y of row 0.
    origin: [f64; 2],
    /// Spacing of columns (x) and rows (y).
    pitch: [f64; 2],
    /// Columns and rows.
    n: [usize; 2],
    /// Voxel pitch over relay pitch along x.
    ratio: usize,
    /// The pair at each cell, row by row.
    cells: Vec<usize>,
}

/// One axis of a regular grid: its first value, spacing and count.
fn regular_axis(mut values: Vec<f64>, tol: f64) -> Option<(f64, f64, usize)> {
    values.sort_by(f64::total_cmp);
    values.dedup_by(|next, kept| (*next - *kept).abs() <= tol);
    let n = values.len();
    if n < 2 {
        return None;
    }
    let (first, pitch) = (values[0], (values[n - 1] - values[0]) / (n - 1) as f64);
    let on_grid = values
        .iter()
        .enumerate()
        .all(|(k, v)| (v - (first + k as f64 * pitch)).abs() <= tol);
    (on_grid && pitch > 0.0).then_some((first, pitch, n))
}

impl ConfocalGrid {
    /// The grid of `set`'s pairs, if they are confocal, on one plane of constant z, on
    /// a full regular lateral grid (in any order), and `grid`'s voxel pitch is a whole
    /// multiple of the grid's pitch along x (to 1 part in 10⁶). Points may be off
    /// the grid by 1 nm per metre of their coordinates.
    pub(super) fn detect(set: &TransientSet, grid: &VolumeGrid) -> Option<Self> {
        let pairs = set.pairs();
        let first = pairs.first()?.xi;
        let reach = pairs.iter().fold(0.0f64, |m, p| m.max(p.xi.abs().max_element()));
        let tol = 1e-9 * (1.0 + reach);
        let flat = pairs
            .iter()
            .all(|p| p.xi == p.xd && (p.xi.z - first.z).abs() <= tol && p.xi.is_finite());
        if !flat {
            return None;
        }
        let axis = |a: usize| regular_axis(pairs.iter().map(|p| p.xi[a]).collect(), tol);
        let ((x0, px, nx), (y0, py, ny)) = (axis(0)?, axis(1)?);
        if nx * ny != pairs.len() {
            return None;
        }
        let voxel = grid.voxel().x;
        let ratio = (voxel / px).round();
        if !(ratio >= 1.0 && (voxel - ratio * px).abs() <= 1e-6 * voxel) {
            return None;
        }
        let ratio = ratio as usize;
        // The layout holds `ratio` column phases of `⌈nx / ratio⌉` columns each: past
        // `nx` phases most are empty, and a relay far finer than the voxels (a pitch of
        // 5·10⁻⁸ m under 5 cm voxels, ratio 10⁶) asked for 30 GB. The general path
        // takes such scans.
        if ratio > nx {
            return None;
        }
        let mut cells = vec![usize::MAX; nx * ny];
        for (i, p) in pairs.iter().enumerate() {
            let jx = (((p.xi.x - x0) / px).round() as usize).min(nx - 1);
            let jy = (((p.xi.y - y0) / py).round() as usize).min(ny - 1);
            let cell = &mut cells[jy * nx + jx];
            if *cell != usize::MAX {
                return None;
            }
            *cell = i;
        }
        Some(Self {
            z: first.z,
            origin: [x0, y0],
            pitch: [px, py],
            n: [nx, ny],
            ratio,
            cells,
        })
    }
}

/// The histograms of a [`ConfocalGrid`] laid out for contiguous runs, and what every
/// slice shares.
pub(super) struct Runs<'a, const C: usize> {
    scan: &'a ConfocalGrid,
    /// `[row][phase][bin][column / r][channel]`, zero where a phase has no column.
    data: Vec<f32>,
    /// Bins per padded histogram, and columns per phase.
    bins: usize,
    width: usize,
    /// Volume grid geometry.
    grid: VolumeGrid,
    /// 1 / bin width; the padded index of path length 0 (negated); the last index.
    inv_w: f64,
    offset: f64,
    top: f64,
    /// Per lateral offset k = r·i − j that reaches a voxel: its squared x distance
    /// and its run.
    dx2: Vec<f64>,
    spans: Vec<Span>,
}

/// The voxels of a row that one lateral offset reaches, and where their histogram
/// values start in the offset's phase.
struct Span {
    /// Phase (j mod r) of the offset's columns.
    phase: usize,
    /// The voxel columns i with 0 ≤ r·i − k < nⱼ.
    voxels: std::ops::Range<usize>,
    /// `j / r` of the first of them.
    skip: usize,
}

impl<'a, const C: usize> Runs<'a, C> {
    /// Lays out `padded` (one padded histogram per pair, `C` channels per bin, as the
    /// general path's) for `scan`.
    pub(super) fn new(
        scan: &'a ConfocalGrid,
        grid: &VolumeGrid,
        padded: &[Vec<f32>],
        inv_w: f64,
        offset: f64,
    ) -> Self {
        let [nx, ny] = scan.n;
        let r = scan.ratio;
        let bins = padded.first().map_or(0, |p| p.len() / C);
        let width = nx.div_ceil(r);
        let mut data = vec![0.0f32; ny * r * bins * width * C];
        for jy in 0..ny {
            for jx in 0..nx {
                let h = &padded[scan.cells[jy * nx + jx]];
                let (phase, m) = (jx % r, jx / r);
                let base = (jy * r + phase) * bins * width;
                for (b, v) in h.chunks_exact(C).enumerate() {
                    let at = ((base + b * width) + m) * C;
                    data[at..at + C].copy_from_slice(v);
                }
            }
        }
        // Voxel column i and relay column j are cx + (r·i − j)·P apart.
        let nvx = grid.shape[0];
        let cx = grid.min().x + 0.5 * grid.voxel().x - scan.origin[0];
        // Offsets that reach no voxel (all of a phase's columns out of reach) are left
        // out.
        let (dx2, spans) = (-(nx as isize - 1)..=(r * (nvx - 1)) as isize)
            .filter_map(|k| {
                // Columns j = r·i − k sit in phase (−k mod r) at j / r = i − q.
                let phase = (-k).rem_euclid(r as isize);
                let q = (k + phase) / r as isize;
                let lo = q.max(0);
                let hi = (q + width as isize).min(nvx as isize);
                let span = Span {
                    phase: phase as usize,
                    voxels: lo as usize..hi.max(lo) as usize,
                    skip: (lo - q) as usize,
                };
                (hi > lo).then(|| ((cx + k as f64 * scan.pitch[0]).powi(2), span))
            })
            .unzip();
        Self {
            scan,
            data,
            dx2,
            spans,
            bins,
            width,
            grid: *grid,
            inv_w,
            offset,
            top: bins.saturating_sub(2) as f64,
        }
    }

    /// Adds what every relay row contributes to the depth slices `first..` of the
    /// volume that `out` holds (`C` values per voxel), relay row by relay row, so a
    /// voxel's sum has the same order however the slices are split.
    ///
    /// Relay rows outside: one row's histograms stay in L2 while every voxel row of
    /// the slices visits them. Per voxel row and relay row, one loop over the lateral
    /// offsets takes their square roots and bins (vectorised across offsets),
    /// and a second adds each offset's run.
    #[inline(always)]
    pub(super) fn slices(&self, out: &mut [f32], first: usize) {
        let scan = self.scan;
        let [nvx, nvy, _] = self.grid.shape;
        let (min, voxel) = (self.grid.min(), self.grid.voxel());
        let run = self.bins * self.width * C;
        let r = scan.ratio;
        let mut index = vec![0.0f64; self.spans.len()];
        for jy in 0..scan.n[1] {
            let hists = &self.data[jy * r * run..(jy + 1) * r * run];
            let y = scan.origin[1] + jy as f64 * scan.pitch[1];
            for (iz, slice) in out.chunks_exact_mut(nvx * nvy * C).enumerate() {
                let dz = min.z + ((first + iz) as f64 + 0.5) * voxel.z - scan.z;
                for (iy, row) in slice.chunks_exact_mut(nvx * C).enumerate() {
                    let dy = min.y + (iy as f64 + 0.5) * voxel.y - y;
                    self.offsets(dy * dy + dz * dz, &mut index);
                    self.add_runs(row, hists, &index);
                }
            }
        }
    }

    /// Adds each lateral offset's run of one relay row's histograms (`hists`) to one
    /// voxel row.
    #[inline(always)]
    fn add_runs(&self, row: &mut [f32], hists: &[f32], index: &[f64]) {
        for (span, &f) in self.spans.iter().zip(index) {
            // Clamped to the padding: zeros on both sides.
            if f <= 0.0 || f >= self.top {
                continue;
            }
            let b = f as usize;
            let t = f - b as f64;
            let (wa, wb) = ((1.0 - t) as f32, t as f32);
            // Bin b's run, then bin b + 1's.
            let at = (span.phase * self.bins + b) * self.width * C + span.skip * C;
            let next = at + self.width * C;
            let n = span.voxels.len() * C;
            let (ha, hb) = (&hists[at..at + n], &hists[next..next + n]);
            let out = &mut row[span.voxels.start * C..span.voxels.end * C];
            for ((o, &a), &b) in out.iter_mut().zip(ha).zip(hb) {
                *o += wa * a + wb * b;
            }
        }
    }

    /// The padded bin index of every lateral offset, at squared distance `dyz` across
    /// rows and depth. (No falloff gain: on a confocal scan the whole weight is a
    /// function of path length, applied to the histograms before backprojection.)
    #[inline(always)]
    fn offsets(&self, dyz: f64, index: &mut [f64]) {
        let (inv_w, offset, top) = (self.inv_w, self.offset, self.top);
        for (f, &dx2) in index.iter_mut().zip(&self.dx2) {
            *f = ((2.0 * (dx2 + dyz).sqrt()) * inv_w - offset).max(0.0).min(top);
        }
    }
}

//! Recognising a regular planar grid in measured relay points, for LCT and RSD.
use glam::DVec3;

use super::SolverError;
use crate::linalg::fit_plane;
use crate::relay::VirtualRelay;
use crate::volume::VolumeGrid;

/// Relay points identified with the cells of a planar grid.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanarScan {
    /// The grid (its normal faces the hidden scene).
    pub relay: VirtualRelay,
    /// For each point, its cell `iy·resolution[0] + ix`.
    pub cells: Vec<usize>,
    /// The scanned grid's columns `[start, end)` and rows within `relay`'s: the whole
    /// grid, unless [`PlanarScan::reaching`] added empty cells around it so that a
    /// solver's volume covers a reconstruction volume wider than the scan. Only cells
    /// inside count as the sampled aperture (the cells' quadrature weights).
    pub aperture: [[usize; 2]; 2],
}

/// Most cells [`PlanarScan::reaching`] makes along an axis, as a multiple of the
/// scanned grid's (the solvers' time and memory grow with the cells).
pub const MAX_REACH_FACTOR: usize = 3;

impl PlanarScan {
    /// Finds the grid `points` lie on: a fitted plane (rms distance at most
    /// `tolerance`), its normal oriented along `normal_hint`, columns along world x
    /// projected into the plane. Coordinates within `tolerance` count as one grid line;
    /// the spacing is the median gap between lines and every point must sit within a
    /// quarter spacing of a grid node. Missing nodes are allowed (they read as zero).
    pub fn detect(
        what: &'static str,
        points: &[DVec3],
        normal_hint: DVec3,
        tolerance: f64,
    ) -> Result<Self, SolverError> {
        if points.is_empty() {
            return Err(SolverError::Empty);
        }
        let plane = fit_plane(points).ok_or_else(|| SolverError::NotGrid {
            what,
            detail: match points.len() {
                1 => "1 point is fewer than three".to_owned(),
                n => format!("{n} points are fewer than three or collinear"),
            },
        })?;
        if plane.rms > tolerance {
            return Err(SolverError::NotPlanar {
                what,
                rms_mm: plane.rms * 1e3,
                tolerance_mm: tolerance * 1e3,
            });
        }
        let normal = if plane.normal.dot(normal_hint) < 0.0 {
            -plane.normal
        } else {
            plane.normal
        };
        let hint = if normal.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
        let frame = VirtualRelay::new(plane.centre, normal, hint, [1.0, 1.0], [2, 2])?;
        let coords: [Vec<f64>; 2] =
            [frame.u, frame.v].map(|axis| points.iter().map(|p| (*p - plane.centre).dot(axis)).collect());
        let mut index = [vec![0usize; points.len()], vec![0usize; points.len()]];
        let mut lines = [(0.0, 0.0, 0usize); 2];
        for a in 0..2 {
            let (first, spacing, count) = grid_lines(what, &coords[a], tolerance)?;
            for (i, &c) in coords[a].iter().enumerate() {
                let f = (c - first) / spacing;
                if (f - f.round()).abs() > 0.25 {
                    return Err(SolverError::NotGrid {
                        what,
                        detail: format!(
                            "point {i} is {:.2} spacings off the nearest grid line",
                            (f - f.round()).abs()
                        ),
                    });
                }
                // Lines clustered within the tolerance can put a point of the first or
                // last cluster a line beyond the grid: not a grid of these lines.
                if f.round() < 0.0 || f.round() >= count as f64 {
                    return Err(SolverError::NotGrid {
                        what,
                        detail: format!("point {i} falls on line {} of a grid of {count} lines", f.round()),
                    });
                }
                index[a][i] = f.round() as usize;
            }
            lines[a] = (first, spacing, count);
        }
        let [(x0, sx, nx), (y0, sy, ny)] = lines;
        let centre = plane.centre
            + frame.u * (x0 + 0.5 * (nx - 1) as f64 * sx)
            + frame.v * (y0 + 0.5 * (ny - 1) as f64 * sy);
        let relay = VirtualRelay::new(
            centre,
            normal,
            frame.u,
            [nx as f64 * sx, ny as f64 * sy],
            [nx, ny],
        )?;
        let cells = (0..points.len())
            .map(|i| index[1][i] * nx + index[0][i])
            .collect();
        Ok(Self {
            relay,
            cells,
            aperture: [[0, nx], [0, ny]],
        })
    }

    /// A scan of a full grid: every cell measured once, in order.
    pub fn full(relay: VirtualRelay) -> Self {
        let [nx, ny] = relay.resolution;
        Self {
            cells: (0..relay.len()).collect(),
            relay,
            aperture: [[0, nx], [0, ny]],
        }
    }

    /// This scan on a grid widened, at the same pitch, by empty cells until it covers
    /// `grid`'s extent across the relay plane (at most [`MAX_REACH_FACTOR`] times the
    /// scanned cells along an axis). A grid solver's volume spans its grid's cells
    /// only, and is zero beyond; on the wider grid it reconstructs what the aperture's
    /// light says of the hidden scene beside the aperture too, as backprojection does,
    /// instead of leaving a volume wider than the scan dark (and its depth map
    /// arbitrary) there. The added cells are outside the aperture: never measured,
    /// never weighted.
    pub fn reaching(&self, grid: &VolumeGrid) -> Self {
        let r = &self.relay;
        let spacing = r.spacing();
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for corner in 0..8 {
            let c = DVec3::new(
                grid.x[corner & 1],
                grid.y[(corner >> 1) & 1],
                grid.z[(corner >> 2) & 1],
            ) - r.centre;
            for (a, axis) in [r.u, r.v].into_iter().enumerate() {
                lo[a] = lo[a].min(c.dot(axis));
                hi[a] = hi[a].max(c.dot(axis));
            }
        }
        let mut add = [[0usize; 2]; 2];
        for a in 0..2 {
            let half = 0.5 * r.size[a];
            let cells = |gap: f64| (gap / spacing[a] - 1e-6).ceil().max(0.0);
            let (low, high) = (cells(-half - lo[a]), cells(hi[a] - half));
            let scanned = (self.aperture[a][1] - self.aperture[a][0]) as f64;
            let room = (MAX_REACH_FACTOR as f64 * scanned - r.resolution[a] as f64).max(0.0);
            let scale = if low + high > room {
                room / (low + high)
            } else {
                1.0
            };
            add[a] = [(low * scale).floor() as usize, (high * scale).floor() as usize];
        }
        if add == [[0, 0], [0, 0]] {
            return self.clone();
        }
        let [nx, _] = r.resolution;
        let resolution = [0, 1].map(|a| r.resolution[a] + add[a][0] + add[a][1]);
        let shift = |a: usize| (add[a][1] as f64 - add[a][0] as f64) * 0.5 * spacing[a];
        let relay = VirtualRelay::new(
            r.centre + r.u * shift(0) + r.v * shift(1),
            r.normal,
            r.u,
            [0, 1].map(|a| resolution[a] as f64 * spacing[a]),
            resolution,
        )
        .expect("a wider grid of the same plane and pitch");
        let cells = self
            .cells
            .iter()
            .map(|&c| (c / nx + add[1][0]) * resolution[0] + c % nx + add[0][0])
            .collect();
        let aperture = [0, 1].map(|a| self.aperture[a].map(|i| i + add[a][0]));
        Self {
            relay,
            cells,
            aperture,
        }
    }
}

/// First grid line, spacing and number of lines along one axis.
///
/// Values within `tolerance` of a line's mean join it. Where the lines come out closer
/// than four tolerances, the tolerance shrinks to a quarter of their spacing and the
/// values are clustered again (a few rounds at most): at a pitch at or below the
/// tolerance, neighbouring lines merged into one, and a 2 mm virtual scan (a 0.5 m
/// volume of 256 voxels) was refused as no grid after its whole fit.
fn grid_lines(what: &'static str, values: &[f64], tolerance: f64) -> Result<(f64, f64, usize), SolverError> {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
    let cluster = |tolerance: f64| {
        let mut centres: Vec<(f64, usize)> = Vec::new();
        for &v in &sorted {
            match centres.last_mut() {
                Some((sum, n)) if v - *sum / *n as f64 <= tolerance => {
                    *sum += v;
                    *n += 1;
                }
                _ => centres.push((v, 1)),
            }
        }
        centres
    };
    let median_gap = |centres: &[(f64, usize)]| {
        let mut gaps: Vec<f64> = centres
            .windows(2)
            .map(|w| w[1].0 / w[1].1 as f64 - w[0].0 / w[0].1 as f64)
            .collect();
        gaps.sort_by(f64::total_cmp);
        gaps.get(gaps.len() / 2).copied()
    };
    let mut tolerance = tolerance;
    let mut centres = cluster(tolerance);
    for _ in 0..8 {
        match median_gap(&centres) {
            Some(gap) if gap < 4.0 * tolerance && gap > 0.0 => {
                tolerance = 0.25 * gap;
                centres = cluster(tolerance);
            }
            _ => break,
        }
    }
    let centres: Vec<f64> = centres.iter().map(|(s, n)| s / *n as f64).collect();
    if centres.len() < 2 {
        return Err(SolverError::NotGrid {
            what,
            detail: "all points share one grid line along an axis".into(),
        });
    }
    let mut gaps: Vec<f64> = centres.windows(2).map(|w| w[1] - w[0]).collect();
    gaps.sort_by(f64::total_cmp);
    let spacing = gaps[gaps.len() / 2];
    let count = ((centres[centres.len() - 1] - centres[0]) / spacing).round() as usize + 1;
    if count > 4096 {
        return Err(SolverError::NotGrid {
            what,
            detail: format!("{count} grid lines along an axis, more than 4096"),
        });
    }
    Ok((centres[0], spacing, count))
}

/// Histograms of the pairs `members` of `set` gathered into a `[cell][bin]` cube on a
/// new axis of `bins` bins starting at path length `start` (same bin width),
/// resampled linearly when the axes are offset by a fraction of a bin. A cell measured
/// more than once gets the mean. A cell never measured stays zero, and when some are
/// missing and `relay_weights` is set, every measured cell is weighted by its share of
/// the grid ([`super::quadrature::cell_weights`]), so the solvers' sums over cells
/// stay quadratures of the integral over the whole aperture.
pub(crate) fn gather_cube(
    set: &crate::transient::TransientSet,
    members: &[usize],
    scan: &PlanarScan,
    start: f64,
    bins: usize,
    relay_weights: bool,
) -> Vec<f32> {
    let [nx, ny] = scan.relay.resolution;
    let cell_count = nx * ny;
    let axis = set.axis();
    let shift = (start - axis.start) / axis.width;
    let whole = shift.floor();
    let frac = (shift - whole) as f32;
    let whole = whole as isize;
    let mut cube = vec![0.0f32; cell_count * bins];
    let mut count = vec![0u32; cell_count];
    for &p in members {
        let cell = scan.cells[p];
        let h = set.measured(p);
        let w = set.weight(p);
        let row = &mut cube[cell * bins..(cell + 1) * bins];
        let src = |b: isize| {
            if b >= 0 && (b as usize) < h.len() {
                h[b as usize]
            } else {
                0.0
            }
        };
        for (t, out) in row.iter_mut().enumerate() {
            let b = t as isize + whole;
            *out += w * ((1.0 - frac) * src(b) + frac * src(b + 1));
        }
        count[cell] += 1;
    }
    let occupied: Vec<bool> = count.iter().map(|&n| n > 0).collect();
    let mut share: Vec<f64> = occupied.iter().map(|&o| f64::from(u8::from(o))).collect();
    if relay_weights {
        // Weighed within the scanned aperture only: the cells a wider grid adds around
        // it were never part of it.
        let [[x0, x1], [y0, y1]] = scan.aperture;
        let inside: Vec<bool> = (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| y * nx + x))
            .map(|c| occupied[c])
            .collect();
        let w = super::quadrature::cell_weights(&inside, [x1 - x0, y1 - y0], scan.relay.spacing());
        for (i, c) in (y0..y1)
            .flat_map(|y| (x0..x1).map(move |x| y * nx + x))
            .enumerate()
        {
            share[c] = w[i];
        }
    }
    for (cell, &n) in count.iter().enumerate() {
        let row = &mut cube[cell * bins..(cell + 1) * bins];
        if n > 1 {
            row.iter_mut().for_each(|v| *v /= n as f32);
        }
        if share[cell] != 1.0 {
            row.iter_mut()
                .for_each(|v| *v = (f64::from(*v) * share[cell]) as f32);
        }
    }
    cube
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transient::{Pair, TimeAxis, TransientSet};

    /// A 6 × 5 grid over 0.6 × 0.5 m with five inner points missing, each measured
    /// point's histogram its own index.
    fn perforated() -> (TransientSet, PlanarScan) {
        let relay = VirtualRelay::new(DVec3::ZERO, DVec3::Z, DVec3::X, [0.6, 0.5], [6, 5]).unwrap();
        let axis = TimeAxis {
            start: 0.0,
            width: 0.01,
            bins: 4,
        };
        let mut set = TransientSet::new(axis).unwrap();
        let mut points = Vec::new();
        for (i, p) in relay
            .points()
            .into_iter()
            .enumerate()
            .filter(|(i, _)| ![7, 8, 14, 20, 21].contains(i))
        {
            set.push(Pair::confocal(p, DVec3::Z), &[i as f32; 4]).unwrap();
            points.push(p);
        }
        let scan = PlanarScan::detect("test", &points, DVec3::Z, 1e-6).unwrap();
        (set, scan)
    }

    /// Lines at 0, 3, 6, 9.5 and 11.4 mm with a 2 mm tolerance: the last two cluster
    /// into one line at 10.45 mm, a grid of four lines, and the point at 11.4 mm falls
    /// on a fifth. Refused as no grid; it was an index past the grid's cells.
    #[test]
    fn a_point_beyond_the_clustered_lines_is_not_a_grid() {
        let at = [0.0, 3.0, 6.0, 9.5, 11.4];
        let points: Vec<DVec3> = at
            .iter()
            .flat_map(|&y| at.iter().map(move |&x| DVec3::new(x * 1e-3, y * 1e-3, 0.0)))
            .collect();
        match PlanarScan::detect("test", &points, DVec3::Z, 2e-3) {
            Err(SolverError::NotGrid { .. }) => {}
            Ok(scan) => {
                let cells = scan.relay.resolution[0] * scan.relay.resolution[1];
                assert!(scan.cells.iter().all(|&c| c < cells), "a cell past the grid");
            }
            Err(e) => panic!("{e}"),
        }
    }

    /// Grids at and below the 2 mm tolerance the solvers default to: a virtual scan at
    /// half a 4 mm voxel, or at a 0.5 m volume's 256 voxels. Their neighbouring lines
    /// merged, and each was refused as no grid.
    #[test]
    fn grids_finer_than_the_tolerance_are_found() {
        for (pitch, n) in [(2e-3, 64), (1.5e-3, 64), (1e-3, 48), (5e-4, 32)] {
            let relay = VirtualRelay::new(
                DVec3::new(0.1, 0.0, 0.0),
                DVec3::Z,
                DVec3::X,
                [pitch * n as f64; 2],
                [n, n],
            )
            .unwrap();
            let scan = PlanarScan::detect("test", &relay.points(), DVec3::Z, 2e-3)
                .unwrap_or_else(|e| panic!("a {} mm grid: {e}", pitch * 1e3));
            assert_eq!(scan.relay.resolution, [n, n], "a {} mm grid", pitch * 1e3);
            assert!((scan.relay.spacing()[0] - pitch).abs() < 1e-12);
            assert!(scan.cells.iter().enumerate().all(|(i, &c)| c == i));
        }
    }

    #[test]
    fn a_wider_volume_widens_the_grid_around_the_aperture_at_the_same_pitch() {
        let (set, scan) = perforated();
        // A volume within the footprint keeps the scan as it is.
        let inside = VolumeGrid::new([-0.25, 0.25], [-0.2, 0.2], [0.1, 1.0], [8, 8, 8]).unwrap();
        assert_eq!(scan.reaching(&inside), scan);
        // One reaching 0.25 m further in −x and 0.1 m in +y: 3 and 1 cells more.
        let wider = VolumeGrid::new([-0.55, 0.3], [-0.25, 0.35], [0.1, 1.0], [8, 8, 8]).unwrap();
        let w = scan.reaching(&wider);
        assert_eq!(w.relay.resolution, [9, 6]);
        assert!((w.relay.spacing()[0] - 0.1).abs() < 1e-12 && (w.relay.spacing()[1] - 0.1).abs() < 1e-12);
        assert_eq!(w.aperture, [[3, 9], [0, 5]]);
        let (old, new) = (scan.relay.points(), w.relay.points());
        for (p, (&a, &b)) in scan.cells.iter().zip(&w.cells).enumerate() {
            assert!(old[a].distance(new[b]) < 1e-12, "point {p} moved");
        }
        // The added cells are empty and outside the aperture: the measured cells keep
        // their weights (a perforated grid's Voronoi shares), the others get none.
        let members: Vec<usize> = (0..set.len()).collect();
        let a = gather_cube(&set, &members, &scan, 0.0, 4, true);
        let b = gather_cube(&set, &members, &w, 0.0, 4, true);
        assert_eq!(a.iter().sum::<f32>(), b.iter().sum::<f32>());
        for (&ca, &cb) in scan.cells.iter().zip(&w.cells) {
            assert_eq!(a[ca * 4..ca * 4 + 4], b[cb * 4..cb * 4 + 4]);
        }
        // At most MAX_REACH_FACTOR times the scanned cells along an axis.
        let huge = VolumeGrid::new([-50.0, 50.0], [-0.2, 0.2], [0.1, 1.0], [8, 8, 8]).unwrap();
        assert_eq!(scan.reaching(&huge).relay.resolution, [6 * MAX_REACH_FACTOR, 5]);
    }
}

//! Recognising a regular planar grid in measured relay points, for LCT and RSD.
use glam::DVec3;

use super::SolverError;
use crate::linalg::fit_plane;
use crate::relay::VirtualRelay;

/// Relay points identified with the cells of a planar grid.
#[derive(Clone, Debug, PartialEq)]
pub struct PlanarScan {
    /// The grid (its normal faces the hidden scene).
    pub relay: VirtualRelay,
    /// For each point, its cell `iy·resolution[0] + ix`.
    pub cells: Vec<usize>,
}

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
            detail: format!("{} points are fewer than three or collinear", points.len()),
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
        Ok(Self { relay, cells })
    }
}

/// First grid line, spacing and number of lines along one axis.
fn grid_lines(what: &'static str, values: &[f64], tolerance: f64) -> Result<(f64, f64, usize), SolverError> {
    let mut sorted = values.to_vec();
    sorted.sort_by(f64::total_cmp);
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
        let h = set.histogram(p);
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
    let share = if relay_weights {
        super::quadrature::cell_weights(&occupied, scan.relay.resolution, scan.relay.spacing())
    } else {
        occupied.iter().map(|&o| f64::from(u8::from(o))).collect()
    };
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

//! Quadrature weights of relay samples. Every solver sums over the relay's samples
//! what is an integral over the relay surface; where the samples are not a full,
//! regular grid, each is weighted by the share of the surface nearest to it (its
//! Voronoi cell), so the sums stay quadratures of the integral over the whole aperture
//! instead of over a perforated or unevenly weighted one.
use std::collections::HashMap;

use glam::DVec3;

use super::PlanarScan;

/// How far from its samples the relay counts as sampled, in sampling pitches: a gap
/// of one or two missing samples is filled by its neighbours' weights, and a larger
/// hole, or the empty corners of a round aperture's bounding rectangle, is left out of
/// the aperture (its interior beyond this reach), so the points at its rim do not
/// speak for a region nobody measured.
pub const REACH_PITCHES: f64 = 1.5;

/// Quadrature weights of a grid's occupied cells: how many of the grid's cells lie
/// nearest to each (its Voronoi cell, counted in grid cells; a cell equally near to
/// several shares itself among them), counting only cells within
/// [`REACH_PITCHES`] of the coarser spacing of an occupied one. A sum over the
/// occupied cells with these weights approximates the integral over the sampled
/// aperture, where zero-filled gaps would make it an integral over a perforated one,
/// with the sidelobes of one. Every weight is 1 on a full grid, and an empty cell's
/// is 0.
pub(crate) fn cell_weights(occupied: &[bool], [nx, ny]: [usize; 2], [sx, sy]: [f64; 2]) -> Vec<f64> {
    let mut weights: Vec<f64> = occupied.iter().map(|&o| f64::from(u8::from(o))).collect();
    if occupied.iter().all(|&o| o) || !occupied.iter().any(|&o| o) {
        return weights;
    }
    let step = sx.min(sy);
    let reach = REACH_PITCHES * sx.max(sy);
    let mut nearest = Vec::new();
    for (cell, _) in occupied.iter().enumerate().filter(|(_, o)| !**o) {
        let (cx, cy) = ((cell % nx) as isize, (cell / nx) as isize);
        let mut best = f64::INFINITY;
        nearest.clear();
        // Square rings of growing radius, until no nearer cell can lie further out.
        for r in 1isize.. {
            if r as f64 * step > best.sqrt().min(reach) * (1.0 + 1e-9) {
                break;
            }
            for dy in -r..=r {
                let y = cy + dy;
                if y < 0 || y >= ny as isize {
                    continue;
                }
                let stride = if dy.abs() == r { 1 } else { 2 * r };
                let mut dx = -r;
                while dx <= r {
                    let x = cx + dx;
                    if x >= 0 && x < nx as isize && occupied[y as usize * nx + x as usize] {
                        let d = (dx as f64 * sx).powi(2) + (dy as f64 * sy).powi(2);
                        let tie = 1e-9 * d;
                        if d < best - tie {
                            best = d;
                            nearest.clear();
                            nearest.push(y as usize * nx + x as usize);
                        } else if d <= best + tie {
                            nearest.push(y as usize * nx + x as usize);
                        }
                    }
                    dx += stride;
                }
            }
        }
        if best > reach * reach * (1.0 + 1e-9) {
            continue;
        }
        let part = 1.0 / nearest.len() as f64;
        for &p in &nearest {
            weights[p] += part;
        }
    }
    weights
}

/// The grid-line tolerance for recognising a regular grid among relay points, metres
/// (the planar solvers' default `grid-tolerance`).
const GRID_TOLERANCE: f64 = 2e-3;

/// Each point's share of the relay area its set samples, mean 1 over the distinct
/// points (a point listed twice gets its place's share each time); `None` where every
/// share is 1 (a full regular grid), fewer than 3 distinct points or a degenerate set
/// (collinear, coincident) leave nothing to weigh.
///
/// Points on a planar regular grid with missing nodes get their grid Voronoi cells
/// (as LCT, f-k and RSD weigh their cells). Any other set gets the area of each point's Voronoi cell in the
/// set's best-fit plane, within the points' bounding rectangle widened by half a
/// sampling pitch each side ([`super::sampling_pitch`]) and within [`REACH_PITCHES`]
/// of the point, counted on a raster of pitch/8 (so within a few per cent for a cell
/// of 64 raster cells).
pub fn relay_areas(points: &[DVec3]) -> Option<Vec<f64>> {
    let mut index: HashMap<[u64; 3], usize> = HashMap::new();
    let mut distinct: Vec<DVec3> = Vec::new();
    let slot: Vec<usize> = points
        .iter()
        .map(|p| {
            *index.entry(p.to_array().map(f64::to_bits)).or_insert_with(|| {
                distinct.push(*p);
                distinct.len() - 1
            })
        })
        .collect();
    let n = distinct.len();
    if n < 3 {
        return None;
    }
    let area = if let Ok(scan) = PlanarScan::detect("relay", &distinct, DVec3::Z, GRID_TOLERANCE) {
        let [nx, ny] = scan.relay.resolution;
        let mut per_cell = vec![0u32; nx * ny];
        for &c in &scan.cells {
            per_cell[c] += 1;
        }
        if per_cell.iter().all(|&k| k == 1) {
            return None;
        }
        let occupied: Vec<bool> = per_cell.iter().map(|&k| k > 0).collect();
        let share = cell_weights(&occupied, scan.relay.resolution, scan.relay.spacing());
        scan.cells
            .iter()
            .map(|&c| share[c] / f64::from(per_cell[c]))
            .collect()
    } else {
        raster_areas(&distinct)?
    };
    let mean = area.iter().sum::<f64>() / n as f64;
    (mean > 0.0).then(|| slot.iter().map(|&s| area[s] / mean).collect())
}

/// The Voronoi cell areas of `points` (distinct) in their best-fit plane, in raster
/// cells, as [`relay_areas`] describes.
fn raster_areas(points: &[DVec3]) -> Option<Vec<f64>> {
    let n = points.len();
    let pitch = super::sampling_pitch(points)?;
    let centre = points.iter().copied().sum::<DVec3>() / n as f64;
    let plane = crate::relay::VirtualRelay::fitted(points, centre + DVec3::Z, None, [2, 2]).ok()?;
    let uv: Vec<[f64; 2]> = points
        .iter()
        .map(|p| {
            let d = *p - plane.centre;
            [d.dot(plane.u), d.dot(plane.v)]
        })
        .collect();
    let cell = pitch / 8.0;
    let extent = [plane.size[0] + pitch, plane.size[1] + pitch];
    let lo = [-0.5 * extent[0], -0.5 * extent[1]];
    let raster = extent.map(|e| (e / cell).round().max(1.0) as usize);
    let buckets = Buckets::new(&uv, lo, pitch, extent);
    let reach = REACH_PITCHES * pitch;
    let mut count = vec![0.0; n];
    for j in 0..raster[1] {
        let y = lo[1] + (j as f64 + 0.5) * cell;
        for i in 0..raster[0] {
            let x = lo[0] + (i as f64 + 0.5) * cell;
            if let Some(k) = buckets.nearest(&uv, [x, y], reach) {
                count[k] += 1.0;
            }
        }
    }
    Some(count)
}

/// Each pair's quadrature weight in a backprojection, mean about 1; `None` where all
/// are 1.
///
/// - Pairs that are every combination of their distinct illumination and detection
///   points (a fixed laser and a detection grid, a few lasers and a scanned SPAD)
///   sample the two relay integrals independently: the product of the two points'
///   [`relay_areas`].
/// - Any other set (confocal scans, scattered pairs) samples one surface: the area of
///   each pair's midpoint (the scan point, for confocal pairs).
///
/// A pair measured more than once shares its weight among its copies.
pub fn pair_weights(pairs: &[crate::Pair]) -> Option<Vec<f64>> {
    let key = |p: &crate::Pair| -> [u64; 6] {
        let (a, b) = (p.xi.to_array(), p.xd.to_array());
        [a[0], a[1], a[2], b[0], b[1], b[2]].map(f64::to_bits)
    };
    let mut copies: HashMap<[u64; 6], u32> = HashMap::new();
    for p in pairs {
        *copies.entry(key(p)).or_default() += 1;
    }
    let count_distinct = |points: &mut dyn Iterator<Item = DVec3>| {
        points
            .map(|x| x.to_array().map(f64::to_bits))
            .collect::<std::collections::HashSet<_>>()
            .len()
    };
    let illumination = count_distinct(&mut pairs.iter().map(|p| p.xi));
    let detection = count_distinct(&mut pairs.iter().map(|p| p.xd));
    let weights: Vec<f64> = if copies.len() == illumination * detection {
        let xi: Vec<DVec3> = pairs.iter().map(|p| p.xi).collect();
        let xd: Vec<DVec3> = pairs.iter().map(|p| p.xd).collect();
        let (ai, ad) = (relay_areas(&xi), relay_areas(&xd));
        if ai.is_none() && ad.is_none() && copies.len() == pairs.len() {
            return None;
        }
        (0..pairs.len())
            .map(|k| ai.as_ref().map_or(1.0, |a| a[k]) * ad.as_ref().map_or(1.0, |a| a[k]))
            .collect()
    } else {
        let mid: Vec<DVec3> = pairs.iter().map(|p| (p.xi + p.xd) * 0.5).collect();
        match relay_areas(&mid) {
            Some(a) => a,
            None if copies.len() == pairs.len() => return None,
            None => vec![1.0; pairs.len()],
        }
    };
    Some(
        pairs
            .iter()
            .zip(weights)
            .map(|(p, w)| w / f64::from(copies[&key(p)]))
            .collect(),
    )
}

/// Points sorted into square buckets of one pitch, for nearest-point queries.
struct Buckets {
    lo: [f64; 2],
    size: f64,
    shape: [usize; 2],
    /// Point indices by bucket (`start[b]..start[b + 1]` of `items`).
    start: Vec<usize>,
    items: Vec<usize>,
}

impl Buckets {
    fn new(uv: &[[f64; 2]], lo: [f64; 2], size: f64, extent: [f64; 2]) -> Self {
        let shape = [
            (extent[0] / size).ceil().max(1.0) as usize,
            (extent[1] / size).ceil().max(1.0) as usize,
        ];
        let mut this = Self {
            lo,
            size,
            shape,
            start: vec![0; shape[0] * shape[1] + 1],
            items: vec![0; uv.len()],
        };
        let of: Vec<usize> = uv.iter().map(|&p| this.bucket(p)).collect();
        for &b in &of {
            this.start[b + 1] += 1;
        }
        for b in 0..this.start.len() - 1 {
            this.start[b + 1] += this.start[b];
        }
        let mut fill = this.start.clone();
        for (i, &b) in of.iter().enumerate() {
            this.items[fill[b]] = i;
            fill[b] += 1;
        }
        this
    }

    fn coords(&self, [x, y]: [f64; 2]) -> [isize; 2] {
        let c =
            |v: f64, lo: f64, n: usize| (((v - lo) / self.size).floor() as isize).clamp(0, n as isize - 1);
        [c(x, self.lo[0], self.shape[0]), c(y, self.lo[1], self.shape[1])]
    }

    fn bucket(&self, p: [f64; 2]) -> usize {
        let [i, j] = self.coords(p);
        j as usize * self.shape[0] + i as usize
    }

    /// The index of the point of `uv` nearest to `q` (the first of equals), if one
    /// lies within `reach`.
    fn nearest(&self, uv: &[[f64; 2]], q: [f64; 2], reach: f64) -> Option<usize> {
        let [ci, cj] = self.coords(q);
        let (mut best, mut at) = (reach * reach, usize::MAX);
        // Square rings of buckets; a point in ring r is at least (r − 1) buckets away.
        for r in 0isize.. {
            if (r - 1) as f64 * self.size > best.sqrt() {
                break;
            }
            if r > self.shape[0].max(self.shape[1]) as isize {
                break;
            }
            for j in cj - r..=cj + r {
                if j < 0 || j >= self.shape[1] as isize {
                    continue;
                }
                let step = if (j - cj).abs() == r { 1 } else { (2 * r).max(1) };
                let mut i = ci - r;
                while i <= ci + r {
                    if i >= 0 && i < self.shape[0] as isize {
                        let b = j as usize * self.shape[0] + i as usize;
                        for &k in &self.items[self.start[b]..self.start[b + 1]] {
                            let d = (uv[k][0] - q[0]).powi(2) + (uv[k][1] - q[1]).powi(2);
                            if d < best || (d == best && k < at) {
                                (best, at) = (d, k);
                            }
                        }
                    }
                    i += step;
                }
            }
        }
        (at != usize::MAX).then_some(at)
    }
}

#[cfg(test)]
mod tests {
    use super::{cell_weights, pair_weights, relay_areas};
    use glam::DVec3;

    #[test]
    fn a_full_grid_weighs_one_and_the_weights_cover_the_grid() {
        assert_eq!(cell_weights(&[true; 12], [4, 3], [0.1, 0.1]), vec![1.0; 12]);
        assert_eq!(cell_weights(&[false; 6], [3, 2], [0.1, 0.1]), vec![0.0; 6]);
        // Scattered cells of a 20 x 15 grid: the weights ...
        let occupied: Vec<bool> = (0..300).map(|c: usize| (c * c * 31 + c * 7) % 7 < 3).collect();
        let w = cell_weights(&occupied, [20, 15], [0.03, 0.02]);
        // ... add up to the cells within reach of a sample (brute force).
        let reach = super::REACH_PITCHES * 0.03;
        let within = (0..300)
            .filter(|&c| {
                (0..300).any(|o| {
                    let (dx, dy) = (
                        (c % 20) as f64 - (o % 20) as f64,
                        (c / 20) as f64 - (o / 20) as f64,
                    );
                    occupied[o] && (dx * 0.03).hypot(dy * 0.02) <= reach
                })
            })
            .count();
        assert!(
            within < 300,
            "some cells out of reach, for the test to mean something"
        );
        assert!((w.iter().sum::<f64>() - within as f64).abs() < 1e-9);
        for (c, (&o, &w)) in occupied.iter().zip(&w).enumerate() {
            assert!(
                if o { w >= 1.0 } else { w == 0.0 },
                "cell {c}: occupied {o}, weight {w}"
            );
        }
    }

    #[test]
    fn a_hole_goes_to_its_nearest_cells() {
        // The centre of a 3 x 3 grid is missing: its four edge neighbours are nearer
        // than the corners and share it.
        let mut occupied = [true; 9];
        occupied[4] = false;
        let w = cell_weights(&occupied, [3, 3], [1.0, 1.0]);
        assert_eq!(w, vec![1.0, 1.25, 1.0, 1.25, 0.0, 1.25, 1.0, 1.25, 1.0]);
        // Columns closer than rows: the row's two neighbours take it.
        let w = cell_weights(&occupied, [3, 3], [1.0, 2.0]);
        assert_eq!(w, vec![1.0, 1.0, 1.0, 1.5, 0.0, 1.5, 1.0, 1.0, 1.0]);
        // A 3 x 3 hole in a 7 x 7 grid: its rim goes to the neighbours outside, its
        // centre (two pitches from any sample) is beyond reach and goes to nobody.
        let mut occupied = [true; 49];
        for c in [16, 17, 18, 23, 24, 25, 30, 31, 32] {
            occupied[c] = false;
        }
        let w = cell_weights(&occupied, [7, 7], [1.0, 1.0]);
        assert_eq!(w.iter().sum::<f64>(), 48.0);
        assert_eq!(
            (w[8], w[9], w[10], w[15], w[22], w[24]),
            (1.0, 1.5, 2.0, 1.5, 2.0, 0.0)
        );
        // A missing corner and its row: the nearest cell of each, further out.
        let occupied = [false, false, false, true, true, true, true, true, true];
        let w = cell_weights(&occupied, [3, 3], [1.0, 1.0]);
        assert_eq!(w, vec![0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 1.0, 1.0, 1.0]);
    }

    fn grid(nx: usize, ny: usize, pitch: f64) -> Vec<DVec3> {
        (0..nx * ny)
            .map(|c| DVec3::new((c % nx) as f64 * pitch, (c / nx) as f64 * pitch, 0.3))
            .collect()
    }

    #[test]
    fn a_full_grid_needs_no_weights_and_a_perforated_one_gets_its_cells() {
        let full = grid(8, 6, 0.05);
        assert_eq!(relay_areas(&full), None);
        let mut holed = full.clone();
        holed.remove(8 * 3 + 4);
        let w = relay_areas(&holed).unwrap();
        let mut occupied = vec![true; 48];
        occupied[8 * 3 + 4] = false;
        let cells = cell_weights(&occupied, [8, 6], [0.05, 0.05]);
        let expected: Vec<f64> = (0..48)
            .filter(|&c| occupied[c])
            .map(|c| cells[c] * 47.0 / 48.0)
            .collect();
        for (k, (a, b)) in w.iter().zip(&expected).enumerate() {
            assert!((a - b).abs() < 1e-12, "point {k}: {a} against {b}");
        }
    }

    #[test]
    fn scattered_points_weigh_their_voronoi_cells() {
        // 300 points on the left half of a tilted 1 m square, 100 on the right: the
        // right's cells are three times as large.
        let mut state = 99u64;
        let mut rand = move || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let (u, v) = (DVec3::new(0.8, 0.0, 0.6), DVec3::Y);
        let points: Vec<DVec3> = (0..400)
            .map(|k| {
                let x = if k < 300 { 0.0 } else { 0.5 } + 0.5 * rand();
                u * x + v * rand()
            })
            .collect();
        let w = relay_areas(&points).unwrap();
        assert!((w.iter().sum::<f64>() - 400.0).abs() < 1e-9);
        let left = w[..300].iter().sum::<f64>() / 300.0;
        let right = w[300..].iter().sum::<f64>() / 100.0;
        assert!(
            (2.5..3.5).contains(&(right / left)),
            "left {left:.3}, right {right:.3}"
        );
        assert!(w.iter().all(|&a| a > 0.0 && a.is_finite()));
        // A point listed twice keeps its place's share each time.
        let mut twice = points.clone();
        twice.push(points[7]);
        let w2 = relay_areas(&twice).unwrap();
        assert!((w2[400] - w2[7]).abs() < 1e-12 && (w2[7] - w[7]).abs() < 1e-12);
        // Too few or degenerate points: nothing to weigh.
        assert_eq!(relay_areas(&points[..2]), None);
        assert_eq!(relay_areas(&[DVec3::ZERO, DVec3::X, 2.0 * DVec3::X]), None);
    }

    #[test]
    fn pairs_weigh_by_the_surfaces_they_sample() {
        use crate::Pair;
        let pitch = 0.05;
        let laser = DVec3::new(0.1, 0.1, 0.3);
        let detect = |xd: DVec3| Pair {
            xi: laser,
            ni: DVec3::Z,
            xd,
            nd: DVec3::Z,
        };
        // A fixed laser and a full grid, or a confocal full grid: nothing to weigh.
        let full = grid(8, 6, pitch);
        assert_eq!(
            pair_weights(&full.iter().map(|&x| detect(x)).collect::<Vec<_>>()),
            None
        );
        assert_eq!(
            pair_weights(
                &full
                    .iter()
                    .map(|&x| Pair::confocal(x, DVec3::Z))
                    .collect::<Vec<_>>()
            ),
            None
        );
        // A fixed laser and a perforated grid: the detection points' areas.
        let mut holed = full.clone();
        holed.remove(20);
        let w = pair_weights(&holed.iter().map(|&x| detect(x)).collect::<Vec<_>>()).unwrap();
        assert_eq!(w, relay_areas(&holed).unwrap());
        // Two lasers on the perforated grid: the same, twice (the lasers weigh alike).
        let two: Vec<Pair> = [laser, laser + DVec3::X]
            .iter()
            .flat_map(|&xi| holed.iter().map(move |&xd| Pair { xi, ..detect(xd) }))
            .collect();
        let w2 = pair_weights(&two).unwrap();
        assert_eq!(w2[..47], w[..]);
        assert_eq!(w2[47..], w[..]);
        // A confocal scan measured twice at one point: the copies share its weight.
        let mut pairs: Vec<Pair> = holed.iter().map(|&x| Pair::confocal(x, DVec3::Z)).collect();
        pairs.push(pairs[3]);
        let w3 = pair_weights(&pairs).unwrap();
        let single = relay_areas(&holed).unwrap();
        assert!((w3[3] - 0.5 * single[3]).abs() < 1e-12 && w3[47] == w3[3]);
        assert!((w3[5] - single[5]).abs() < 1e-12);
    }
}

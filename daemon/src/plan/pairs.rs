//! Pair planning: which illumination and detection points to measure, chosen among the
//! relay points the LOS scan found, so every pair has a measured position and normal.
use glam::DVec3;
use periscope_drivers::{AngleLimits, GalvoPose, OpticalAngles};
use periscope_recon::linalg::{FittedPlane, fit_plane};
use periscope_recon::relay::Region;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

use crate::config::{ConfigError, TomlSource};

/// How pairs are laid out.
#[derive(Clone, Debug, PartialEq)]
pub enum PairMode {
    /// Laser and SPAD on the same grid of relay points, the SPAD `offset` metres away
    /// along the relay (against pile-up from the direct return).
    Confocal {
        /// Grid points across the detection region.
        grid: [usize; 2],
        /// Detection offset, metres.
        offset: f64,
    },
    /// One laser point (the relay point nearest `laser`), a grid of detection points.
    FixedLaser {
        /// Where to aim the laser, metres.
        laser: DVec3,
        /// Detection grid.
        grid: [usize; 2],
    },
    /// A grid of laser points × a grid of detection points.
    Scanned {
        /// Laser grid.
        laser_grid: [usize; 2],
        /// Detection grid.
        grid: [usize; 2],
    },
    /// `count` pairs drawn without replacement from the scanned layout.
    Random {
        /// Laser grid.
        laser_grid: [usize; 2],
        /// Detection grid.
        grid: [usize; 2],
        /// Pairs to draw.
        count: usize,
        /// Seed of the draw.
        seed: u64,
    },
    /// A confocal grid with a structured mask: one string per row, `#` measured,
    /// `.` skipped (rows from +v down, columns along +u, in the world-fixed frame of
    /// [`FittedPlane::world_oriented`]: on a wall facing +z, top to bottom from +y and
    /// left to right along +x).
    Mask {
        /// The rows.
        rows: Vec<String>,
        /// Detection offset, metres.
        offset: f64,
    },
}

impl PairMode {
    /// Most pairs this layout can produce.
    pub fn max_pairs(&self) -> usize {
        match self {
            PairMode::Confocal { grid, .. } | PairMode::FixedLaser { grid, .. } => grid[0] * grid[1],
            PairMode::Scanned { laser_grid, grid } => laser_grid[0] * laser_grid[1] * grid[0] * grid[1],
            PairMode::Random { count, .. } => *count,
            PairMode::Mask { rows, .. } => rows.iter().map(|r| r.chars().filter(|&c| c == '#').count()).sum(),
        }
    }

    /// Most detection points this layout can use (distinct cells of its detection
    /// grid, or of the mask).
    pub fn max_detection_points(&self) -> usize {
        match self {
            PairMode::Confocal { grid, .. }
            | PairMode::FixedLaser { grid, .. }
            | PairMode::Scanned { grid, .. } => grid[0] * grid[1],
            PairMode::Random { grid, count, .. } => (grid[0] * grid[1]).min(*count),
            PairMode::Mask { .. } => self.max_pairs(),
        }
    }

    /// A short description.
    pub fn describe(&self) -> String {
        match self {
            PairMode::Confocal { grid, offset } => {
                format!(
                    "confocal {}×{} grid, detection offset {:.1} mm",
                    grid[0],
                    grid[1],
                    offset * 1e3
                )
            }
            PairMode::FixedLaser { laser, grid } => {
                format!(
                    "fixed laser at ({:.3}, {:.3}, {:.3}) m, {}×{} detection grid",
                    laser.x, laser.y, laser.z, grid[0], grid[1]
                )
            }
            PairMode::Scanned { laser_grid, grid } => format!(
                "scanned: {}×{} laser points × {}×{} detection points",
                laser_grid[0], laser_grid[1], grid[0], grid[1]
            ),
            PairMode::Random {
                laser_grid,
                grid,
                count,
                ..
            } => format!(
                "{count} random pairs from {}×{} laser × {}×{} detection points",
                laser_grid[0], laser_grid[1], grid[0], grid[1]
            ),
            PairMode::Mask { rows, .. } => format!("masked confocal grid of {} rows", rows.len()),
        }
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub(crate) struct RawPairs {
    mode: String,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    grid: Option<[usize; 2]>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    laser_grid: Option<[usize; 2]>,
    offset_mm: Option<f64>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    laser: Option<[f64; 3]>,
    count: Option<usize>,
    seed: Option<u64>,
    mask: Option<Vec<String>>,
    candidates: Option<String>,
}

impl RawPairs {
    /// Whether the plan asks for an adaptive capture (`mode = "adaptive"`): the pairs
    /// the `candidates` planner lays out are candidates, and the running fit chooses
    /// which of them to measure (`[recon.adaptive]`).
    pub(crate) fn is_adaptive(&self) -> bool {
        self.mode == "adaptive"
    }
}

/// The pair layout a plan's `[pairs]` asks for. A new plan (`new`) is also refused a
/// key its mode does not read; a stored one (a run made before that was refused) is
/// read as it was.
pub(crate) fn pair_mode(src: &TomlSource, raw: RawPairs, new: bool) -> Result<PairMode, ConfigError> {
    let grid = |key: &str, g: Option<[usize; 2]>| -> Result<[usize; 2], ConfigError> {
        let g = g.ok_or_else(|| src.invalid(key, "is required for this mode: give [nx, ny]"))?;
        if g.iter().any(|&n| !(1..=512).contains(&n)) {
            return Err(src.invalid(key, "must be two counts, 1 to 512"));
        }
        Ok(g)
    };
    let offset_mm = raw.offset_mm.unwrap_or(0.0);
    if !(0.0..=100.0).contains(&offset_mm) {
        return Err(src.invalid("pairs.offset-mm", "must be 0 to 100 mm"));
    }
    let offset = offset_mm * 1e-3;
    let mode = if raw.is_adaptive() {
        match raw.candidates.as_deref() {
            Some("adaptive") => {
                return Err(src.invalid("pairs.candidates", "must name the planner whose pairs are the candidates: \"confocal\", \"fixed-laser\", \"scanned\", \"random\" or \"mask\""));
            }
            Some(m) => m,
            None => {
                return Err(src.invalid(
                    "pairs.candidates",
                    "is required for mode \"adaptive\": the planner whose pairs the fit chooses from (\"confocal\", \"fixed-laser\", \"scanned\", \"random\" or \"mask\", with its keys)",
                ));
            }
        }
    } else {
        if raw.candidates.is_some() {
            return Err(src.invalid(
                "pairs.candidates",
                "is only for mode = \"adaptive\"; remove it, or set that mode",
            ));
        }
        raw.mode.as_str()
    };
    // A key the mode does not read would do nothing, silently (a `count` on a confocal
    // grid, a `laser` on a scanned one): refused, naming it and the mode.
    let mode_key = if raw.is_adaptive() {
        "pairs.candidates"
    } else {
        "pairs.mode"
    };
    let reads: &[&str] = match mode {
        "confocal" => &["grid", "offset-mm"],
        "fixed-laser" => &["laser", "grid"],
        "scanned" => &["laser-grid", "grid"],
        "random" => &["laser-grid", "grid", "count", "seed"],
        "mask" => &["mask", "offset-mm"],
        other => {
            return Err(src.invalid(
                mode_key,
                format!("`{other}` is not a mode: use \"confocal\", \"fixed-laser\", \"scanned\", \"random\", \"mask\" or \"adaptive\" (with `candidates`, one of the others)"),
            ));
        }
    };
    for (name, given) in [
        ("grid", raw.grid.is_some()),
        ("laser-grid", raw.laser_grid.is_some()),
        ("offset-mm", raw.offset_mm.is_some()),
        ("laser", raw.laser.is_some()),
        ("count", raw.count.is_some()),
        ("seed", raw.seed.is_some()),
        ("mask", raw.mask.is_some()),
    ] {
        if new && given && !reads.contains(&name) {
            return Err(src.invalid(
                &format!("pairs.{name}"),
                format!(
                    "is not read by {} `{mode}`, which reads {}: remove it, or choose the mode that uses it",
                    if raw.is_adaptive() { "candidates" } else { "mode" },
                    reads.join(", ")
                ),
            ));
        }
    }
    match mode {
        "confocal" => Ok(PairMode::Confocal {
            grid: grid("pairs.grid", raw.grid)?,
            offset,
        }),
        "fixed-laser" => {
            let laser = raw
                .laser
                .map(DVec3::from_array)
                .ok_or_else(|| src.invalid("pairs.laser", "is required for mode \"fixed-laser\": the point [x, y, z] in metres to aim the laser at"))?;
            if !laser.is_finite() {
                return Err(src.invalid(
                    "pairs.laser",
                    format!("{laser:?} is not a point: each of [x, y, z] must be a finite number of metres"),
                ));
            }
            Ok(PairMode::FixedLaser {
                laser,
                grid: grid("pairs.grid", raw.grid)?,
            })
        }
        "scanned" => Ok(PairMode::Scanned {
            laser_grid: grid("pairs.laser-grid", raw.laser_grid)?,
            grid: grid("pairs.grid", raw.grid)?,
        }),
        "random" => {
            let laser_grid = grid("pairs.laser-grid", raw.laser_grid)?;
            let g = grid("pairs.grid", raw.grid)?;
            let most = laser_grid[0] * laser_grid[1] * g[0] * g[1];
            let count = raw.count.ok_or_else(|| src.invalid("pairs.count", "is required for mode \"random\""))?;
            if !(1..=most).contains(&count) {
                return Err(src.invalid("pairs.count", format!("must be 1 to {most} (laser grid × detection grid)")));
            }
            Ok(PairMode::Random {
                laser_grid,
                grid: g,
                count,
                seed: raw.seed.unwrap_or(0),
            })
        }
        "mask" => {
            let rows = raw.mask.ok_or_else(|| src.invalid("pairs.mask", "is required for mode \"mask\": rows of `#` (measure) and `.` (skip)"))?;
            let width = rows.first().map_or(0, |r| r.chars().count());
            let valid = !rows.is_empty()
                && rows.len() <= 512
                && (1..=512).contains(&width)
                && rows.iter().all(|r| r.chars().count() == width && r.chars().all(|c| c == '#' || c == '.'))
                && rows.iter().any(|r| r.contains('#'));
            if !valid {
                return Err(src.invalid(
                    "pairs.mask",
                    "must be 1 to 512 rows of equal length (1 to 512) made of `#` (measure) and `.` (skip), with at least one `#`",
                ));
            }
            Ok(PairMode::Mask { rows, offset })
        }
        other => Err(src.invalid(
            "pairs.mode",
            format!("`{other}` is not a mode: use \"confocal\", \"fixed-laser\", \"scanned\", \"random\", \"mask\" or \"adaptive\" (with `candidates`, one of the others)"),
        )),
    }
}

/// The most pairs a plan may lay out (2 Mi). Its `pairs.json` holds each at up to
/// about 420 bytes, and the run reads it back at resume, reconstruction and export
/// under a cap of 1 GiB (`run_dir`): a layout past that finished a first session and
/// left its data unreadable after any pause. A 512 × 512 confocal grid is 256 Ki.
pub(crate) const MAX_PLANNED_PAIRS: usize = 1 << 21;

/// Refuses a layout of more than [`MAX_PLANNED_PAIRS`], naming the key that sets its
/// size and the most it may have.
pub(crate) fn refuse_too_many(src: &TomlSource, mode: &PairMode) -> Result<(), ConfigError> {
    let n = mode.max_pairs();
    if n <= MAX_PLANNED_PAIRS {
        return Ok(());
    }
    let key = match mode {
        PairMode::Random { .. } => "pairs.count",
        // Laser grid × detection grid: named by the second, the message says both.
        PairMode::Scanned { .. } => "pairs.grid",
        PairMode::Mask { .. } => "pairs.mask",
        PairMode::Confocal { .. } | PairMode::FixedLaser { .. } => "pairs.grid",
    };
    Err(src.invalid(
        key,
        format!(
            "lays out {n} pairs (the laser grid × the detection grid, or the count), more than the {MAX_PLANNED_PAIRS} a run may hold (its pair plan, pairs.json, \
             must stay readable to resume, reconstruct and export it): use coarser grids, or fewer pairs"
        ),
    ))
}

/// One planned measurement.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlannedPair {
    /// Illumination point and normal.
    pub xi: DVec3,
    /// Normal at `xi`.
    pub ni: DVec3,
    /// Detection point.
    pub xd: DVec3,
    /// Normal at `xd`.
    pub nd: DVec3,
    /// Laser arm angles.
    pub laser: OpticalAngles,
    /// SPAD arm angles.
    pub spad: OpticalAngles,
}

impl PlannedPair {
    /// The pair as reconstructions see it (points and normals).
    pub fn pair(&self) -> periscope_recon::Pair {
        periscope_recon::Pair {
            xi: self.xi,
            ni: self.ni,
            xd: self.xd,
            nd: self.nd,
        }
    }
}

/// The relay as the LOS scan measured it.
pub struct RelayView<'a> {
    /// Points.
    pub points: &'a [DVec3],
    /// Unit normals, toward the instrument.
    pub normals: &'a [DVec3],
}

/// How a grid is laid out over the relay's fitted plane.
#[derive(Clone, Copy, PartialEq)]
enum Layout {
    /// Along the plane's axes as fitted: the first along the points' widest spread,
    /// signs and (on a near-square relay) angle as the scan's noise sets them. Any
    /// rotation of a full grid is as good a grid, and a rotated one staggers where it
    /// skips a column of the LOS scan's lattice (measured below).
    Fitted,
    /// In the world-fixed frame of [`FittedPlane::world_oriented`], the normal on the
    /// side the points' normals face (the instrument's): a mask's first row and column
    /// are the same corner of the relay on every scan.
    World,
}

/// The plane fitted to `candidates`, its axes as `layout` says; `None` where no plane
/// fits.
///
/// Plain grids keep the fitted frame. Laid out in the world frame, the demo's 24 × 24
/// grid (33 mm cells) over its LOS scan's 27 mm lattice skips whole columns of the
/// lattice in step; its FBP silhouette (`tests/e2e.rs`, from the exported capture) fell
/// from 0.66–0.70 to 0.59–0.62 IoU over nine simulator seeds, and the two-torso scene's
/// 3D-GTR from a mean of 0.54 to 0.50.
fn relay_frame(relay: &RelayView<'_>, candidates: &[usize], layout: Layout) -> Option<FittedPlane> {
    let pts: Vec<DVec3> = candidates.iter().map(|&i| relay.points[i]).collect();
    let plane = fit_plane(&pts)?;
    Some(match layout {
        Layout::Fitted => plane,
        Layout::World => plane.world_oriented(candidates.iter().map(|&i| relay.normals[i]).sum()),
    })
}

/// Picks up to `grid` points of `candidates` on a regular grid over their extent in
/// the relay's plane (`relay_frame`): in each cell, the point nearest the cell centre.
/// Returns (row-major cell index, point index), columns along +u, rows from +v down
/// (in the world layout on a wall facing +z, as the instrument sees it: left to right
/// along +x, top to bottom from +y).
fn grid_sample(
    relay: &RelayView<'_>,
    candidates: &[usize],
    grid: [usize; 2],
    layout: Layout,
) -> Vec<(usize, usize)> {
    grid_sample_skipping(relay, candidates, grid, layout, None)
}

/// [`grid_sample`] with the point `skip` laid out with the others (the grid's frame
/// and extent are theirs) but never picked.
fn grid_sample_skipping(
    relay: &RelayView<'_>,
    candidates: &[usize],
    grid: [usize; 2],
    layout: Layout,
    skip: Option<usize>,
) -> Vec<(usize, usize)> {
    let Some(plane) = relay_frame(relay, candidates, layout) else {
        return Vec::new();
    };
    let uv: Vec<(f64, f64)> = candidates
        .iter()
        .map(|&i| {
            let d = relay.points[i] - plane.centre;
            (d.dot(plane.u), d.dot(plane.v))
        })
        .collect();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for &(u, v) in &uv {
        lo = [lo[0].min(u), lo[1].min(v)];
        hi = [hi[0].max(u), hi[1].max(v)];
    }
    let cell = [(hi[0] - lo[0]) / grid[0] as f64, (hi[1] - lo[1]) / grid[1] as f64];
    let mut best: Vec<Option<(f64, usize)>> = vec![None; grid[0] * grid[1]];
    for (k, &(u, v)) in uv.iter().enumerate() {
        if Some(candidates[k]) == skip {
            continue;
        }
        let cx = (((u - lo[0]) / cell[0].max(1e-12)) as usize).min(grid[0] - 1);
        let cy = (((hi[1] - v) / cell[1].max(1e-12)) as usize).min(grid[1] - 1);
        let centre = (
            lo[0] + (cx as f64 + 0.5) * cell[0],
            hi[1] - (cy as f64 + 0.5) * cell[1],
        );
        let d = (u - centre.0).hypot(v - centre.1);
        let slot = &mut best[cy * grid[0] + cx];
        if slot.is_none_or(|(bd, _)| d < bd) {
            *slot = Some((d, candidates[k]));
        }
    }
    best.iter()
        .enumerate()
        .filter_map(|(c, b)| b.map(|(_, i)| (c, i)))
        .collect()
}

/// `n` distinct indices below `len`, sorted, drawn uniformly: memory in proportion
/// to `n`, not `len` (rejection sampling while fewer than half are drawn; otherwise a
/// partial shuffle of `0..len`, which is then at most `2n` long).
fn draw_indices(rng: &mut ChaCha8Rng, len: usize, n: usize) -> Vec<usize> {
    use rand::Rng;
    let n = n.min(len);
    let mut out: Vec<usize> = if n * 2 <= len {
        let mut seen = std::collections::HashSet::with_capacity(n);
        while seen.len() < n {
            seen.insert(rng.random_range(0..len));
        }
        seen.into_iter().collect()
    } else {
        let mut all: Vec<usize> = (0..len).collect();
        for i in 0..n {
            let j = rng.random_range(i..len);
            all.swap(i, j);
        }
        all.truncate(n);
        all
    };
    out.sort_unstable();
    out
}

/// Plans the pairs on a measured relay: positions and normals from the relay, angles
/// from the calibration model. Pairs whose angles fall outside either arm's limits are
/// left out and counted in the second return value.
pub fn plan_pairs(
    mode: &PairMode,
    relay: &RelayView<'_>,
    illumination: &Region,
    detection: &Region,
    arms: [(&GalvoPose, &AngleLimits); 2],
) -> (Vec<PlannedPair>, usize) {
    let ill: Vec<usize> = illumination.select(relay.points);
    let det: Vec<usize> = detection.select(relay.points);
    let both: Vec<usize> = {
        let d: std::collections::HashSet<usize> = det.iter().copied().collect();
        ill.iter().copied().filter(|i| d.contains(i)).collect()
    };
    let mut raw: Vec<(DVec3, DVec3, DVec3, DVec3)> = Vec::new();
    // The SPAD's spot is `offset` from the laser's along the grid's columns (+u), the
    // same way for every pair, so that the scan stays one offset confocal grid.
    let confocal =
        |raw: &mut Vec<_>, grid: [usize; 2], layout: Layout, keep: &dyn Fn(usize) -> bool, offset: f64| {
            let u = relay_frame(relay, &both, layout).map_or(DVec3::X, |p| p.u);
            for (cell, i) in grid_sample(relay, &both, grid, layout) {
                if !keep(cell) {
                    continue;
                }
                let (x, n) = (relay.points[i], relay.normals[i]);
                let along = (u - n * u.dot(n)).normalize_or_zero();
                raw.push((x, n, x + along * offset, n));
            }
        };
    match mode {
        PairMode::Confocal { grid, offset } => {
            confocal(&mut raw, *grid, Layout::Fitted, &|_| true, *offset);
        }
        PairMode::Mask { rows, offset } => {
            let width = rows[0].chars().count();
            let flags: Vec<bool> = rows.iter().flat_map(|r| r.chars().map(|c| c == '#')).collect();
            confocal(
                &mut raw,
                [width, rows.len()],
                Layout::World,
                &|c| flags[c],
                *offset,
            );
        }
        PairMode::FixedLaser { laser, grid } => {
            if let Some(&li) = ill.iter().min_by(|&&a, &&b| {
                relay.points[a]
                    .distance(*laser)
                    .total_cmp(&relay.points[b].distance(*laser))
            }) {
                // The laser's own spot is no detection point: its direct return
                // would swamp the counter. Its cell takes the next point in it; the
                // grid itself is laid out over every detection point, as without it.
                for (_, d) in grid_sample_skipping(relay, &det, *grid, Layout::Fitted, Some(li)) {
                    raw.push((
                        relay.points[li],
                        relay.normals[li],
                        relay.points[d],
                        relay.normals[d],
                    ));
                }
            }
        }
        PairMode::Scanned { laser_grid, grid } | PairMode::Random { laser_grid, grid, .. } => {
            let lasers = grid_sample(relay, &ill, *laser_grid, Layout::Fitted);
            let dets = grid_sample(relay, &det, *grid, Layout::Fitted);
            let product = lasers.len() * dets.len();
            // Random pairs are drawn as indices into the laser × detection product,
            // which is never built: only the drawn pairs are.
            let picked: Box<dyn Iterator<Item = usize>> = match mode {
                PairMode::Random { count, seed, .. } => {
                    let mut rng = ChaCha8Rng::seed_from_u64(*seed);
                    Box::new(draw_indices(&mut rng, product, (*count).min(product)).into_iter())
                }
                _ => Box::new(0..product),
            };
            for k in picked {
                let (l, d) = (lasers[k / dets.len()].1, dets[k % dets.len()].1);
                raw.push((
                    relay.points[l],
                    relay.normals[l],
                    relay.points[d],
                    relay.normals[d],
                ));
            }
        }
    }
    let [(lpose, llim), (spose, slim)] = arms;
    let mut out = Vec::with_capacity(raw.len());
    let mut unreachable = 0;
    for (xi, ni, xd, nd) in raw {
        match (lpose.angles_for(xi), spose.angles_for(xd)) {
            (Some(laser), Some(spad)) if llim.contains(laser) && slim.contains(spad) => {
                out.push(PlannedPair {
                    xi,
                    ni,
                    xd,
                    nd,
                    laser,
                    spad,
                })
            }
            _ => unreachable += 1,
        }
    }
    (out, unreachable)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `nx × ny` relay points `pitch` apart over a plane through the origin spanned by
    /// `a` (columns) and `b` (rows), every normal `n`.
    fn wall(a: DVec3, b: DVec3, n: DVec3, [nx, ny]: [usize; 2], pitch: f64) -> (Vec<DVec3>, Vec<DVec3>) {
        let points: Vec<DVec3> = (0..ny)
            .flat_map(|j| (0..nx).map(move |i| (i, j)))
            .map(|(i, j)| {
                a * ((i as f64 - 0.5 * (nx - 1) as f64) * pitch)
                    + b * ((j as f64 - 0.5 * (ny - 1) as f64) * pitch)
            })
            .collect();
        let normals = vec![n; points.len()];
        (points, normals)
    }

    /// Both arms 1 m out along `n`, looking back at the relay, with room to spare.
    fn plan(mode: &PairMode, points: &[DVec3], normals: &[DVec3], detection: &Region) -> Vec<PlannedPair> {
        let n = normals[0];
        let up = if n.x.abs() < 0.9 {
            DVec3::X.cross(n)
        } else {
            DVec3::Z
        };
        let pose = GalvoPose::looking(n, -n, up).expect("a pose");
        let limits = AngleLimits {
            x: [-1.2, 1.2],
            y: [-1.2, 1.2],
        };
        let relay = RelayView { points, normals };
        let (pairs, unreachable) = plan_pairs(mode, &relay, &Region::All, detection, [(&pose, &limits); 2]);
        assert_eq!(unreachable, 0);
        pairs
    }

    fn corner_mask() -> PairMode {
        PairMode::Mask {
            rows: vec!["#...".into(), "....".into(), "....".into()],
            offset: 0.0,
        }
    }

    #[test]
    fn a_masks_first_cell_is_the_top_left_of_a_wall_however_its_points_spread() {
        // Facing +z, seen from the instrument: +x to the right, +y up. A wide wall and
        // a tall one (whose spread puts the fitted plane's first axis along y), each
        // listed forwards and backwards (which flips nothing in the world).
        for size in [[41, 21], [21, 41]] {
            let (mut points, normals) = wall(DVec3::X, DVec3::Y, DVec3::Z, size, 0.02);
            for _ in 0..2 {
                let pairs = plan(&corner_mask(), &points, &normals, &Region::All);
                assert_eq!(pairs.len(), 1);
                let (lo_x, hi_y) = points
                    .iter()
                    .fold((f64::INFINITY, f64::NEG_INFINITY), |(x, y), p| {
                        (x.min(p.x), y.max(p.y))
                    });
                let w = 0.02 * size[0] as f64 / 4.0;
                let h = 0.02 * size[1] as f64 / 3.0;
                let p = pairs[0].xi;
                assert!(
                    p.x < lo_x + w && p.y > hi_y - h,
                    "size {size:?}: the mask's first cell took {p:?}, not the wall's top left"
                );
                points.reverse();
            }
        }
        // A ZNLOS wall in the x–z plane facing −y: +x to the right, +z up.
        let (points, normals) = wall(DVec3::X, DVec3::Z, DVec3::NEG_Y, [21, 41], 0.02);
        let p = plan(&corner_mask(), &points, &normals, &Region::All)[0].xi;
        assert!(p.x < -0.1 && p.z > 0.2, "ZNLOS wall: the first cell took {p:?}");
    }

    #[test]
    fn a_fixed_laser_never_detects_at_its_own_spot() {
        // Several relay points in each detection cell, the laser's among them; its
        // cell takes another. (A wider wall than high: the fitted layout's axes follow the
        // spread, and on a square one the noise would set their angle.)
        let (points, normals) = wall(DVec3::X, DVec3::Y, DVec3::Z, [16, 12], 0.02);
        let mode = PairMode::FixedLaser {
            laser: DVec3::new(0.01, 0.01, 0.0),
            grid: [8, 6],
        };
        let pairs = plan(&mode, &points, &normals, &Region::All);
        assert_eq!(pairs.len(), 48);
        assert!(
            pairs
                .iter()
                .all(|p| p.xi.distance(DVec3::new(0.01, 0.01, 0.0)) < 1e-12)
        );
        assert!(
            pairs.iter().all(|p| p.xd.distance(p.xi) > 0.01),
            "a pair detects at the laser's spot"
        );
    }
}

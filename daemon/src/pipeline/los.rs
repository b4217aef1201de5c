//! The LOS stage: the SPAD arm sweeps the relay under the diffused laser; each
//! histogram's first-bounce peak gives a range along the SPAD ray, hence a relay point.
//! Then thresholds, outlier removal and normals turn the points into the relay.
use std::collections::BTreeMap;
use std::fs::{File, OpenOptions};
use std::io::{self, Write};
use std::path::Path;
use std::time::Duration;

use glam::DVec3;
use periscope_drivers::{OpticalAngles, TdcConfig};
use periscope_recon::TimeAxis;
use periscope_recon::relay::{estimate_normals, reject_isolated};

use super::{PipelineError, RelayError, Run};
use crate::events::RunEvent;
use crate::run_dir::{RelayPoint, file};

/// Fewest counts in the peak bin that count as a return.
const MIN_PEAK_COUNTS: f64 = 8.0;

/// Sub-bin peak of a histogram (parabola through the top three bins) as a fractional
/// bin index (bin k spans [k, k + 1), so a return wholly in bin k reads k + 0.5 once
/// the half bin is added), with the peak's value; `None` below 8 counts.
pub fn peak<T: Copy + Into<f64>>(counts: &[T]) -> Option<(f64, f64)> {
    let (b, top) =
        counts
            .iter()
            .map(|&c| c.into())
            .enumerate()
            .fold(None, |best: Option<(usize, f64)>, (i, v)| match best {
                Some((_, t)) if t > v => best,
                _ => Some((i, v)),
            })?;
    if !(top >= MIN_PEAK_COUNTS) {
        return None;
    }
    let at = |i: isize| {
        usize::try_from(i)
            .ok()
            .and_then(|i| counts.get(i))
            .map_or(0.0, |&c| c.into())
    };
    let (l, c, r) = (at(b as isize - 1), top, at(b as isize + 1));
    let denom = l - 2.0 * c + r;
    let delta = if denom < 0.0 {
        (0.5 * (l - r) / denom).clamp(-0.5, 0.5)
    } else {
        0.0
    };
    Some((b as f64 + delta, top))
}

/// The first-bounce return's photons: the counts within `half_width` bins of the
/// peak at fractional bin `at` ([`peak`]), less the histogram's median count a bin
/// (dark counts and ambient light). Unlike the peak bin's count, this does not depend
/// on where the pulse falls within its bin, so it reads the spot's albedo to its
/// counting noise ([`periscope_recon::relay::RelayAlbedo`]).
pub(crate) fn return_photons(counts: &[f32], at: f64, half_width: usize) -> f64 {
    if counts.is_empty() {
        return 0.0;
    }
    let centre = (at.max(0.0) as usize).min(counts.len() - 1);
    let lo = centre.saturating_sub(half_width);
    let hi = (centre + half_width + 1).min(counts.len());
    let mut order = counts.to_vec();
    let mid = order.len() / 2;
    let (_, &mut median, _) = order.select_nth_unstable_by(mid, f32::total_cmp);
    let background = f64::from(median).max(0.0);
    counts[lo..hi]
        .iter()
        .map(|&c| f64::from(c) - background)
        .sum::<f64>()
        .max(0.0)
}

/// The range r along the SPAD ray p = S + r·d (`d` a unit vector) of the point whose
/// first-bounce path laser → p → SPAD is `ell`: |p − L| + |p − S| = ℓ gives
/// r = (ℓ² − |D|²) / (2(ℓ + D·d)) with D = S − L (DESIGN.md §4). `None` when no point
/// in front of the SPAD has that path (ℓ shorter than the baseline, or not finite).
pub fn first_bounce_range(ell: f64, laser: DVec3, spad: DVec3, d: DVec3) -> Option<f64> {
    let d_ls = spad - laser;
    // A path no longer than the baseline reaches no point (numerator and denominator
    // both negative once ℓ + D·d < 0 gave a point r > 0 whose path is not ℓ: an early
    // stray count in a window that starts before the light leaves, until 2026-12-07).
    if !(ell > d_ls.length()) {
        return None;
    }
    let r = (ell * ell - d_ls.length_squared()) / (2.0 * (ell + d_ls.dot(d)));
    (r.is_finite() && r > 0.0).then_some(r)
}

impl Run {
    /// Scans the relay; returns the raw returns (point, the return's photons). Each
    /// row's returns are appended to the run's [`LosLog`] as the row is done, so a
    /// resumed scan measures only the rows it lacks (and none, with the laser never
    /// on, where every row is there).
    pub(crate) fn los_scan(&mut self) -> Result<Vec<(DVec3, f64)>, PipelineError> {
        let (mut log, rows) = LosLog::open(&self.dir, self.plan.los.grid)
            .map_err(|e| PipelineError::storage(&self.dir.join(file::LOS), e))?;
        let result = self.los_rows(&mut log, rows);
        if result.is_err() {
            // A stop or a failure: the laser goes off before the log is synced, as the
            // capture's does; the run's `make_safe` parks the arms after.
            if let Err(e) = self.devices.laser.set_emission(false) {
                tracing::warn!(error = %e, "switching the laser off as the LOS scan stopped failed; the run's shutdown tries again");
            }
        }
        let synced = log
            .sync()
            .map_err(|e| PipelineError::storage(&self.dir.join(file::LOS), e));
        let out = result?;
        synced?;
        Ok(out)
    }

    /// [`Run::los_scan`]'s work, with `stored` the rows an earlier session kept.
    fn los_rows(
        &mut self,
        log: &mut LosLog,
        mut stored: LosRows,
    ) -> Result<Vec<(DVec3, f64)>, PipelineError> {
        let los = self.plan.los.clone();
        let acq = self.plan.acquisition.clone();
        let tdc = self.instrument.tdc.clone();
        let [nx, ny] = los.grid;
        let total = nx * ny;
        // Rows past the grid are not this plan's (a log the reader does not trust).
        stored.retain(|&row, _| row < ny);
        if !stored.is_empty() {
            tracing::info!(
                rows = stored.len(),
                of = ny,
                "the LOS scan resumes with the rows an earlier session measured"
            );
        }
        let mut out = Vec::new();
        if stored.len() < ny {
            let devices = &mut self.devices;
            devices.tdc.configure(&TdcConfig {
                bin_width: acq.bin_width,
                bins: acq.bins,
                offset: acq.offset,
                sync_divider: tdc.sync_divider,
                acquisition: los.dwell,
            })?;
            devices.laser_arm.park()?;
            devices.laser_arm.wait_settled(Duration::from_secs(2))?;
            devices.laser.set_diffuser(true)?;
            self.checkpoint()?;
            // The histogrammer must answer before the laser goes on.
            self.devices.tdc.status()?;
            // Emission only while measuring: on here, off as soon as the last point is
            // in (every error path switches it off too).
            self.laser_on()?;
        }
        let spad_pose = self.instrument.spad_arm.pose;
        let (l, s) = (self.instrument.laser_arm.pose.origin, spad_pose.origin);
        let settle = self.settle_timeout();
        // The return's bins: ±1.3 jitter FWHM (±3σ) about its peak, and one more.
        let half_width =
            ((1.3 * self.instrument.spad.jitter_fwhm / acq.bin_width).ceil() as usize + 1).max(2);
        let mut iy = 0;
        while iy < ny {
            if let Some(row) = stored.remove(&iy) {
                out.extend(row);
                iy += 1;
                continue;
            }
            let mut row = Vec::new();
            for jx in 0..nx {
                // Serpentine: no long fly-back between rows.
                let ix = if iy % 2 == 0 { jx } else { nx - 1 - jx };
                let t = |r: [f64; 2], i: usize, n: usize| r[0] + (r[1] - r[0]) * i as f64 / (n - 1) as f64;
                let angles = OpticalAngles {
                    x: t(los.x, ix, nx),
                    y: t(los.y, iy, ny),
                };
                self.checkpoint()?;
                self.devices.spad.move_settled(angles, settle)?;
                let h = self.acquire()?;
                // The first-bounce return is the brightest the SPAD sees: pile-up
                // skews it towards early bins unless undone.
                let counts =
                    crate::record::corrected_counts(&h.counts, los.dwell.as_secs_f64(), &self.instrument);
                if let Some((b, _)) = peak(&counts) {
                    let ell =
                        TimeAxis::of_tdc(acq.offset, acq.bin_width, counts.len(), tdc.system_delay).centre(b);
                    let dir = spad_pose.direction(angles);
                    if let Some(r) = first_bounce_range(ell, l, s, dir) {
                        row.push((s + dir * r, return_photons(&counts, b, half_width)));
                    }
                }
                let done = iy * nx + jx + 1;
                if done % nx == 0 {
                    self.events.emit(RunEvent::LosPoint { done, total });
                }
            }
            if let Some(s) = self.laser_suspension()? {
                // The light changed under this row (the interlock opened, emission
                // was lost): it is measured again once the suspension has cleared
                // (until 2026-12-07 it was kept).
                self.suspend(s, None)?;
                continue;
            }
            log.append(iy, &row)
                .map_err(|e| PipelineError::storage(&self.dir.join(file::LOS), e))?;
            out.extend(row);
            iy += 1;
        }
        self.devices.laser.set_emission(false)?;
        self.devices.laser.set_diffuser(false)?;
        self.report_laser();
        if out.is_empty() {
            // Total paths, as `periscope check` gives them: the window less the
            // system's delay.
            let axis = TimeAxis::of_tdc(acq.offset, acq.bin_width, acq.bins as usize, tdc.system_delay);
            return Err(RelayError::NoReturns {
                scanned: total,
                window: [axis.start, axis.start + axis.bins as f64 * axis.width],
            }
            .into());
        }
        Ok(out)
    }

    /// Keeps the LOS scan's rows aside (`los.jsonl.failed`, `.1`, … for later ones)
    /// after the relay could not be made from them (no returns, too few points): the
    /// rows stay on disk, and a resume scans the relay again instead of failing on the
    /// same rows for good once the cause (a capped lens, a SPAD off, a moved relay) is
    /// put right.
    pub(crate) fn set_aside_los_rows(&self) {
        let from = self.dir.join(file::LOS);
        let mut to = self.dir.join(format!("{}.failed", file::LOS));
        let mut n = 0;
        while to.symlink_metadata().is_ok() {
            n += 1;
            to = self.dir.join(format!("{}.failed.{n}", file::LOS));
        }
        match std::fs::rename(&from, &to).and_then(|()| periscope_recon::io::sync_directory(&self.dir)) {
            Ok(()) => tracing::warn!(
                kept = %to.display(),
                "no relay could be made from the LOS scan's rows; they were kept aside, and a resume scans the relay again"
            ),
            Err(e) => tracing::warn!(
                error = %e,
                "no relay could be made from the LOS scan's rows, and they could not be kept aside: move {} aside before resuming, or the resume fails on the same rows",
                from.display()
            ),
        }
    }

    /// Thresholds, outlier removal and normals ([`relay_points`]).
    pub(crate) fn extract_relay(&self, returns: &[(DVec3, f64)]) -> Result<Vec<RelayPoint>, PipelineError> {
        let s = self.instrument.spad_arm.pose.origin;
        let view = 0.5 * (self.instrument.laser_arm.pose.origin + s);
        relay_points(returns, &self.plan.relay, s, view)
    }
}

/// The relay from the LOS scan's `returns` (point, photons): those within the depth
/// window from the SPAD `spad` and at least `min-intensity` of the brightest among
/// them, isolated points removed, normals estimated facing `view`.
pub(crate) fn relay_points(
    returns: &[(DVec3, f64)],
    r: &crate::plan::RelayStage,
    spad: DVec3,
    view: DVec3,
) -> Result<Vec<RelayPoint>, PipelineError> {
    // The brightest return within the relay's depths: something nearer the instrument
    // (it returns more light) must not raise the threshold the relay is held to. Until
    // 2026-12-07 it was the brightest of all returns.
    let in_depth: Vec<(DVec3, f64)> = returns
        .iter()
        .copied()
        .filter(|(p, _)| (r.depth[0]..=r.depth[1]).contains(&p.distance(spad)))
        .collect();
    let brightest = in_depth.iter().map(|p| p.1).fold(0.0, f64::max);
    let kept: Vec<(DVec3, f64)> = in_depth
        .into_iter()
        .filter(|(_, i)| *i >= r.min_intensity * brightest)
        .collect();
    if kept.len() < r.neighbours.max(8) {
        return Err(RelayError::TooFewPoints {
            kept: kept.len(),
            total: returns.len(),
            depth: r.depth,
            min_intensity: r.min_intensity,
        }
        .into());
    }
    let points: Vec<DVec3> = kept.iter().map(|p| p.0).collect();
    let keep = reject_isolated(&points, 8.min(points.len() - 1), 3.0).map_err(RelayError::from)?;
    let points: Vec<(DVec3, f64)> = kept
        .into_iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(p, _)| p)
        .collect();
    let xs: Vec<DVec3> = points.iter().map(|p| p.0).collect();
    let normals = estimate_normals(&xs, r.neighbours.min(xs.len()), view).map_err(RelayError::from)?;
    Ok(points
        .iter()
        .zip(normals)
        .filter_map(|(&(x, intensity), n)| {
            n.map(|n| RelayPoint {
                x,
                n: n.normal,
                intensity,
            })
        })
        .collect())
}

/// The LOS scan's returns as measured, row by row (`los.jsonl` in the run directory):
/// one line a finished grid row, `CRC-32 (8 hex digits), a space, the row as JSON`
/// (`{"row": iy, "returns": [[x, y, z, photons], …]}`; JSON's shortest round-trip
/// numbers give the same f64s back). Appended as each row is done and synced when the
/// scan stops; a resumed scan takes the rows whose lines are whole and check out, and
/// measures the others (a line cut short or damaged is measured again, never trusted).
pub(crate) struct LosLog {
    file: File,
}

/// The rows a [`LosLog`] holds: each row's returns (point, photons), by row.
pub(crate) type LosRows = BTreeMap<usize, Vec<(DVec3, f64)>>;

#[derive(serde::Serialize, serde::Deserialize)]
struct LosRow {
    row: usize,
    returns: Vec<[f64; 4]>,
}

/// Most bytes a `los.jsonl` line takes a grid point (four f64s as JSON's shortest
/// round-trip numbers take at most 24 characters each, with their brackets and
/// commas); a row's own header and CRC are within [`LOS_LOG_SLACK`].
const LOS_LOG_POINT_BYTES: u64 = 128;

/// Bytes a `los.jsonl` may hold beyond its points': rows' headers and CRCs, and lines
/// a crash cut short that a resumed scan wrote again.
const LOS_LOG_SLACK: u64 = 16 << 20;

impl LosLog {
    /// Opens (or makes) the run's LOS log in `dir` for appending, with the rows it
    /// holds: each row's first whole line, in row order. A file larger than a scan of
    /// `grid` ([nx, ny]) writes is refused before it is read.
    pub(crate) fn open(dir: &Path, grid: [usize; 2]) -> io::Result<(LosLog, LosRows)> {
        let path = dir.join(file::LOS);
        let most = (grid[0] as u64 * grid[1] as u64).saturating_mul(LOS_LOG_POINT_BYTES) + LOS_LOG_SLACK;
        let mut rows = BTreeMap::new();
        // Whether the file ends in a line a crash cut short.
        let mut open_line = false;
        let made = match std::fs::symlink_metadata(&path) {
            Ok(m) if !m.is_file() => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidInput,
                    "not a regular file (a link, a FIFO or a directory): move it aside",
                ));
            }
            Ok(m) if m.len() > most => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidData,
                    format!(
                        "{} bytes, more than a scan of {} × {} points writes ({most}): not this run's; move it aside",
                        m.len(),
                        grid[0],
                        grid[1]
                    ),
                ));
            }
            Ok(_) => {
                let bytes = std::fs::read(&path)?;
                open_line = bytes.last().is_some_and(|&b| b != b'\n');
                for line in bytes.split(|&b| b == b'\n') {
                    if let Some(r) = parse_los_line(line) {
                        rows.entry(r.row).or_insert_with(|| {
                            r.returns
                                .iter()
                                .map(|&[x, y, z, photons]| (DVec3::new(x, y, z), photons))
                                .collect()
                        });
                    }
                }
                false
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => true,
            Err(e) => return Err(e),
        };
        let mut log = LosLog {
            file: OpenOptions::new().create(true).append(true).open(&path)?,
        };
        if made {
            // Its entry made durable with the run directory, as the histogram log's.
            periscope_recon::io::sync_directory(dir)?;
        }
        if open_line {
            // A line a crash cut short is ended, so the next row's line starts whole.
            log.file.write_all(b"\n")?;
        }
        Ok((log, rows))
    }

    /// Appends row `row`'s `returns`.
    fn append(&mut self, row: usize, returns: &[(DVec3, f64)]) -> io::Result<()> {
        let json = serde_json::to_string(&LosRow {
            row,
            returns: returns
                .iter()
                .map(|(p, photons)| [p.x, p.y, p.z, *photons])
                .collect(),
        })
        .map_err(io::Error::other)?;
        let line = format!("{:08x} {json}\n", crc32fast::hash(json.as_bytes()));
        self.file.write_all(line.as_bytes())
    }

    fn sync(&mut self) -> io::Result<()> {
        self.file.sync_data()
    }
}

/// A `los.jsonl` line's row, if the line is whole and its CRC checks out.
fn parse_los_line(line: &[u8]) -> Option<LosRow> {
    let (crc, json) = line.split_at_checked(8)?;
    let json = json.strip_prefix(b" ")?;
    let crc = u32::from_str_radix(std::str::from_utf8(crc).ok()?, 16).ok()?;
    if crc32fast::hash(json) != crc {
        return None;
    }
    let row: LosRow = serde_json::from_slice(json).ok()?;
    row.returns
        .iter()
        .all(|r| r.iter().all(|v| v.is_finite()))
        .then_some(row)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A return of 1,000 photons (a Gaussian of σ 1.6 bins, the simulator's 60 ps
    /// FWHM on 16 ps bins) over 2 background counts a bin, placed anywhere within its
    /// bin: its photons come back within 0.5 %, where the peak bin's count moves by
    /// more than 4 %.
    #[test]
    fn a_returns_photons_do_not_depend_on_its_place_in_the_bin() {
        let (sigma, total) = (1.6, 1000.0);
        let mut photons = Vec::new();
        let mut peaks = Vec::new();
        for k in 0..10 {
            let centre = 40.0 + 0.1 * k as f64;
            let h: Vec<f32> = (0..128)
                .map(|b| {
                    let cdf = |x: f64| periscope_recon::special::norm_cdf((x - centre) / sigma);
                    (2.0 + total * (cdf(b as f64 + 1.0) - cdf(b as f64))) as f32
                })
                .collect();
            let (at, top) = peak(&h).unwrap();
            photons.push(return_photons(&h, at, 6));
            peaks.push(top);
        }
        let spread = |v: &[f64]| {
            let (lo, hi) = v
                .iter()
                .fold((f64::INFINITY, 0.0f64), |(l, h), &x| (l.min(x), h.max(x)));
            hi / lo - 1.0
        };
        assert!(
            photons.iter().all(|p| (p - total).abs() < 0.005 * total),
            "{photons:?}"
        );
        assert!(spread(&peaks) > 0.04, "the peak bins {peaks:?}");
    }

    /// A return nearer the instrument than the relay's depth window (an object that
    /// sends back far more light) does not raise the threshold the relay's returns are
    /// held to: a 20 × 20 wall 2 m away at 1,000 photons a point, its edge rows at 300,
    /// beside one return of 10⁶ at 1 m. Until 2026-12-07 the threshold was 5 % of that
    /// one, and every wall point fell under it.
    #[test]
    fn a_bright_return_outside_the_depth_window_leaves_the_relays_threshold_alone() {
        let spad = DVec3::new(0.0, 0.0, 2.0);
        let mut returns: Vec<(DVec3, f64)> = (0..400)
            .map(|i| {
                let (x, y) = ((i % 20) as f64 * 0.05 - 0.5, (i / 20) as f64 * 0.05 - 0.5);
                let edge = i % 20 == 0 || i % 20 == 19;
                (DVec3::new(x, y, 0.0), if edge { 300.0 } else { 1000.0 })
            })
            .collect();
        returns.push((DVec3::new(0.0, 0.0, 1.0), 1e6));
        let stage = crate::plan::RelayStage {
            depth: [1.5, 3.0],
            min_intensity: 0.05,
            neighbours: 16,
            illumination: periscope_recon::relay::Region::All,
            detection: periscope_recon::relay::Region::All,
            albedo_from_scan: true,
        };
        let relay = relay_points(&returns, &stage, spad, spad).unwrap();
        assert!(relay.len() >= 390, "{} of 400 wall points kept", relay.len());
        assert!(relay.iter().all(|p| p.x.z == 0.0), "the near return is not relay");
        // 0.35 of the brightest within the window: the edge rows (0.3) go.
        let strict = crate::plan::RelayStage {
            min_intensity: 0.35,
            ..stage.clone()
        };
        let relay = relay_points(&returns, &strict, spad, spad).unwrap();
        assert!(relay.len() <= 360 && relay.len() >= 340, "{}", relay.len());
    }

    #[test]
    fn the_peak_is_refined_between_bins() {
        let mut h = vec![0u32; 32];
        h[10] = 50;
        h[11] = 100;
        h[12] = 50;
        assert_eq!(peak(&h), Some((11.0, 100.0)));
        h[12] = 90;
        let (b, _) = peak(&h).unwrap();
        assert!(b > 11.0 && b < 11.5, "{b}");
        assert_eq!(peak(&[0u32, 3, 1]), None, "too few counts is no return");
    }
}

#[cfg(test)]
mod log_tests {
    use super::*;

    const GRID: [usize; 2] = [4, 4];

    /// Rows read back are the rows appended, to the bit; a line a crash cut short or a
    /// flipped digit is not taken (its row is measured again), and the next append
    /// after a cut line starts a line of its own.
    #[test]
    fn the_los_log_gives_back_whole_rows_only() {
        let dir = tempfile::tempdir().unwrap();
        let row = |k: f64| {
            vec![
                (DVec3::new(0.1 * k, -0.2, 1.0 / 3.0), 17.25 * k),
                (DVec3::new(k, k, k), 0.0),
            ]
        };
        {
            let (mut log, rows) = LosLog::open(dir.path(), GRID).unwrap();
            assert!(rows.is_empty());
            log.append(0, &row(1.0)).unwrap();
            log.append(1, &row(2.0)).unwrap();
            log.append(2, &[]).unwrap();
            log.sync().unwrap();
        }
        let path = dir.path().join(file::LOS);
        let mut bytes = std::fs::read(&path).unwrap();
        let (_, rows) = LosLog::open(dir.path(), GRID).unwrap();
        assert_eq!(rows.len(), 3);
        assert_eq!(rows[&0], row(1.0));
        assert_eq!(rows[&1], row(2.0));
        assert!(rows[&2].is_empty());
        // Row 1's line damaged (a digit changed), and row 3's cut short.
        let second = bytes.iter().position(|&b| b == b'\n').unwrap() + 1;
        let digit = second + bytes[second..].iter().position(|&b| b == b'2').unwrap();
        bytes[digit] = b'3';
        let mut torn = bytes.clone();
        let whole = {
            let mut log = LosLog {
                file: File::create(dir.path().join("scratch")).unwrap(),
            };
            log.append(3, &row(3.0)).unwrap();
            std::fs::read(dir.path().join("scratch")).unwrap()
        };
        torn.extend_from_slice(&whole[..whole.len() / 2]);
        std::fs::write(&path, &torn).unwrap();
        let (mut log, rows) = LosLog::open(dir.path(), GRID).unwrap();
        assert_eq!(rows.keys().copied().collect::<Vec<_>>(), [0, 2]);
        log.append(1, &row(2.0)).unwrap();
        drop(log);
        let (_, rows) = LosLog::open(dir.path(), GRID).unwrap();
        assert_eq!(rows.keys().copied().collect::<Vec<_>>(), [0, 1, 2]);
        assert_eq!(rows[&1], row(2.0));
    }
}

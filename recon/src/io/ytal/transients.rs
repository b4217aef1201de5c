//! What a capture means for a reconstruction: the relay pair and the hidden-path start
//! of each transient, every transient rebinned onto a volume's hidden-path axis, and a
//! default volume and viewpoint for a capture that comes with none.
use std::path::PathBuf;

use glam::DVec3;

use super::{FLAG_OVERFLOW, YtalCapture, YtalError};
use crate::transient::{
    C0, Pair, TimeAxis, TransientSet, clip_to_measured, hidden_axis, paths_needed, rebin_path,
};
use crate::volume::VolumeGrid;

/// Most bytes the rebinned transients of a capture may take in memory (the default
/// run budget).
const MAX_TRANSIENT_BYTES: u64 = 16 << 30;

/// Bins of margin, each side, between a transient's paths through the volume and the
/// bins [`YtalCapture::transients`] reads the ambient level from (the pulse's width).
pub(crate) const AMBIENT_MARGIN_BINS: f64 = 5.0;

/// The longest side a volume derived from a capture's relay may have, metres (as a
/// RECON.toml's volume may reach at most 100 m).
pub(super) const MAX_DEFAULT_SIDE_M: f64 = 100.0;

impl YtalCapture {
    /// Laser and sensor point indices of transient `c`.
    pub fn indices(&self, c: usize) -> (usize, usize) {
        let ns = self.sensor_grid.points.len();
        if self.h_format.is_product() {
            (c / ns, c % ns)
        } else if self.laser_grid.points.len() == 1 {
            (0, c)
        } else {
            (c, c)
        }
    }

    /// The relay pair of transient `c`.
    pub fn pair(&self, c: usize) -> Pair {
        let (l, s) = self.indices(c);
        Pair {
            xi: self.laser_grid.points[l],
            ni: self.laser_grid.normals[l],
            xd: self.sensor_grid.points[s],
            nd: self.sensor_grid.normals[s],
        }
    }

    /// Transient `c`, time bins in order.
    pub fn transient(&self, c: usize) -> impl Iterator<Item = f32> + '_ {
        let stride = self.len();
        self.h.iter().skip(c).step_by(stride).copied()
    }

    /// Path length at the start of transient `c`'s bin 0, in hidden path length (legs
    /// from the laser and to the SPAD removed when the file includes them).
    pub fn hidden_start(&self, c: usize) -> f64 {
        if !self.t_accounts_first_and_last_bounces {
            return self.t_start;
        }
        let p = self.pair(c);
        let legs = match (self.laser_xyz, self.sensor_xyz) {
            (Some(l), Some(s)) => p.xi.distance(l) + p.xd.distance(s),
            _ => 0.0, // excluded by `check`
        };
        self.t_start - legs
    }

    /// All transients rebinned onto the hidden-path axis for `volume`, at the file's bin
    /// width, where the file recorded it (the axis stops where the last transient's time
    /// window ends, and starts no earlier than the first one's begins, even when the
    /// volume's paths reach further: [`clip_to_measured`]). Transients with no counts
    /// are left out, and so are those the flags mark overflowed (their counts are only
    /// a lower bound), as in a run's own reconstruction.
    /// The set also records the counts of the bins outside every path through the
    /// volume (with 5 bins to spare), which the crop drops: the ambient level's
    /// evidence ([`TransientSet::ambient`]).
    pub fn transients(&self, volume: &VolumeGrid) -> Result<TransientSet, YtalError> {
        let pairs: Vec<Pair> = (0..self.len()).map(|c| self.pair(c)).collect();
        let axis: TimeAxis =
            hidden_axis(&pairs, volume, self.delta_t / C0).map_err(|e| self.error(e.to_string()))?;
        // Only the paths some transient recorded: beyond the file's time window the
        // rebinned histograms would hold zeros nobody measured.
        let span = self.bins() as f64 * self.delta_t;
        let measured = (0..self.len())
            .map(|c| self.hidden_start(c))
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), s| {
                (lo.min(s), hi.max(s + span))
            });
        let axis = clip_to_measured(&axis, measured, paths_needed(&pairs, volume))
            .map_err(|e| self.error(e.to_string()))?;
        let bytes = (pairs.len() as u64)
            .saturating_mul(axis.bins as u64)
            .saturating_mul(8);
        if bytes > MAX_TRANSIENT_BYTES {
            return Err(self.error(format!(
                "{} transients of {} bins would take {bytes} bytes, more than {MAX_TRANSIENT_BYTES}: \
                 give a smaller [volume] or a coarser capture",
                pairs.len(),
                axis.bins
            )));
        }
        let mut set = TransientSet::new(axis).map_err(|e| self.error(e.to_string()))?;
        // Whole non-negative numbers throughout, or counts corrected for pile-up: a
        // photon-counting capture.
        let mut counts_seen = CountEvidence::default();
        let mut ambient = (0.0f64, 0usize);
        for (c, pair) in pairs.into_iter().enumerate() {
            if self.flags.as_ref().is_some_and(|f| f[c] & FLAG_OVERFLOW != 0) {
                continue;
            }
            self.transient(c).for_each(|v| counts_seen.see(v));
            // The bins no path through the volume reaches hold the ambient level only.
            let (near, far) = crate::transient::path_range(&pair, volume);
            let margin = AMBIENT_MARGIN_BINS * self.delta_t;
            let start = self.hidden_start(c);
            let (mut counts, mut bins) = (0.0f64, 0usize);
            for (k, v) in self.transient(c).enumerate() {
                let (a, b) = (
                    start + k as f64 * self.delta_t,
                    start + (k + 1) as f64 * self.delta_t,
                );
                if b < near - margin || a > far + margin {
                    counts += f64::from(v.max(0.0));
                    bins += 1;
                }
            }
            ambient.0 += counts;
            ambient.1 += bins;
            let h = rebin_path(self.transient(c), start, self.delta_t, &axis);
            if h.iter().any(|&v| v != 0.0) {
                set.push(pair, &h).map_err(|e| self.error(e.to_string()))?;
                // Where the legs differ from pair to pair, so does the part of the axis
                // each window records.
                set.limit_recorded(set.len() - 1, (start, start + span));
            } else {
                set.note_left_out_empty(1);
            }
        }
        if counts_seen.photon_counts() {
            set.mark_photon_counts();
        }
        set.add_ambient(ambient.0, ambient.1);
        Ok(set)
    }

    fn error(&self, message: String) -> YtalError {
        YtalError::Format {
            path: PathBuf::from(super::UNNAMED),
            message,
        }
    }

    /// A reconstruction volume for a capture that comes with none (its sides at most
    /// `MAX_DEFAULT_SIDE_M`, 100 m): over the relay
    /// points' extent, from 5 cm in front of the relay out to the depth the time axis
    /// reaches (at most 3 m), on the side the normals face.
    pub fn default_volume(&self) -> Result<VolumeGrid, YtalError> {
        let pts: Vec<DVec3> = self
            .sensor_grid
            .points
            .iter()
            .chain(&self.laser_grid.points)
            .copied()
            .collect();
        let normal = self
            .sensor_grid
            .normals
            .iter()
            .fold(DVec3::ZERO, |a, &n| a + n)
            .normalize_or_zero();
        if normal == DVec3::ZERO {
            return Err(self.error("the sensor normals cancel out; give a RECON.toml with a [volume]".into()));
        }
        let (lo, hi) = pts.iter().fold(
            (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
            |(a, b), &p| (a.min(p), b.max(p)),
        );
        let reach = (0..self.len())
            .map(|c| self.hidden_start(c))
            .fold(f64::NEG_INFINITY, f64::max)
            + self.delta_t * self.bins() as f64;
        let depth = (0.5 * reach).clamp(0.2, 3.0);
        let (near, far) = (lo + normal * 0.05, hi + normal * depth);
        let (a, b) = (near.min(far).min(lo), near.max(far).max(hi));
        // Keep the relay itself out of the volume along the normal axis.
        let axis = normal.abs().max_element();
        let mut min = a;
        let mut max = b;
        for k in 0..3 {
            if normal[k].abs() == axis {
                if normal[k] > 0.0 {
                    min[k] = hi[k] + 0.05;
                    max[k] = hi[k] + depth;
                } else {
                    max[k] = lo[k] - 0.05;
                    min[k] = lo[k] - depth;
                }
            }
        }
        // A relay of hundreds of metres (a unit error in the file, metres for
        // millimetres the other way) made a volume as wide, whose fit ran for minutes;
        // a RECON.toml's volume may reach 100 m at most, and so may this one.
        let side = (max - min).max_element();
        if !(side <= MAX_DEFAULT_SIDE_M) {
            return Err(self.error(format!(
                "the relay points span {side:.3e} m, and a volume over them would too, past the {MAX_DEFAULT_SIDE_M} m \
                 a volume may be: check that the positions are in metres, or give a RECON.toml with a [volume]"
            )));
        }
        VolumeGrid::new([min.x, max.x], [min.y, max.y], [min.z, max.z], [64, 64, 64]).map_err(|e| {
            self.error(format!(
                "the relay points span no area across their normal ({e}), so no volume over them can be derived: \
                 give a RECON.toml with a [volume]"
            ))
        })
    }

    /// A point on the side of the relay the normals face (orients the virtual relay).
    pub fn viewpoint(&self) -> DVec3 {
        let n = self.sensor_grid.points.len() as f64;
        let centre = self.sensor_grid.points.iter().fold(DVec3::ZERO, |a, &p| a + p) / n;
        let normal = self.sensor_grid.normals.iter().fold(DVec3::ZERO, |a, &p| a + p) / n;
        centre + normal
    }
}

/// The most a correction for pile-up and dead time may raise a count, as a fraction:
/// a quarter, which Coates' correction alone reaches where one pulse in five has
/// already been taken (the TDC flags pile-up at one in twenty).
const MAX_CORRECTION: f32 = 0.25;

/// Values of this size or above say nothing about whether they were counted: every
/// such value is within [`MAX_CORRECTION`] above some whole number.
const SMALL_COUNT: f32 = 4.0;

/// How many small values (positive, under [`SMALL_COUNT`]) a capture of corrected
/// counts must hold for the reader to read it as counts.
const MIN_SMALL_COUNTS: usize = 32;

/// What a capture's values say of whether they are detected photons, read from the
/// values themselves (a file's `scene_info` may say nothing, or be wrong).
///
/// Counted photons are whole numbers. A counter's histograms with pile-up and dead
/// time undone (Periscope's own export, `tdc.pile-up-correction`) are not, but each
/// corrected value is its count raised by a factor from 1 to a little above it
/// (Coates' correction never lowers a count): no value lies between 0 and 1, and the
/// small ones sit just above whole numbers, in [n, n·(1 + [`MAX_CORRECTION`])]. A
/// render or a processed capture holds values anywhere, and so fails one test or the
/// other; one whose every value is large shows neither, and is not read as counts.
#[derive(Debug, Clone, Copy)]
struct CountEvidence {
    whole: bool,
    corrected: bool,
    small: usize,
}

impl Default for CountEvidence {
    fn default() -> Self {
        CountEvidence {
            whole: true,
            corrected: true,
            small: 0,
        }
    }
}

impl CountEvidence {
    fn see(&mut self, v: f32) {
        self.whole &= v >= 0.0 && v.fract() == 0.0;
        if v == 0.0 {
            return;
        }
        if v < SMALL_COUNT {
            self.small += 1;
        }
        self.corrected &= v >= 1.0 && (v >= SMALL_COUNT || v <= v.floor() * (1.0 + MAX_CORRECTION));
    }

    fn photon_counts(&self) -> bool {
        self.whole || (self.corrected && self.small >= MIN_SMALL_COUNTS)
    }
}

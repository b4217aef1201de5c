//! Measured (or synthesised) transients in hidden path length.
//!
//! A transient set holds, per illumination/detection pair, the two relay points with
//! their outward normals and a histogram over hidden path length ℓ (first and last
//! legs and the system delay already removed). Bin `b` covers
//! `[start + b·width, start + (b+1)·width)`, in metres, the y-tal convention.
use std::ops::Range;

use glam::DVec3;

use crate::volume::VolumeGrid;

/// Speed of light in vacuum, m/s.
pub const C0: f64 = 299_792_458.0;

/// The histogram axis in hidden path length.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct TimeAxis {
    /// Path length at the start of bin 0, metres.
    pub start: f64,
    /// Bin width in path length, metres (`c0 · bin width in seconds`).
    pub width: f64,
    /// Number of bins.
    pub bins: usize,
}

impl TimeAxis {
    /// An axis from a TDC bin width in seconds.
    pub fn from_seconds(start: f64, bin_width_s: f64, bins: usize) -> Self {
        Self {
            start,
            width: bin_width_s * C0,
            bins,
        }
    }

    /// Path length at the lower edge of bin `b` (any integer, also outside the axis).
    pub fn edge(&self, b: isize) -> f64 {
        self.start + b as f64 * self.width
    }

    /// Path length at the end of the last bin.
    pub fn end(&self) -> f64 {
        self.edge(self.bins as isize)
    }

    /// The total-path axis of a TDC histogram whose first bin starts `offset_s` after
    /// the laser pulse, with bins `bin_width_s` wide: the path light travels in that
    /// time, less the system delay (cables, electronics), metres. The hidden path of a
    /// pair is this less its two legs (laser to illumination point, detection point to
    /// SPAD).
    pub fn of_tdc(offset_s: f64, bin_width_s: f64, bins: usize, system_delay_s: f64) -> Self {
        Self {
            start: C0 * (offset_s - system_delay_s),
            width: C0 * bin_width_s,
            bins,
        }
    }

    /// Path length at the centre of bin `b`.
    pub fn centre(&self, b: f64) -> f64 {
        self.start + (b + 0.5) * self.width
    }

    fn validate(&self) -> Result<(), TransientError> {
        if !(self.start.is_finite() && self.width.is_finite() && self.width > 0.0 && self.bins > 0) {
            return Err(TransientError::Axis(*self));
        }
        Ok(())
    }
}

/// One illumination/detection pair on the relay surface.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Pair {
    /// Illumination point, metres.
    pub xi: DVec3,
    /// Unit outward normal at the illumination point (towards the hidden scene).
    pub ni: DVec3,
    /// Detection point, metres.
    pub xd: DVec3,
    /// Unit outward normal at the detection point.
    pub nd: DVec3,
}

impl Pair {
    /// A confocal pair: illumination and detection at the same point.
    pub fn confocal(x: DVec3, n: DVec3) -> Self {
        Self {
            xi: x,
            ni: n,
            xd: x,
            nd: n,
        }
    }

    fn validate(&self) -> Result<(), &'static str> {
        let finite = [self.xi, self.ni, self.xd, self.nd].iter().all(|v| v.is_finite());
        if !finite {
            return Err("a point or normal is not finite");
        }
        for n in [self.ni, self.nd] {
            if (n.length() - 1.0).abs() > 1e-6 {
                return Err("a normal is not of unit length");
            }
        }
        Ok(())
    }
}

/// Why transients were rejected.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TransientError {
    /// The axis has no bins, a non-positive width or a non-finite start.
    #[error("invalid time axis {0:?}: it needs at least one bin, a positive bin width and a finite start")]
    Axis(TimeAxis),
    /// A histogram has the wrong number of bins.
    #[error("pair {index}: the histogram has {got} bins but the set's axis has {expected}")]
    Length {
        /// Index the pair would have had.
        index: usize,
        /// Bins given.
        got: usize,
        /// Bins expected.
        expected: usize,
    },
    /// No hidden-path window fits the pairs, the volume and the bin width.
    #[error("{0}")]
    Window(String),
    /// A pair or its histogram holds a bad value.
    #[error("pair {index}: {reason}")]
    Value {
        /// Index the pair would have had.
        index: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

/// Most bins a transient on the hidden-path axis may have (at 4 ps bins, 1.3 km of
/// path): beyond this a capture's geometry or bin width is wrong, not large.
pub const MAX_AXIS_BINS: usize = 1 << 20;

/// Rebins values whose bin k covers path lengths [start + k·width, start + (k+1)·width)
/// (metres) onto `axis`, splitting each bin over the axis bins it overlaps so the total
/// inside the axis is preserved (area-exact). Bins outside the axis are dropped.
pub fn rebin_path(
    values: impl IntoIterator<Item = f32>,
    start: f64,
    width: f64,
    axis: &TimeAxis,
) -> Vec<f32> {
    let mut out = vec![0.0f32; axis.bins];
    let shift = (start - axis.start) / axis.width;
    let scale = width / axis.width;
    if !(shift.is_finite() && scale.is_finite() && scale > 0.0) {
        // No overlap can be computed: nothing lands on the axis.
        return out;
    }
    for (k, c) in values.into_iter().enumerate() {
        if c == 0.0 {
            continue;
        }
        let lo = shift + k as f64 * scale;
        let hi = lo + scale;
        // Bins wholly outside the axis are skipped before any index is formed, so
        // far-off starts (hostile files) neither overflow nor loop.
        if !(hi > 0.0 && lo < axis.bins as f64) {
            continue;
        }
        let (first, last) = (lo.floor() as isize, (hi.ceil() as isize).saturating_sub(1));
        for j in first.max(0)..=last.min(axis.bins as isize - 1) {
            let overlap = (hi.min(j as f64 + 1.0) - lo.max(j as f64)).max(0.0);
            out[j as usize] += (f64::from(c) * overlap / scale) as f32;
        }
    }
    out
}

/// `axis` without the bins that lie outside `measured`, the hidden path lengths
/// `[from, to]` (metres) that some transient of a capture actually recorded. A hidden
/// axis ([`hidden_axis`]) spans every path the volume can produce; where the capture's
/// time window stops short of that (a volume deeper or wider than the recording
/// reaches), the bins beyond hold zeros that were never measured, and a fit would read
/// them as "no light here". The bins kept are those wholly inside `measured`, on the
/// same grid (`start + k·width`). An error when none is: the capture does not reach
/// the volume at all.
/// `needed` is what the volume's paths span ([`paths_needed`]), for the message.
pub fn clip_to_measured(
    axis: &TimeAxis,
    measured: (f64, f64),
    needed: (f64, f64),
) -> Result<TimeAxis, TransientError> {
    let (from, to) = measured;
    let Some((first, end)) = bins_within(axis, measured) else {
        // Hidden paths that end before they start were made so by the legs taken
        // out: the laser's and sensor's origins (y-tal `laser_xyz`, `sensor_xyz`), most
        // often in other units than the relay's, not the time window.
        let legs = if to <= 0.0 {
            " (every recorded path is negative once the legs from the laser and to the sensor are taken \
             out: check the laser's and the sensor's origins, such as y-tal's `laser_xyz` and `sensor_xyz`, \
             are in the relay's units, metres)"
        } else {
            ""
        };
        return Err(TransientError::Window(format!(
            "the capture recorded hidden path lengths {from:.3} to {to:.3} m, which do not reach the \
             {:.3} to {:.3} m the volume's paths need{legs}: check the capture's time window (t_start, \
             delta_t) or give a [volume] the recording covers",
            needed.0, needed.1
        )));
    };
    Ok(TimeAxis {
        start: axis.start + first as f64 * axis.width,
        width: axis.width,
        bins: end - first,
    })
}

/// The bins of `axis` wholly inside `measured`, the path lengths `[from, to]`, as
/// `(first, end)`; `None` when there are none. A thousandth of a bin of slack, so an
/// edge that falls on a bin boundary up to rounding keeps that bin.
pub fn bins_within(axis: &TimeAxis, measured: (f64, f64)) -> Option<(usize, usize)> {
    let (from, to) = measured;
    let slack = 1e-3;
    let first = ((from - axis.start) / axis.width - slack).ceil().max(0.0);
    let end = ((to - axis.start) / axis.width + slack)
        .floor()
        .min(axis.bins as f64);
    (from.is_finite() && to.is_finite() && first.is_finite() && end.is_finite() && end > first)
        .then_some((first as usize, end as usize))
}

/// Most a point-source laser's falloff may vary across a capture's illumination
/// points ([`TransientSet::compensate_laser_falloff`]): 10⁴ takes the laser from 1 cm
/// to 1 m of the relay at normal incidence, or cos θ from 1 to 0.01.
pub const MAX_FALLOFF_SPAN: f64 = 1e4;

/// The shortest and longest hidden path of `pair` through `volume`'s box: each leg at
/// least its point's distance to the box (a lower bound on the shortest), and the
/// longest to a corner.
pub fn path_range(pair: &Pair, volume: &VolumeGrid) -> (f64, f64) {
    let (lo, hi) = (volume.min(), volume.max());
    let mut far = 0.0f64;
    for c in 0..8 {
        let q = DVec3::new(
            if c & 1 == 0 { lo.x } else { hi.x },
            if c & 2 == 0 { lo.y } else { hi.y },
            if c & 4 == 0 { lo.z } else { hi.z },
        );
        far = far.max(q.distance(pair.xi) + q.distance(pair.xd));
    }
    let clamp = |x: DVec3| x.clamp(lo, hi);
    (
        clamp(pair.xi).distance(pair.xi) + clamp(pair.xd).distance(pair.xd),
        far,
    )
}

/// The shortest and longest hidden path any of `pairs` can have through `volume`
/// ([`path_range`] over the pairs): what a capture must record for the volume. The
/// axis of [`hidden_axis`] spans it with a few bins to spare on either side.
pub fn paths_needed(pairs: &[Pair], volume: &VolumeGrid) -> (f64, f64) {
    let (mut near, mut far) = (f64::INFINITY, 0.0f64);
    for p in pairs {
        let (n, f) = path_range(p, volume);
        near = near.min(n);
        far = far.max(f);
    }
    (near.max(0.0), far)
}

/// The hidden-path axis all pairs are rebinned to: the TDC's bin width, spanning the
/// shortest to the longest hidden path any pair can have to the reconstruction volume.
pub fn hidden_axis(pairs: &[Pair], volume: &VolumeGrid, bin_width: f64) -> Result<TimeAxis, TransientError> {
    let width = C0 * bin_width;
    if !(width.is_finite() && width > 0.0) {
        return Err(TransientError::Window(format!(
            "the bin width {bin_width} s is not a positive time"
        )));
    }
    let (near, far) = paths_needed(pairs, volume);
    let start = ((near / width).floor() - 4.0).max(0.0) * width;
    // In f64 first: hostile geometry (a tiny bin width, points far away) must be
    // refused, not wrapped or allocated.
    let bins = ((far - start) / width).ceil() + 4.0;
    if !(bins.is_finite() && start.is_finite()) || bins > MAX_AXIS_BINS as f64 {
        return Err(TransientError::Window(format!(
            "the hidden paths span {:.3e} m, {bins:.3e} bins of {width:.3e} m: more than the {MAX_AXIS_BINS} \
             bins a transient may have; check the bin width, the relay points and the volume",
            far - start
        )));
    }
    Ok(TimeAxis {
        start,
        width,
        bins: (bins as usize).max(8),
    })
}

/// Transients on a common time axis, stored contiguously for fast batched access.
#[derive(Clone, Debug)]
pub struct TransientSet {
    axis: TimeAxis,
    pairs: Vec<Pair>,
    counts: Vec<f32>,
    weights: Vec<f32>,
    /// Each transient's known gain in the model (a point-source laser's falloff,
    /// [`TransientSet::compensate_laser_falloff`]): its counts are `gain` times what a
    /// transient at gain 1 would hold. All 1 unless set.
    gains: Vec<f32>,
    /// Counts and bins read where no light from the scene can arrive (before the
    /// transients were cut to the volume's paths): the ambient level's evidence.
    ambient: (f64, usize),
    photon_counts: bool,
    /// Each transient's recorded bins, `[first, end)` on the axis
    /// ([`TransientSet::recorded`]): the whole axis unless
    /// [`TransientSet::limit_recorded`] narrowed it.
    recorded: Vec<[u32; 2]>,
    /// Transients the reader left out because they held no count on the axis
    /// ([`TransientSet::note_left_out_empty`]).
    left_out_empty: usize,
}

impl TransientSet {
    /// An empty set on `axis`.
    pub fn new(axis: TimeAxis) -> Result<Self, TransientError> {
        axis.validate()?;
        Ok(Self {
            axis,
            pairs: Vec::new(),
            counts: Vec::new(),
            weights: Vec::new(),
            gains: Vec::new(),
            ambient: (0.0, 0),
            photon_counts: false,
            recorded: Vec::new(),
            left_out_empty: 0,
        })
    }

    /// Records that the reader left `n` more transients out because they held no
    /// count on the axis: a solver that needs the capture's layout (a confocal grid)
    /// says so when what is left is too little to find it.
    pub fn note_left_out_empty(&mut self, n: usize) {
        self.left_out_empty += n;
    }

    /// Transients the reader left out as empty on the axis.
    pub fn left_out_empty(&self) -> usize {
        self.left_out_empty
    }

    /// Marks the histograms as detected photons (counts, rebinned or corrected for
    /// pile-up perhaps, but on the scale of photons), so noise follows Poisson
    /// statistics: solvers then derive their regularisation from the counts
    /// ([`crate::solver::default_snr`]). Unmarked sets are taken as noise-free
    /// (rendered or processed transients).
    pub fn mark_photon_counts(&mut self) {
        self.photon_counts = true;
    }

    /// Whether the histograms are detected photons ([`Self::mark_photon_counts`]).
    pub fn is_photon_counts(&self) -> bool {
        self.photon_counts
    }

    /// Appends one transient with weight 1.
    pub fn push(&mut self, pair: Pair, histogram: &[f32]) -> Result<(), TransientError> {
        self.push_weighted(pair, histogram, 1.0)
    }

    /// Appends one transient with a loss weight (≥ 0, finite).
    pub fn push_weighted(
        &mut self,
        pair: Pair,
        histogram: &[f32],
        weight: f32,
    ) -> Result<(), TransientError> {
        let index = self.pairs.len();
        if histogram.len() != self.axis.bins {
            return Err(TransientError::Length {
                index,
                got: histogram.len(),
                expected: self.axis.bins,
            });
        }
        pair.validate()
            .map_err(|reason| TransientError::Value { index, reason })?;
        if histogram.iter().any(|c| !c.is_finite()) {
            return Err(TransientError::Value {
                index,
                reason: "the histogram holds a NaN or infinite count",
            });
        }
        if !(weight.is_finite() && weight >= 0.0) {
            return Err(TransientError::Value {
                index,
                reason: "the weight must be finite and not negative",
            });
        }
        self.pairs.push(pair);
        self.counts.extend_from_slice(histogram);
        self.weights.push(weight);
        self.gains.push(1.0);
        self.recorded.push([0, self.axis.bins as u32]);
        Ok(())
    }

    /// Appends one transient with weight 1 whose model carries a known `gain` (finite and
    /// positive; [`TransientSet::gain`]): the relay's albedo at its two spots, read from the
    /// relay scan ([`crate::relay::RelayAlbedo`]). The counts stay as measured.
    pub fn push_with_gain(&mut self, pair: Pair, histogram: &[f32], gain: f32) -> Result<(), TransientError> {
        if !(gain.is_finite() && gain > 0.0) {
            return Err(TransientError::Value {
                index: self.pairs.len(),
                reason: "the known gain must be finite and positive",
            });
        }
        self.push_weighted(pair, histogram, 1.0)?;
        *self.gains.last_mut().expect("just pushed") = gain;
        Ok(())
    }

    /// Appends every transient of `other`, which must share this set's axis.
    pub fn extend(&mut self, other: &TransientSet) -> Result<(), TransientError> {
        if other.axis != self.axis {
            return Err(TransientError::Length {
                index: self.len(),
                got: other.axis.bins,
                expected: self.axis.bins,
            });
        }
        self.photon_counts = if self.is_empty() {
            other.photon_counts
        } else {
            self.photon_counts && other.photon_counts
        };
        self.pairs.extend_from_slice(&other.pairs);
        self.counts.extend_from_slice(&other.counts);
        self.weights.extend_from_slice(&other.weights);
        self.gains.extend_from_slice(&other.gains);
        self.recorded.extend_from_slice(&other.recorded);
        self.ambient = (self.ambient.0 + other.ambient.0, self.ambient.1 + other.ambient.1);
        Ok(())
    }

    /// The transients at `indices` (in that order, repeats allowed), with their weights,
    /// gains and this set's marking: the pairs an adaptive capture or its replay has revealed.
    ///
    /// # Panics
    /// If an index is out of range.
    pub fn subset(&self, indices: &[usize]) -> TransientSet {
        let bins = self.axis.bins;
        let mut out = TransientSet {
            axis: self.axis,
            pairs: Vec::with_capacity(indices.len()),
            counts: Vec::with_capacity(indices.len() * bins),
            weights: Vec::with_capacity(indices.len()),
            gains: Vec::with_capacity(indices.len()),
            ambient: self.ambient,
            photon_counts: self.photon_counts,
            recorded: Vec::with_capacity(indices.len()),
            left_out_empty: self.left_out_empty,
        };
        for &i in indices {
            out.pairs.push(self.pairs[i]);
            out.counts.extend_from_slice(self.histogram(i));
            out.weights.push(self.weights[i]);
            out.gains.push(self.gains[i]);
            out.recorded.push(self.recorded[i]);
        }
        out
    }

    /// The time axis.
    pub fn axis(&self) -> &TimeAxis {
        &self.axis
    }

    /// Number of transients.
    pub fn len(&self) -> usize {
        self.pairs.len()
    }

    /// Whether the set holds no transient.
    pub fn is_empty(&self) -> bool {
        self.pairs.is_empty()
    }

    /// All pairs.
    pub fn pairs(&self) -> &[Pair] {
        &self.pairs
    }

    /// The histogram of transient `i`.
    pub fn histogram(&self, i: usize) -> &[f32] {
        &self.counts[i * self.axis.bins..(i + 1) * self.axis.bins]
    }

    /// The loss weight of transient `i`.
    pub fn weight(&self, i: usize) -> f32 {
        self.weights[i]
    }

    /// The known gain of transient `i` in the model (1 unless
    /// [`TransientSet::compensate_laser_falloff`] or [`TransientSet::push_with_gain`]
    /// set it): its counts are this times a transient's at gain 1.
    pub fn gain(&self, i: usize) -> f32 {
        self.gains[i]
    }

    /// The bins of transient `i` its recording covers: the whole axis, unless
    /// [`TransientSet::limit_recorded`] narrowed it. Outside them the histogram holds
    /// zeros nobody measured (or, at the edge, a part of a bin), which the fit leaves
    /// out of its data term, its gains and its background.
    pub fn recorded(&self, i: usize) -> Range<usize> {
        let [first, end] = self.recorded[i];
        first as usize..end as usize
    }

    /// Narrows transient `i`'s recorded bins ([`TransientSet::recorded`]) to those
    /// wholly inside `measured`, the hidden path lengths `[from, to]` (metres) its own
    /// recording covers: its time window, less its legs where they differ from pair to
    /// pair. A bin partly inside holds only a part of its counts and is left out too;
    /// none may remain, and such a transient tells the fit nothing. The counts stay as
    /// they are, so the solvers, which read zeros as zeros, see what they saw.
    pub fn limit_recorded(&mut self, i: usize, measured: (f64, f64)) {
        let (first, end) = bins_within(&self.axis, measured).unwrap_or((0, 0));
        let [a, b] = self.recorded[i];
        let a = a.max(first as u32);
        self.recorded[i] = [a, b.min(end as u32).max(a)];
    }

    /// Records `bins` bins holding `counts` in all, read where no light from the scene
    /// can arrive (outside every path through the volume, before the transients were
    /// cut to it): [`TransientSet::ambient`] reads the ambient level from them.
    pub fn add_ambient(&mut self, counts: f64, bins: usize) {
        self.ambient = (self.ambient.0 + counts, self.ambient.1 + bins);
    }

    /// The mean count of the bins [`TransientSet::add_ambient`] recorded, and how many
    /// there were; `None` without any.
    pub fn ambient(&self) -> Option<(f64, usize)> {
        (self.ambient.1 > 0).then(|| (self.ambient.0 / self.ambient.1 as f64, self.ambient.1))
    }

    /// Whether any transient has a known gain other than 1.
    pub fn has_gains(&self) -> bool {
        self.gains.iter().any(|&g| g != 1.0)
    }

    /// Transient `i` as it would be at gain 1: its counts over its known gain, for the
    /// methods that take the counts as they are (the solvers). Not Poisson counts any
    /// more where the gain is not 1: a likelihood puts the gain in its model instead.
    pub fn measured(&self, i: usize) -> std::borrow::Cow<'_, [f32]> {
        let g = self.gains[i];
        if g == 1.0 {
            std::borrow::Cow::Borrowed(self.histogram(i))
        } else {
            std::borrow::Cow::Owned(self.histogram(i).iter().map(|&c| c / g).collect())
        }
    }

    /// Accounts for the falloff of a laser that lights the relay as a point source at
    /// `laser` (metres): such a source gives illumination point `x` with normal `n` an
    /// irradiance proportional to `cos θ / d²` (d = |laser − x|, θ the angle of
    /// incidence), so every histogram carries that factor. Transient `i`'s known gain
    /// becomes its factor over the mean factor of the set (so the overall scale is
    /// kept): the counts stay as measured, Poisson with their one ambient background,
    /// and the gain goes into the model of a likelihood fit (3D-GTR renders `gain ×
    /// scene + background`), while the solvers take the counts over the gain
    /// ([`TransientSet::measured`]): y-tal's `tal.reconstruct.compensate_laser_cos_dsqr`
    /// (which divides by the raw factor). A collimated laser puts the same power into
    /// its spot wherever it points and needs none of this (docs/ytal.md, "Laser
    /// falloff").
    ///
    /// Returns the smallest and largest multiplier (1 / gain) it implies for the counts.
    /// Refused, with the set unchanged, when the laser is not in front of an illumination point
    /// (cos θ ≤ 0.01, a grazing angle whose factor would amplify the counts a
    /// hundredfold) or coincides with one, when the factors span more than
    /// [`MAX_FALLOFF_SPAN`], or when a multiplied count would not fit an `f32`.
    pub fn compensate_laser_falloff(&mut self, laser: DVec3) -> Result<(f64, f64), TransientError> {
        let mut factors = Vec::with_capacity(self.len());
        for (index, p) in self.pairs.iter().enumerate() {
            let to_laser = laser - p.xi;
            let d = to_laser.length();
            let cos = if d > 0.0 { to_laser.dot(p.ni) / d } else { f64::NAN };
            let factor = cos / (d * d);
            if !(laser.is_finite() && cos > 0.01 && factor.is_finite() && factor > 0.0) {
                return Err(TransientError::Value {
                    index,
                    reason: "the laser does not light this illumination point from in front of the relay \
                             (cos θ at most 0.01, or the laser sits on the point), so its falloff cannot be \
                             compensated",
                });
            }
            factors.push(factor);
        }
        let Some(&top) = factors.iter().max_by(|a, b| a.total_cmp(b)) else {
            return Ok((1.0, 1.0));
        };
        // Relative to the largest factor, so neither the mean nor a multiplier overflows.
        let relative: Vec<f64> = factors.iter().map(|f| f / top).collect();
        let mean = relative.iter().sum::<f64>() / relative.len() as f64;
        let multipliers: Vec<f64> = relative.iter().map(|r| mean / r).collect();
        let (lo, hi) = multipliers
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(l, h), &m| (l.min(m), h.max(m)));
        let bins = self.axis.bins;
        let fits = self.counts.chunks_exact(bins).zip(&multipliers).all(|(h, m)| {
            let peak = h.iter().fold(0.0f64, |a, v| a.max(f64::from(v.abs())));
            (peak * m).is_finite() && peak * m <= f64::from(f32::MAX)
        });
        if !(hi / lo <= MAX_FALLOFF_SPAN && fits) {
            return Err(TransientError::Window(format!(
                "the laser's falloff (cos θ / d²) varies {:.3e}-fold across the illumination points, more than \
                 the {MAX_FALLOFF_SPAN:e} a laser aimed at a relay can give: check the laser origin and the relay \
                 points",
                hi / lo
            )));
        }
        for (g, m) in self.gains.iter_mut().zip(&multipliers) {
            *g = (f64::from(*g) / m) as f32;
        }
        Ok((lo, hi))
    }

    /// Sum of all counts, weighted.
    pub fn total_counts(&self) -> f64 {
        (0..self.len())
            .map(|i| self.weight(i) as f64 * self.histogram(i).iter().map(|&c| c as f64).sum::<f64>())
            .sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Each transient's recorded bins start as the whole axis; `limit_recorded` keeps
    /// those wholly inside its window (an edge inside a bin drops that bin), only
    /// narrows, may leave none, and leaves the counts as they were; `subset` and
    /// `extend` carry the ranges with their transients.
    #[test]
    fn each_transient_keeps_the_bins_its_own_window_recorded() {
        let axis = TimeAxis {
            start: 1.0,
            width: 0.01,
            bins: 100,
        };
        let mut set = TransientSet::new(axis).unwrap();
        let h: Vec<f32> = (0..100).map(|b| b as f32).collect();
        for _ in 0..4 {
            set.push(Pair::confocal(DVec3::ZERO, DVec3::Z), &h).unwrap();
        }
        assert_eq!(set.recorded(0), 0..100);
        set.limit_recorded(0, (1.2, 1.5));
        set.limit_recorded(1, (1.2012, 2.5));
        set.limit_recorded(2, (0.0, 1.2));
        set.limit_recorded(2, (1.1, 3.0));
        set.limit_recorded(3, (2.5, 3.0));
        assert_eq!(set.recorded(0), 20..50);
        assert_eq!(set.recorded(1), 21..100);
        assert_eq!(set.recorded(2), 10..20, "a second window narrows the first");
        assert!(set.recorded(3).is_empty());
        assert_eq!(set.histogram(0), &h[..], "the counts stay");
        let sub = set.subset(&[3, 0]);
        assert_eq!((sub.recorded(0), sub.recorded(1)), (set.recorded(3), 20..50));
        let mut more = TransientSet::new(axis).unwrap();
        more.push(Pair::confocal(DVec3::ZERO, DVec3::Z), &h).unwrap();
        more.extend(&sub).unwrap();
        assert_eq!([more.recorded(0), more.recorded(2)], [0..100, 20..50]);
    }

    /// The bins wholly inside the recording are kept, on the axis's own grid; an axis
    /// the recording covers comes back unchanged, and one it misses is refused.
    #[test]
    fn clip_to_measured_keeps_the_recorded_bins() {
        let axis = TimeAxis {
            start: 0.37,
            width: 0.005,
            bins: 624,
        };
        let tail = clip_to_measured(&axis, (0.0, 2.56), (0.0, 1.0)).unwrap();
        assert_eq!((tail.start, tail.bins), (0.37, 438), "{tail:?}");
        assert!((tail.end() - 2.56).abs() < 1e-9, "{tail:?}");
        let both = clip_to_measured(&axis, (1.0, 1.5), (0.0, 1.0)).unwrap();
        assert!((both.start - 1.0).abs() < 1e-12 && both.bins == 100, "{both:?}");
        // An edge inside a bin drops that bin.
        let inside = clip_to_measured(&axis, (1.0012, 1.4987), (0.0, 1.0)).unwrap();
        assert!(
            (inside.start - 1.005).abs() < 1e-12 && inside.bins == 98,
            "{inside:?}"
        );
        assert_eq!(clip_to_measured(&axis, (-1.0, 10.0), (0.0, 1.0)).unwrap(), axis);
        // The message names what the volume's paths need, not the axis's padding.
        for missed in [(5.0, 6.0), (0.0, 0.3), (1.0, 1.003), (f64::NAN, 2.0)] {
            let e = clip_to_measured(&axis, missed, (0.39, 3.47))
                .unwrap_err()
                .to_string();
            assert!(e.contains("do not reach the 0.390 to 3.470 m"), "{missed:?}: {e}");
            assert!(!e.contains("sensor_xyz"), "{e}");
        }
        // Every path negative once the legs are out: the origins' units are named.
        let e = clip_to_measured(&axis, (-2998.0, -2997.0), (0.39, 3.47))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("`laser_xyz` and `sensor_xyz`") && e.contains("metres"),
            "{e}"
        );
    }

    fn axis() -> TimeAxis {
        TimeAxis {
            start: 0.5,
            width: 0.01,
            bins: 4,
        }
    }

    #[test]
    fn rebinning_preserves_counts_and_shifts_by_the_legs() {
        let mut counts = vec![0.0f32; 64];
        counts[20] = 1000.0;
        let tdc = TimeAxis::of_tdc(0.0, 16e-12, 64, 0.0);
        let axis = TimeAxis {
            start: 0.0,
            width: tdc.width,
            bins: 64,
        };
        // Legs of exactly 10.25 bins: TDC bin 20 covers hidden bins [9.75, 10.75),
        // a quarter in bin 9 and three quarters in bin 10.
        let legs = 10.25 * axis.width;
        let h = rebin_path(counts, tdc.start - legs, tdc.width, &axis);
        let total: f32 = h.iter().sum();
        assert!((total - 1000.0).abs() < 1e-3, "{total}");
        assert!(
            (h[9] - 250.0).abs() < 1e-3 && (h[10] - 750.0).abs() < 1e-3,
            "{:?}",
            &h[8..12]
        );
    }

    #[test]
    fn a_tdc_axis_starts_at_the_path_after_the_system_delay() {
        // 10 ns after the pulse with a 2.5 ns system delay: 7.5 ns of flight.
        let a = TimeAxis::of_tdc(10e-9, 4e-12, 100, 2.5e-9);
        assert!((a.start - C0 * 7.5e-9).abs() < 1e-12, "{a:?}");
        assert!((a.width - C0 * 4e-12).abs() < 1e-15);
        assert!((a.centre(0.0) - (a.start + 0.5 * a.width)).abs() < 1e-12);
    }

    #[test]
    fn rejects_bad_input_with_the_pair_index() {
        let mut set = TransientSet::new(axis()).unwrap();
        let pair = Pair::confocal(DVec3::ZERO, DVec3::Z);
        set.push(pair, &[0.0; 4]).unwrap();
        let err = set.push(pair, &[0.0; 3]).unwrap_err();
        assert!(err.to_string().starts_with("pair 1:"), "{err}");
        assert!(set.push(pair, &[f32::NAN, 0.0, 0.0, 0.0]).is_err());
        assert!(
            set.push(Pair::confocal(DVec3::ZERO, DVec3::ONE), &[0.0; 4])
                .is_err()
        );
        assert!(set.push_weighted(pair, &[0.0; 4], -1.0).is_err());
        assert_eq!(set.len(), 1, "rejected transients are not stored");
    }

    #[test]
    fn a_point_source_lasers_falloff_becomes_each_transients_gain_around_the_mean() {
        // Laser 1 m above the origin. The point under it: d = 1, cos θ = 1, factor 1.
        // The point 1 m to the side: d = √2, cos θ = 1/√2, factor 1/(2√2).
        let mut set = TransientSet::new(axis()).unwrap();
        let side = 1.0 / (2.0 * 2f64.sqrt());
        set.push(Pair::confocal(DVec3::ZERO, DVec3::Z), &[0.0, 4.0, 2.0, 0.0])
            .unwrap();
        set.push(
            Pair::confocal(DVec3::X, DVec3::Z),
            &[0.0, (4.0 * side) as f32, (2.0 * side) as f32, 0.0],
        )
        .unwrap();
        let (lo, hi) = set.compensate_laser_falloff(DVec3::Z).unwrap();
        let mean = 0.5 * (1.0 + side);
        assert!(
            (lo - mean).abs() < 1e-12 && (hi - mean / side).abs() < 1e-12,
            "{lo} {hi}"
        );
        // The counts stay as measured; the falloff is each transient's gain in the model
        // (relative to the mean factor), and at gain 1 both carry the same transient, at
        // the mean factor's scale.
        assert_eq!(set.histogram(0), &[0.0, 4.0, 2.0, 0.0]);
        assert!(
            (f64::from(set.gain(0)) - 1.0 / mean).abs() < 1e-6,
            "{}",
            set.gain(0)
        );
        assert!(
            (f64::from(set.gain(1)) - side / mean).abs() < 1e-6,
            "{}",
            set.gain(1)
        );
        for i in 0..2 {
            let h = set.measured(i);
            assert!((f64::from(h[1]) - 4.0 * mean).abs() < 1e-5, "{i}: {h:?}");
            assert!((f64::from(h[2]) - 2.0 * mean).abs() < 1e-5, "{i}: {h:?}");
        }
        // A subset keeps its transients' gains.
        assert_eq!(set.subset(&[1]).gain(0), set.gain(1));
        // A laser behind the relay, or grazing it, is refused and changes nothing.
        let before = set.histogram(1).to_vec();
        let gain = set.gain(1);
        let err = set
            .compensate_laser_falloff(DVec3::new(0.0, 0.0, -1.0))
            .unwrap_err();
        assert!(err.to_string().starts_with("pair 0:"), "{err}");
        assert!(set.compensate_laser_falloff(DVec3::new(1e3, 0.0, 1.0)).is_err());
        // Hostile geometry: a laser 11 mm above one point and a metre from the other
        // (factors 8,264 and 0.011), and counts that would overflow once multiplied.
        let err = set
            .compensate_laser_falloff(DVec3::new(0.0, 0.0, 0.011))
            .unwrap_err();
        assert!(err.to_string().contains("varies"), "{err}");
        let mut huge = TransientSet::new(axis()).unwrap();
        huge.push(Pair::confocal(DVec3::ZERO, DVec3::Z), &[f32::MAX; 4])
            .unwrap();
        huge.push(Pair::confocal(DVec3::X, DVec3::Z), &[f32::MAX; 4])
            .unwrap();
        assert!(huge.compensate_laser_falloff(DVec3::Z).is_err());
        assert_eq!((set.histogram(1), set.gain(1)), (&before[..], gain));
        assert!(huge.histogram(0).iter().all(|v| *v == f32::MAX));
        assert!(!huge.has_gains());
    }

    #[test]
    fn rejects_degenerate_axes() {
        for bad in [
            TimeAxis { bins: 0, ..axis() },
            TimeAxis { width: 0.0, ..axis() },
            TimeAxis {
                start: f64::NAN,
                ..axis()
            },
        ] {
            assert!(TransientSet::new(bad).is_err());
        }
    }

    #[test]
    fn edges_follow_the_ytal_convention() {
        let a = axis();
        assert_eq!(a.edge(0), 0.5);
        assert!((a.edge(2) - 0.52).abs() < 1e-15);
        assert!((a.end() - 0.54).abs() < 1e-15);
    }
}

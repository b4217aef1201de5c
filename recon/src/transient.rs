//! Measured (or synthesised) transients in hidden path length.
//!
//! A transient set holds, per illumination/detection pair, the two relay points with
//! their outward normals and a histogram over hidden path length ℓ (first and last
//! legs and the system delay already removed). Bin `b` covers
//! `[start + b·width, start + (b+1)·width)`, in metres, the y-tal convention.
use glam::DVec3;

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
    /// A pair or its histogram holds a bad value.
    #[error("pair {index}: {reason}")]
    Value {
        /// Index the pair would have had.
        index: usize,
        /// What is wrong.
        reason: &'static str,
    },
}

/// Transients on a common time axis, stored contiguously for fast batched access.
#[derive(Clone, Debug)]
pub struct TransientSet {
    axis: TimeAxis,
    pairs: Vec<Pair>,
    counts: Vec<f32>,
    weights: Vec<f32>,
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
        })
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
        self.pairs.extend_from_slice(&other.pairs);
        self.counts.extend_from_slice(&other.counts);
        self.weights.extend_from_slice(&other.weights);
        Ok(())
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

    fn axis() -> TimeAxis {
        TimeAxis {
            start: 0.5,
            width: 0.01,
            bins: 4,
        }
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

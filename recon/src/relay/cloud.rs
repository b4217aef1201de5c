//! Thresholds on the first-bounce point cloud and removal of isolated points.
use std::num::NonZero;

use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::{GeometryError, check_finite};

/// Which LOS points count as relay: a window on the depth along the SPAD ray (the
/// distance from the SPAD galvo origin) and a floor on the first-bounce intensity.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Thresholds {
    /// Nearest accepted depth, metres.
    pub min_depth: f64,
    /// Farthest accepted depth, metres.
    pub max_depth: f64,
    /// Smallest accepted intensity (same unit as the intensities passed in).
    pub min_intensity: f64,
}

impl Default for Thresholds {
    fn default() -> Self {
        Self {
            min_depth: 0.0,
            max_depth: f64::INFINITY,
            min_intensity: 0.0,
        }
    }
}

impl Thresholds {
    /// Whether a point at `depth` with `intensity` passes. NaN never passes.
    pub fn accepts(&self, depth: f64, intensity: f64) -> bool {
        depth >= self.min_depth && depth <= self.max_depth && intensity >= self.min_intensity
    }

    /// Indices of the points that pass, seen from `origin`.
    pub fn select(&self, origin: DVec3, points: &[DVec3], intensities: &[f64]) -> Vec<usize> {
        points
            .iter()
            .zip(intensities)
            .enumerate()
            .filter(|(_, (p, i))| p.is_finite() && self.accepts(p.distance(origin), **i))
            .map(|(k, _)| k)
            .collect()
    }
}

/// Statistical outlier removal: a point is isolated when its mean distance to its `k`
/// nearest neighbours exceeds the mean of that statistic over the cloud by more than
/// `std_ratio` standard deviations. Returns a keep-mask.
pub fn reject_isolated(points: &[DVec3], k: usize, std_ratio: f64) -> Result<Vec<bool>, GeometryError> {
    check_finite(points)?;
    if k == 0 {
        return Err(GeometryError::OutOfRange {
            name: "neighbours",
            value: k.to_string(),
            expected: "at least 1",
        });
    }
    if !(std_ratio.is_finite() && std_ratio > 0.0) {
        return Err(GeometryError::OutOfRange {
            name: "std_ratio",
            value: std_ratio.to_string(),
            expected: "a positive number of standard deviations",
        });
    }
    if points.len() <= k {
        return Err(GeometryError::TooFewPoints {
            points: points.len(),
            needed: k + 1,
        });
    }
    let coords: Vec<[f64; 3]> = points.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&coords);
    let qty = NonZero::new(k + 1).expect("k + 1 > 0");
    let mean_dist: Vec<f64> = coords
        .par_iter()
        .map(|q| {
            let found = tree.nearest_n::<SquaredEuclidean>(q, qty);
            // The first hit is the point itself (distance 0).
            found.iter().skip(1).map(|n| n.distance.sqrt()).sum::<f64>() / k as f64
        })
        .collect();
    let n = mean_dist.len() as f64;
    let mean = mean_dist.iter().sum::<f64>() / n;
    let std = (mean_dist.iter().map(|d| (d - mean).powi(2)).sum::<f64>() / n).sqrt();
    let limit = mean + std_ratio * std;
    Ok(mean_dist.iter().map(|&d| d <= limit).collect())
}

//! Per-point normals by principal component analysis of the k nearest neighbours.
//!
//! The normal is the eigenvector of the neighbourhood covariance with the smallest
//! eigenvalue, flipped to face the instrument (`n·(viewpoint − x) > 0`): the hidden
//! scene lies in front of the relay, on the instrument's side.
//!
//! PCA alone tilts the normal on curved surfaces wherever the neighbourhood is
//! one-sided (scan borders, holes): the plane it fits is the tangent at the neighbours'
//! centroid, not at the point. So the PCA frame is refined by a least-squares quadric
//! h = a + b·s + c·t + d·s² + e·s·t + f·t² in the frame's coordinates around the point,
//! whose gradient at the point gives the normal. The refinement is used only where the
//! curvature is significant (an F-test of the quadratic terms against a plane): on a
//! flat, noisy scan a quadric would fit the noise, and PCA is the better estimator.
//! With too few or degenerate neighbours the PCA normal stands. A neighbourhood that
//! is (nearly) a line has no defined normal; such points get `None`, never a guess.
use std::num::NonZero;

use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};
use rayon::prelude::*;

use super::{GeometryError, check_finite};
use crate::linalg::{covariance, solve, sym_eigen};

/// A neighbourhood whose second eigenvalue is below this fraction of the largest is
/// treated as a line (no normal): its spread across its main direction under a tenth
/// of its spread along it. A LOS scan whose 16 nearest neighbours lie in one row
/// (64 × 8 points over a square metre, 1 mm of depth noise) spans only the row and
/// the noise, and its normal, the direction across the row, lay in the relay's plane,
/// 90° off, until 2026-12-07 (the ratio was 1e-6, which noise always passes).
const LINE_RATIO: f64 = 1e-2;

/// A neighbourhood spans a plane only where its spread across its main direction is
/// clearly more than its spread out of any plane: the second eigenvalue at least this
/// many times the smallest (a spread √10 ≈ 3.2 times the thickness). Points along a
/// line with noise in every direction have the two alike.
const PLANE_RATIO: f64 = 10.0;

/// F statistic (3 and n − 6 degrees of freedom) above which the quadratic terms count as
/// real curvature rather than noise; noise alone exceeds 30 with probability < 1e-4.
const SIGNIFICANT_CURVATURE: f64 = 30.0;

/// The normal of one point.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceNormal {
    /// Unit normal facing the viewpoint.
    pub normal: DVec3,
    /// Surface variation λ0 / (λ0 + λ1 + λ2): 0 on a plane, up to 1/3 for isotropic
    /// clutter. A quality measure for thresholds.
    pub variation: f64,
}

/// Normals of `points` from their `neighbours` nearest neighbours (the point itself
/// included), oriented toward `viewpoint`. Runs in parallel over points.
pub fn estimate_normals(
    points: &[DVec3],
    neighbours: usize,
    viewpoint: DVec3,
) -> Result<Vec<Option<SurfaceNormal>>, GeometryError> {
    check_finite(points)?;
    if neighbours < 3 {
        return Err(GeometryError::OutOfRange {
            name: "neighbours",
            value: neighbours.to_string(),
            expected: "at least 3 (a plane needs three points)",
        });
    }
    if !viewpoint.is_finite() {
        return Err(GeometryError::OutOfRange {
            name: "viewpoint",
            value: format!("{viewpoint:?}"),
            expected: "a finite position",
        });
    }
    if points.len() < neighbours {
        return Err(GeometryError::TooFewPoints {
            points: points.len(),
            needed: neighbours,
        });
    }
    let coords: Vec<[f64; 3]> = points.iter().map(|p| p.to_array()).collect();
    let tree: ImmutableKdTree<f64, 3> = ImmutableKdTree::new_from_slice(&coords);
    let qty = NonZero::new(neighbours).expect("neighbours ≥ 3");
    Ok(points
        .par_iter()
        .map(|&x| {
            let found = tree.nearest_n::<SquaredEuclidean>(&x.to_array(), qty);
            let hood: Vec<DVec3> = found.iter().map(|n| points[n.item as usize]).collect();
            let centre = hood.iter().copied().sum::<DVec3>() / hood.len() as f64;
            let e = sym_eigen(covariance(hood.iter().map(|p| *p - centre)));
            let total = e.values.iter().sum::<f64>();
            let plane = e.values[1] > LINE_RATIO * e.values[2] && e.values[1] > PLANE_RATIO * e.values[0];
            if !(plane && total > 0.0) {
                return None;
            }
            let mut normal = refine(x, &hood, e.vectors[0], e.vectors[1], e.vectors[2]);
            if normal.dot(viewpoint - x) < 0.0 {
                normal = -normal;
            }
            Some(SurfaceNormal {
                normal,
                variation: (e.values[0].max(0.0) / total).min(1.0),
            })
        })
        .collect())
}

/// The normal at `x` of the quadric fitted to `hood` in the frame (n, t1, t2).
fn refine(x: DVec3, hood: &[DVec3], n: DVec3, t1: DVec3, t2: DVec3) -> DVec3 {
    if hood.len() < 8 {
        return n;
    }
    // Normal equations of the 6-term fit, coordinates scaled by the neighbourhood radius
    // for conditioning.
    let radius = hood.iter().map(|p| p.distance(x)).fold(0.0f64, f64::max);
    if !(radius > 0.0) {
        return n;
    }
    let mut a = [[0.0f64; 6]; 6];
    let mut b = [0.0f64; 6];
    let mut plane_a = [[0.0f64; 3]; 3];
    let mut plane_b = [0.0f64; 3];
    for p in hood {
        let d = (*p - x) / radius;
        let (s, t, h) = (d.dot(t1), d.dot(t2), d.dot(n));
        let basis = [1.0, s, t, s * s, s * t, t * t];
        for i in 0..6 {
            for j in 0..6 {
                a[i][j] += basis[i] * basis[j];
            }
            b[i] += basis[i] * h;
        }
        for i in 0..3 {
            for j in 0..3 {
                plane_a[i][j] += basis[i] * basis[j];
            }
            plane_b[i] += basis[i] * h;
        }
    }
    let Some(c) = solve(a, b, 1e-10) else {
        return n;
    };
    // F-test of the three quadratic terms against the plane h = a + b·s + c·t.
    let Some(p) = solve(plane_a, plane_b, 1e-10) else {
        return n;
    };
    let (mut rss_quad, mut rss_plane) = (0.0, 0.0);
    for q in hood {
        let d = (*q - x) / radius;
        let (s, t, h) = (d.dot(t1), d.dot(t2), d.dot(n));
        let quad = c[0] + c[1] * s + c[2] * t + c[3] * s * s + c[4] * s * t + c[5] * t * t;
        rss_quad += (h - quad).powi(2);
        rss_plane += (h - (p[0] + p[1] * s + p[2] * t)).powi(2);
    }
    let dof = (hood.len() - 6) as f64;
    if !((rss_plane - rss_quad) / 3.0 > SIGNIFICANT_CURVATURE * rss_quad / dof) {
        return n;
    }
    // The surface h(s, t) has gradient (b, c) at the point; its normal is n − b·t1 − c·t2.
    let refined = (n - t1 * c[1] - t2 * c[2]).try_normalize().unwrap_or(n);
    // A quadric that turns the normal more than this within its own neighbourhood is
    // one the points do not pin down: a neighbourhood of one row of a LOS scan and a
    // few points of the next fitted a slope across the rows that turned the plane's
    // normal 90° (until 2026-12-07).
    if refined.dot(n) < MAX_REFINEMENT_COS {
        return n;
    }
    refined
}

/// The cosine of the most the quadric may turn a neighbourhood's plane normal: 30°.
const MAX_REFINEMENT_COS: f64 = 0.866;

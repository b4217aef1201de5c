//! Small dense linear algebra the geometry needs and glam lacks: the eigen
//! decomposition of a symmetric 3×3 matrix (cyclic Jacobi, which stays accurate for
//! the nearly degenerate covariances of flat neighbourhoods) and PCA plane fits.
use glam::{DMat3, DVec3};

/// Eigenvalues in ascending order and the matching unit eigenvectors (columns).
#[derive(Clone, Copy, Debug)]
pub struct SymEigen {
    /// λ0 ≤ λ1 ≤ λ2.
    pub values: [f64; 3],
    /// Eigenvector of `values[k]` is `vectors[k]`.
    pub vectors: [DVec3; 3],
}

/// Eigen decomposition of the symmetric matrix `m` (only its symmetric part is used).
pub fn sym_eigen(m: DMat3) -> SymEigen {
    let mut a = [[0.0f64; 3]; 3];
    for (i, row) in a.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            *v = 0.5 * (m.col(j)[i] + m.col(i)[j]);
        }
    }
    let mut v = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    for _sweep in 0..32 {
        let off = a[0][1].abs() + a[0][2].abs() + a[1][2].abs();
        let scale = a[0][0].abs() + a[1][1].abs() + a[2][2].abs();
        if off <= f64::EPSILON * scale.max(f64::MIN_POSITIVE) {
            break;
        }
        for (p, q) in [(0, 1), (0, 2), (1, 2)] {
            if a[p][q] == 0.0 {
                continue;
            }
            let theta = (a[q][q] - a[p][p]) / (2.0 * a[p][q]);
            let t = theta.signum() / (theta.abs() + (theta * theta + 1.0).sqrt());
            let t = if theta == 0.0 { 1.0 } else { t };
            let c = 1.0 / (t * t + 1.0).sqrt();
            let s = t * c;
            for k in 0..3 {
                let (akp, akq) = (a[k][p], a[k][q]);
                a[k][p] = c * akp - s * akq;
                a[k][q] = s * akp + c * akq;
            }
            for k in 0..3 {
                let (apk, aqk) = (a[p][k], a[q][k]);
                a[p][k] = c * apk - s * aqk;
                a[q][k] = s * apk + c * aqk;
            }
            for row in v.iter_mut() {
                let (vp, vq) = (row[p], row[q]);
                row[p] = c * vp - s * vq;
                row[q] = s * vp + c * vq;
            }
        }
    }
    let mut order = [0usize, 1, 2];
    order.sort_by(|&i, &j| a[i][i].total_cmp(&a[j][j]));
    let column = |k: usize| DVec3::new(v[0][k], v[1][k], v[2][k]).normalize();
    SymEigen {
        values: order.map(|k| a[k][k]),
        vectors: order.map(column),
    }
}

/// A plane fitted to points by PCA.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FittedPlane {
    /// Centroid of the points.
    pub centre: DVec3,
    /// Unit normal (the direction of least variance; sign arbitrary until oriented).
    pub normal: DVec3,
    /// In-plane axis of largest variance.
    pub u: DVec3,
    /// `normal × u`, completing a right-handed frame (u, v, normal).
    pub v: DVec3,
    /// Root-mean-square distance of the points from the plane.
    pub rms: f64,
}

impl FittedPlane {
    /// The same plane in a frame the world fixes rather than the points: its normal
    /// turned to the side of `facing` (kept as fitted if `facing` is zero or in the
    /// plane), `u` along world x projected into the plane (world y where the normal is
    /// within about 26° of x), `v = normal × u`. Seen from the side the normal faces, a
    /// wall facing +z has u along +x and v along +y, and a wall facing −y (ZNLOS's) u
    /// along +x and v along +z. The fitted `u`'s direction and sign come from the
    /// points' spread and from the eigen-solver, so grids laid along it turn and mirror
    /// from one scan of the same relay to the next.
    pub fn world_oriented(&self, facing: DVec3) -> FittedPlane {
        let normal = if self.normal.dot(facing) < 0.0 {
            -self.normal
        } else {
            self.normal
        };
        let hint = if normal.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
        let u = (hint - normal * hint.dot(normal)).normalize();
        FittedPlane {
            centre: self.centre,
            normal,
            u,
            v: normal.cross(u),
            rms: self.rms,
        }
    }
}

/// The spread across a set's main direction must be this many times its spread out of
/// the plane (as variances, the second eigenvalue against the smallest) for the plane
/// to be defined: points along a line with noise fit no plane, where the noise alone
/// would set its tilt. A relay of two backs, its depth a third of its height, has
/// about 10.
const PLANE_SPREAD_RATIO: f64 = 3.0;

/// And at least this fraction of its spread along it (as variances: a strip 1 m long
/// must be 1 cm wide): a line scan's depth noise alone, 1 mm on a metre (1.3e-5),
/// does not make a plane.
const PLANE_ASPECT: f64 = 1e-4;

/// Fits a plane to `points`; `None` for fewer than three points, collinear ones, or
/// ones along a line but for noise: a spread across the line under a hundredth of the
/// spread along it (as variances), or under √3 times the spread out of any plane.
pub fn fit_plane(points: &[DVec3]) -> Option<FittedPlane> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let centre = points.iter().copied().sum::<DVec3>() / n;
    let cov = covariance(points.iter().map(|p| *p - centre)) * (1.0 / n);
    let e = sym_eigen(cov);
    if !(e.values[1] > PLANE_ASPECT * e.values[2].max(f64::MIN_POSITIVE))
        || !(e.values[1] > PLANE_SPREAD_RATIO * e.values[0].max(0.0))
        || !e.values[2].is_finite()
    {
        return None;
    }
    let normal = e.vectors[0];
    let u = e.vectors[2];
    Some(FittedPlane {
        centre,
        normal,
        u,
        v: normal.cross(u),
        rms: e.values[0].max(0.0).sqrt(),
    })
}

/// Σ d dᵀ over the given offsets (not normalised).
pub fn covariance(offsets: impl Iterator<Item = DVec3>) -> DMat3 {
    let mut c = [0.0f64; 6];
    for d in offsets {
        c[0] += d.x * d.x;
        c[1] += d.x * d.y;
        c[2] += d.x * d.z;
        c[3] += d.y * d.y;
        c[4] += d.y * d.z;
        c[5] += d.z * d.z;
    }
    DMat3::from_cols(
        DVec3::new(c[0], c[1], c[2]),
        DVec3::new(c[1], c[3], c[4]),
        DVec3::new(c[2], c[4], c[5]),
    )
}

/// Solves the `N × N` system `a · x = b` by Gaussian elimination with partial pivoting;
/// `None` when a pivot is below `rel_tol` times the largest entry (near singular).
pub fn solve<const N: usize>(mut a: [[f64; N]; N], mut b: [f64; N], rel_tol: f64) -> Option<[f64; N]> {
    let scale = a.iter().flatten().fold(0.0f64, |m, v| m.max(v.abs()));
    if !(scale > 0.0 && scale.is_finite()) {
        return None;
    }
    for col in 0..N {
        let pivot = (col..N).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() <= rel_tol * scale {
            return None;
        }
        a.swap(col, pivot);
        b.swap(col, pivot);
        for row in col + 1..N {
            let f = a[row][col] / a[col][col];
            for k in col..N {
                a[row][k] -= f * a[col][k];
            }
            b[row] -= f * b[col];
        }
    }
    let mut x = [0.0; N];
    for row in (0..N).rev() {
        let s: f64 = (row + 1..N).map(|k| a[row][k] * x[k]).sum();
        x[row] = (b[row] - s) / a[row][row];
    }
    x.iter().all(|v| v.is_finite()).then_some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DQuat;

    #[test]
    fn eigen_of_a_rotated_diagonal_matrix() {
        let r = DMat3::from_quat(DQuat::from_euler(glam::EulerRot::XYZ, 0.3, -1.1, 0.7));
        let d = DMat3::from_diagonal(DVec3::new(2.0, 1e-9, 0.5));
        let e = sym_eigen(r * d * r.transpose());
        let want = [1e-9, 0.5, 2.0];
        for k in 0..3 {
            assert!(
                (e.values[k] - want[k]).abs() < 1e-12,
                "λ{k}: {} vs {}",
                e.values[k],
                want[k]
            );
        }
        assert!(e.vectors[0].dot(r.col(1)).abs() > 1.0 - 1e-12);
        assert!(e.vectors[2].dot(r.col(0)).abs() > 1.0 - 1e-12);
    }

    #[test]
    fn plane_fit_rejects_collinear_points() {
        let line: Vec<DVec3> = (0..10).map(|i| DVec3::splat(i as f64)).collect();
        assert!(fit_plane(&line).is_none());
        assert!(fit_plane(&line[..2]).is_none());
    }

    /// A line scan with noise fits no plane (its tilt would be the noise's: 1 mm of
    /// noise on 100 points along x gave a normal of (0, 0.88, 0.48) until 2026-12-07);
    /// a strip 1 m by 2 cm, and a relay as deep as a third of its height, do.
    #[test]
    fn a_noisy_line_fits_no_plane_and_a_narrow_strip_does() {
        // Deterministic noise: a low-discrepancy sequence in [−1, 1].
        let noise = |i: usize, k: f64| ((i as f64 * k).fract() * 2.0 - 1.0) * 1e-3;
        let line: Vec<DVec3> = (0..100)
            .map(|i| DVec3::new(i as f64 * 0.01, noise(i, 0.618_034), noise(i, 0.414_214)))
            .collect();
        assert!(fit_plane(&line).is_none());
        // Depth noise alone: the points lie in the x–z plane, but a line scan's.
        let scan: Vec<DVec3> = (0..100)
            .map(|i| DVec3::new(i as f64 * 0.01, 0.0, noise(i, 0.414_214)))
            .collect();
        assert!(fit_plane(&scan).is_none());
        let strip: Vec<DVec3> = (0..100)
            .map(|i| {
                DVec3::new(
                    (i / 2) as f64 * 0.02,
                    (i % 2) as f64 * 0.02,
                    noise(i, 0.618_034) * 0.1,
                )
            })
            .collect();
        let plane = fit_plane(&strip).expect("a strip is a plane");
        assert!(plane.normal.z.abs() > 0.99, "{}", plane.normal);
        // Two backs: 0.9 m wide, 0.65 m tall, 0.24 m deep, as curved caps.
        let backs: Vec<DVec3> = (0..400)
            .map(|i| {
                let (u, v) = ((i % 20) as f64 / 19.0 - 0.5, (i / 20) as f64 / 19.0 - 0.5);
                let cap = |x: f64| 0.24 * (1.0 - (2.0 * ((x.abs() - 0.25) / 0.45)).powi(2)).max(0.0);
                DVec3::new(0.9 * u, 0.65 * v, cap(0.9 * u))
            })
            .collect();
        let plane = fit_plane(&backs).expect("two backs");
        assert!(plane.normal.z.abs() > 0.9, "{}", plane.normal);
    }
}

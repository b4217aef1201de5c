//! A small Levenberg–Marquardt least-squares solver: nine parameters and a few
//! hundred residuals, so dense normal equations, a central-difference Jacobian and a
//! Cholesky solve are all it takes. Written here rather than taken from a crate
//! (`levenberg-marquardt` would bring nalgebra, a large dependency for one 9 × 9
//! solve); the finite-difference Jacobian keeps the model code the one statement of
//! the physics, with no hand-derived derivatives to drift from it.

/// Why a least-squares problem could not be solved.
#[derive(Debug, Clone, PartialEq)]
pub(crate) enum SolveError {
    /// The model cannot be evaluated at the starting point.
    Start,
    /// The residuals do not constrain parameter `index` (its column of the Jacobian
    /// is zero or a combination of the others).
    Unconstrained {
        /// The parameter.
        index: usize,
    },
}

/// A solution: the parameters, the final residuals, the normal matrix JᵀJ at the
/// solution (for the parameters' uncertainties), and whether the iterations ended
/// because no step lowered the cost any further, however damped (a minimum to the
/// model's precision, or a point past which the model cannot be evaluated; `false`:
/// they ran out at [`MAX_ITERATIONS`] with the last step still lowering it).
#[derive(Debug, Clone)]
pub(crate) struct Solution {
    pub x: Vec<f64>,
    pub residuals: Vec<f64>,
    pub normal: Vec<Vec<f64>>,
    pub converged: bool,
}

/// Finite-difference step, in the parameters' units (metres and radians): a micron
/// and a microradian, well above rounding in f64 and well below what the model's
/// curvature notices.
const STEP: f64 = 1e-6;
/// Most iterations before giving up improving further: a well-posed calibration takes
/// a few dozen; one still improving at this count has not converged, and says so.
pub(crate) const MAX_ITERATIONS: usize = 200;
/// Smallest pivot, relative to its diagonal element, of a normal matrix that counts
/// as constraining every parameter: a smaller one means a parameter is (almost) a
/// combination of the others.
const MIN_PIVOT: f64 = 1e-10;

/// Minimises ½‖f(x)‖² from `x0`. `f` returns `None` where the model cannot be
/// evaluated (a ray that misses the target): such steps are refused.
pub(crate) fn least_squares(
    f: &dyn Fn(&[f64]) -> Option<Vec<f64>>,
    x0: &[f64],
) -> Result<Solution, SolveError> {
    least_squares_within(f, x0, MAX_ITERATIONS)
}

/// [`least_squares`] with at most `max_iterations` iterations.
fn least_squares_within(
    f: &dyn Fn(&[f64]) -> Option<Vec<f64>>,
    x0: &[f64],
    max_iterations: usize,
) -> Result<Solution, SolveError> {
    let n = x0.len();
    let mut x = x0.to_vec();
    let mut r = f(&x)
        .filter(|r| r.iter().all(|v| v.is_finite()))
        .ok_or(SolveError::Start)?;
    let mut cost = half_norm(&r);
    let mut lambda = 1e-3;
    let mut normal = Vec::new();
    let mut converged = false;
    for _ in 0..max_iterations {
        let j = jacobian(f, &x, &r).ok_or(SolveError::Start)?;
        let (a, g) = normal_equations(&j, &r, n);
        check_constrained(&a)?;
        normal = a.clone();
        let mut improved = false;
        while lambda < 1e12 {
            let mut damped = a.clone();
            for i in 0..n {
                damped[i][i] += lambda * a[i][i];
            }
            let Some(step) = cholesky_solve(&damped, &g.iter().map(|v| -v).collect::<Vec<_>>()) else {
                lambda *= 10.0;
                continue;
            };
            let trial: Vec<f64> = x.iter().zip(&step).map(|(a, b)| a + b).collect();
            match f(&trial).filter(|r| r.iter().all(|v| v.is_finite())) {
                Some(tr) if half_norm(&tr) < cost => {
                    let small = step.iter().map(|s| s.abs()).fold(0.0, f64::max) < 1e-12;
                    let gain = cost - half_norm(&tr);
                    x = trial;
                    r = tr;
                    cost = half_norm(&r);
                    lambda = (lambda / 3.0).max(1e-12);
                    improved = !small && gain > 1e-15 * cost.max(1e-300);
                    break;
                }
                _ => lambda *= 4.0,
            }
        }
        if !improved {
            converged = true;
            break;
        }
    }
    if normal.is_empty() {
        let j = jacobian(f, &x, &r).ok_or(SolveError::Start)?;
        normal = normal_equations(&j, &r, n).0;
    }
    Ok(Solution {
        x,
        residuals: r,
        normal,
        converged,
    })
}

fn half_norm(r: &[f64]) -> f64 {
    0.5 * r.iter().map(|v| v * v).sum::<f64>()
}

/// Central differences, one-sided where a side cannot be evaluated; columns by
/// parameter.
fn jacobian(f: &dyn Fn(&[f64]) -> Option<Vec<f64>>, x: &[f64], r: &[f64]) -> Option<Vec<Vec<f64>>> {
    let mut cols = Vec::with_capacity(x.len());
    for i in 0..x.len() {
        let at = |d: f64| {
            let mut y = x.to_vec();
            y[i] += d;
            f(&y).filter(|v| v.len() == r.len() && v.iter().all(|e| e.is_finite()))
        };
        let col = match (at(STEP), at(-STEP)) {
            (Some(p), Some(m)) => p.iter().zip(&m).map(|(a, b)| (a - b) / (2.0 * STEP)).collect(),
            (Some(p), None) => p.iter().zip(r).map(|(a, b)| (a - b) / STEP).collect(),
            (None, Some(m)) => r.iter().zip(&m).map(|(a, b)| (a - b) / STEP).collect(),
            (None, None) => return None,
        };
        cols.push(col);
    }
    Some(cols)
}

/// JᵀJ and Jᵀr from the Jacobian's columns.
fn normal_equations(cols: &[Vec<f64>], r: &[f64], n: usize) -> (Vec<Vec<f64>>, Vec<f64>) {
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let a = (0..n)
        .map(|i| (0..n).map(|k| dot(&cols[i], &cols[k])).collect())
        .collect();
    let g = (0..n).map(|i| dot(&cols[i], r)).collect();
    (a, g)
}

/// Fails with the first parameter the normal matrix does not constrain: a zero
/// diagonal, or a small pivot of the correlation matrix's Cholesky factorisation.
fn check_constrained(a: &[Vec<f64>]) -> Result<(), SolveError> {
    let n = a.len();
    if let Some(index) = (0..n).find(|&i| !(a[i][i] > 0.0)) {
        return Err(SolveError::Unconstrained { index });
    }
    let corr: Vec<Vec<f64>> = (0..n)
        .map(|i| (0..n).map(|k| a[i][k] / (a[i][i] * a[k][k]).sqrt()).collect())
        .collect();
    match cholesky(&corr) {
        Ok(_) => Ok(()),
        Err(index) => Err(SolveError::Unconstrained { index }),
    }
}

/// The lower Cholesky factor of a symmetric matrix, or the index of the first pivot
/// below [`MIN_PIVOT`] (relative to its diagonal element).
fn cholesky(a: &[Vec<f64>]) -> Result<Vec<Vec<f64>>, usize> {
    let n = a.len();
    let mut l = vec![vec![0.0; n]; n];
    for i in 0..n {
        for k in 0..=i {
            let s: f64 = (0..k).map(|m| l[i][m] * l[k][m]).sum();
            if i == k {
                let d = a[i][i] - s;
                if !(d > MIN_PIVOT * a[i][i].abs()) {
                    return Err(i);
                }
                l[i][i] = d.sqrt();
            } else {
                l[i][k] = (a[i][k] - s) / l[k][k];
            }
        }
    }
    Ok(l)
}

/// Solves A·x = b for a symmetric positive-definite A.
fn cholesky_solve(a: &[Vec<f64>], b: &[f64]) -> Option<Vec<f64>> {
    let l = cholesky(a).ok()?;
    let n = b.len();
    let mut y = vec![0.0; n];
    for i in 0..n {
        y[i] = (b[i] - (0..i).map(|k| l[i][k] * y[k]).sum::<f64>()) / l[i][i];
    }
    let mut x = vec![0.0; n];
    for i in (0..n).rev() {
        x[i] = (y[i] - (i + 1..n).map(|k| l[k][i] * x[k]).sum::<f64>()) / l[i][i];
    }
    Some(x)
}

/// The diagonal of A⁻¹ (the parameters' variances for unit-variance residuals).
pub(crate) fn inverse_diagonal(a: &[Vec<f64>]) -> Option<Vec<f64>> {
    let n = a.len();
    (0..n)
        .map(|i| {
            let mut e = vec![0.0; n];
            e[i] = 1.0;
            cholesky_solve(a, &e).map(|c| c[i])
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_curve_fit_recovers_its_parameters() {
        // y = a·exp(b·t) + c, sampled without noise.
        let truth = [2.0, -0.7, 0.3];
        let ts: Vec<f64> = (0..30).map(|i| i as f64 * 0.2).collect();
        let model = |p: &[f64], t: f64| p[0] * (p[1] * t).exp() + p[2];
        let ys: Vec<f64> = ts.iter().map(|&t| model(&truth, t)).collect();
        let f = |p: &[f64]| Some(ts.iter().zip(&ys).map(|(&t, &y)| model(p, t) - y).collect());
        let s = least_squares(&f, &[1.0, -0.1, 0.0]).unwrap();
        for (i, (got, want)) in s.x.iter().zip(truth).enumerate() {
            assert!((got - want).abs() < 1e-8, "parameter {i}: {got} vs {want}");
        }
    }

    #[test]
    fn iterations_that_run_out_while_still_improving_are_not_converged() {
        // Rosenbrock's valley as least squares: from (−1.2, 1) it takes more than a
        // few steps to reach (1, 1).
        let f = |p: &[f64]| Some(vec![10.0 * (p[1] - p[0] * p[0]), 1.0 - p[0]]);
        let cut = least_squares_within(&f, &[-1.2, 1.0], 3).unwrap();
        assert!(!cut.converged, "stopped after 3 iterations at {:?}", cut.x);
        let whole = least_squares(&f, &[-1.2, 1.0]).unwrap();
        assert!(whole.converged);
        assert!(
            (whole.x[0] - 1.0).abs() < 1e-8 && (whole.x[1] - 1.0).abs() < 1e-8,
            "{:?}",
            whole.x
        );
    }

    #[test]
    fn a_parameter_the_residuals_ignore_is_named() {
        let f = |p: &[f64]| Some(vec![p[0] - 1.0, p[0] + 1.0, 2.0 * p[0]]);
        assert_eq!(
            least_squares(&f, &[0.0, 0.0]).unwrap_err(),
            SolveError::Unconstrained { index: 1 }
        );
        // Two parameters that only ever appear as their sum.
        let g = |p: &[f64]| Some(vec![p[0] + p[1] - 1.0, 2.0 * (p[0] + p[1]), p[2] - 3.0]);
        assert_eq!(
            least_squares(&g, &[0.0, 0.0, 0.0]).unwrap_err(),
            SolveError::Unconstrained { index: 1 }
        );
    }

    #[test]
    fn a_model_that_cannot_start_is_refused() {
        let f = |_: &[f64]| None;
        assert_eq!(least_squares(&f, &[0.0]).unwrap_err(), SolveError::Start);
        let nan = |_: &[f64]| Some(vec![f64::NAN]);
        assert_eq!(least_squares(&nan, &[0.0]).unwrap_err(), SolveError::Start);
    }

    #[test]
    fn the_inverse_diagonal_is_exact() {
        let a = vec![vec![4.0, 1.0], vec![1.0, 3.0]];
        let d = inverse_diagonal(&a).unwrap();
        assert!((d[0] - 3.0 / 11.0).abs() < 1e-15 && (d[1] - 4.0 / 11.0).abs() < 1e-15);
    }
}

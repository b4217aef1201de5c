//! The relay's albedo from the relay scan, as each transient's known gain.
//!
//! A relay's albedo varies from spot to spot (paint, a poster, clothes), and every
//! third-bounce transient carries the albedo of the spot the laser lights and of the
//! spot the SPAD sees: a gain no capture file states, which a fit with gains 1 bends
//! the scene to explain. The relay scan has already measured it. Under the diffused
//! laser, the first-bounce counts `I(p)` at a relay point are
//! `E(p) · a(p) · C(p)`: the diffuser's irradiance `E = cos θ_L / |p − L|²` (a source
//! at the laser arm's origin L, even over its cone), the albedo, and the SPAD's
//! collection `C` from that spot, whatever it is. A transient of the pair (x_i, x_d)
//! carries `a(x_i) · a(x_d) C(x_d)` (the focused laser puts the same power into its
//! spot wherever it points), that is `I(x_i) / (E(x_i) C(x_i))` times `I(x_d) /
//! E(x_d)`: the detection side needs no model of the collection, and the
//! illumination side takes `C = cos θ_S / |p − S|²`, a spot seen from the SPAD arm's
//! origin S.
//!
//! Counting noise is not albedo: each side's logarithm is split into a quadratic over
//! the relay (a smooth trend, which hundreds of points fix well) and each point's
//! departure from it, which is kept in the proportion `τ² / (τ² + v)` (`v = 1/I`, the
//! Poisson variance of `ln I`; `τ²` the departures' spread less that noise), so a
//! uniform relay gives gains of 1 up to a fraction of the counting noise.
use glam::DVec3;
use kiddo::{ImmutableKdTree, SquaredEuclidean};

use crate::transient::Pair;

/// The first-bounce counts a relay point needs for its albedo to be read from them
/// (fewer: its departure from the relay's smooth albedo is not used).
const MIN_COUNTS: f64 = 1.0;

/// The least cosine, from the spot to the laser or to the SPAD, at which a point's
/// return is read: nearer grazing (84°) a small error in the estimated normal is a
/// large error in `cos θ / d²`, and the point is left to its neighbours.
const MIN_COSINE: f64 = 0.1;

/// A pair's gain stays within this factor of the pairs' geometric mean, as the fit's
/// own gain estimates do: beyond it the relay scan has misread a spot, not an albedo.
const MAX_SPREAD: f64 = 10.0;

/// Each relay point's two factors of a transient's gain, in the logarithm
/// ([`RelayAlbedo::pair_gains`] combines them per pair).
#[derive(Clone, Debug)]
pub struct RelayAlbedo {
    points: Vec<DVec3>,
    /// `ln(a · C)` at each point, up to a constant (the detection side).
    detection: Vec<f64>,
    /// `ln a` at each point, up to a constant (the illumination side).
    illumination: Vec<f64>,
    tree: ImmutableKdTree<f64, 3>,
}

impl RelayAlbedo {
    /// From the relay scan: `points` and their unit `normals` (toward the instrument),
    /// each point's first-bounce `counts` (photons, background removed), and the
    /// diffused laser's and the SPAD's origins. Points with under one count, or seen
    /// nearer grazing than a cosine of 0.1 from the laser or the SPAD, are left out
    /// (pairs there take their nearest neighbour's factors). `None` with fewer than six points left, or when
    /// the lengths differ.
    pub fn from_scan(
        points: &[DVec3],
        normals: &[DVec3],
        counts: &[f64],
        laser: DVec3,
        spad: DVec3,
    ) -> Option<Self> {
        let n = points.len();
        if normals.len() != n || counts.len() != n {
            return None;
        }
        let cosine_over_d2 = |p: DVec3, normal: DVec3, at: DVec3| {
            let to = at - p;
            let d2 = to.length_squared();
            let cos = normal.dot(to) / d2.sqrt();
            (cos >= MIN_COSINE && d2 > 0.0).then(|| (cos / d2).ln())
        };
        let mut used = Vec::new();
        let (mut det, mut ill, mut var) = (Vec::new(), Vec::new(), Vec::new());
        for k in 0..n {
            let (p, nrm, c) = (points[k], normals[k], counts[k]);
            if !(c.is_finite() && c >= MIN_COUNTS && p.is_finite() && nrm.is_finite()) {
                continue;
            }
            let (Some(e), Some(s)) = (cosine_over_d2(p, nrm, laser), cosine_over_d2(p, nrm, spad)) else {
                continue;
            };
            used.push(k);
            det.push(c.ln() - e);
            ill.push(c.ln() - e - s);
            var.push(1.0 / c);
        }
        if used.len() < 6 {
            return None;
        }
        let kept: Vec<DVec3> = used.iter().map(|&k| points[k]).collect();
        let detection = shrink(&kept, &det, &var);
        let illumination = shrink(&kept, &ill, &var);
        let coords: Vec<[f64; 3]> = kept.iter().map(|p| p.to_array()).collect();
        Some(Self {
            tree: ImmutableKdTree::new_from_slice(&coords),
            points: kept,
            detection,
            illumination,
        })
    }

    /// Each pair's gain: the illumination factor at the relay point nearest `xi`
    /// times the detection factor at the one nearest `xd`, over their geometric mean
    /// across `pairs` (so the overall scale stays the fit's), within 10× of it.
    pub fn pair_gains(&self, pairs: &[Pair]) -> Vec<f64> {
        let nearest = |x: DVec3| self.tree.nearest_one::<SquaredEuclidean>(&x.to_array()).item as usize;
        let logs: Vec<f64> = pairs
            .iter()
            .map(|p| self.illumination[nearest(p.xi)] + self.detection[nearest(p.xd)])
            .collect();
        if logs.is_empty() {
            return Vec::new();
        }
        let mean = logs.iter().sum::<f64>() / logs.len() as f64;
        let limit = MAX_SPREAD.ln();
        logs.iter()
            .map(|l| (l - mean).clamp(-limit, limit).exp())
            .collect()
    }

    /// The relay points the factors were read at.
    pub fn points(&self) -> &[DVec3] {
        &self.points
    }
}

/// `values` (logarithms at `points`, variances `var`) as their smooth quadratic over
/// the relay plus each point's departure from it kept in the proportion
/// `τ² / (τ² + v)` (empirical Bayes; module docs).
fn shrink(points: &[DVec3], values: &[f64], var: &[f64]) -> Vec<f64> {
    let weights: Vec<f64> = var.iter().map(|v| 1.0 / v).collect();
    let smooth = crate::gtr::train::smooth_log_gains(points, values, &weights);
    let n = values.len() as f64;
    let spread = values
        .iter()
        .zip(&smooth)
        .map(|(v, s)| (v - s) * (v - s))
        .sum::<f64>()
        / n;
    let noise = var.iter().sum::<f64>() / n;
    let tau2 = (spread - noise).max(0.0);
    values
        .iter()
        .zip(&smooth)
        .zip(var)
        .map(|((v, s), var)| s + tau2 / (tau2 + var) * (v - s))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 30 × 30 wall at z = 0 under a laser and SPAD 2 m away: counts drawn from a
    /// known albedo (a ramp and every point's own factor) give back the transients'
    /// gains `a(xi) · a(xd) C(xd)` up to the counting noise, and a uniform wall gives
    /// the collection's gains within half of it.
    #[test]
    fn gains_from_the_scan_follow_the_relays_albedo() {
        use rand::{Rng, SeedableRng};
        let (laser, spad) = (DVec3::new(-0.1, 0.0, 2.0), DVec3::new(0.1, 0.0, 2.0));
        let mut points = Vec::new();
        for i in 0..30 {
            for j in 0..30 {
                points.push(DVec3::new(
                    -0.4 + 0.8 * i as f64 / 29.0,
                    -0.4 + 0.8 * j as f64 / 29.0,
                    0.0,
                ));
            }
        }
        let normals = vec![DVec3::Z; points.len()];
        let geometry = |p: DVec3, at: DVec3| {
            let to = at - p;
            to.z / to.length() / to.length_squared()
        };
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(54);
        let own: Vec<f64> = (0..points.len()).map(|_| rng.random_range(0.7..1.3)).collect();
        let albedo = |k: usize, patchy: bool| {
            if patchy {
                (0.5 * points[k].x + 0.3 * points[k].y).exp() * own[k]
            } else {
                1.0
            }
        };
        let pairs: Vec<Pair> = (0..points.len())
            .map(|k| Pair {
                xi: points[k],
                ni: DVec3::Z,
                xd: points[(k + 37) % points.len()],
                nd: DVec3::Z,
            })
            .collect();
        for patchy in [false, true] {
            // About 2,000 photons a point: Gaussian noise of the Poisson variance.
            let counts: Vec<f64> = (0..points.len())
                .map(|k| {
                    let mean = 2000.0 / 0.25f64.powi(2)
                        * geometry(points[k], laser)
                        * geometry(points[k], spad)
                        * albedo(k, patchy);
                    let u: f64 = rng.random_range(-1.0..1.0);
                    mean + u * (3.0 * mean).sqrt()
                })
                .collect();
            let relay = RelayAlbedo::from_scan(&points, &normals, &counts, laser, spad).unwrap();
            let got = relay.pair_gains(&pairs);
            let want: Vec<f64> = (0..points.len())
                .map(|k| {
                    let d = (k + 37) % points.len();
                    (albedo(k, patchy) * albedo(d, patchy) * geometry(points[d], spad)).ln()
                })
                .collect();
            let mean = want.iter().sum::<f64>() / want.len() as f64;
            let err: Vec<f64> = got.iter().zip(&want).map(|(g, w)| g.ln() - (w - mean)).collect();
            let rms = (err.iter().map(|e| e * e).sum::<f64>() / err.len() as f64).sqrt();
            // Two points' counting noise a pair: all of it where the albedo varies
            // (bounded by 1.5 of it), little of it on a uniform wall (half).
            let noise = (2.0f64 / 2000.0).sqrt();
            let bound = if patchy { 1.5 * noise } else { 0.5 * noise };
            assert!(
                rms < bound,
                "patchy {patchy}: gains off by {rms:.4} in the log (noise {noise:.4})"
            );
            if !patchy {
                let spread =
                    (want.iter().map(|w| (w - mean).powi(2)).sum::<f64>() / want.len() as f64).sqrt();
                assert!(
                    spread < 0.05,
                    "a uniform wall's collection alone spreads {spread}"
                );
            }
        }
    }
}

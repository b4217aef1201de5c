//! The Gaussian cloud as the optimiser sees it: unconstrained raw parameters stored
//! structure-of-arrays, one flat array per optimiser group, and the smooth maps that
//! turn them into valid physical primitives.
//!
//! | group    | raw (per primitive)  | physical                                        |
//! |----------|----------------------|-------------------------------------------------|
//! | centres  | θx ∈ ℝ³              | x = c + h ⊙ tanh(θx): always inside the ROI box |
//! | scales   | θs ∈ ℝ³              | ln s = ln s_min + (ln s_max − ln s_min)·sigmoid(θs) |
//! | rotations| r ∈ ℝ⁴ (w, x, y, z)  | unit quaternion q = r/‖r‖ → R(q)                |
//! | albedo   | θρ ∈ ℝ               | ρ = softplus(θρ) ≥ 0                            |
//!
//! Bounded log-scales keep every primitive between a size the time axis can resolve
//! and one that still fits the ROI, so no optimiser step can produce a zero or
//! infinite covariance.
use glam::{DMat3, DQuat, DVec3};

use super::kernel::{Kernel, PhysicalGrad};
use crate::roi::RoiBox;
use crate::simd::{Quad, tanh_scalar};

/// The range of primitive scales (standard deviations), metres.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ScaleBounds {
    /// Smallest scale.
    pub min: f64,
    /// Largest scale.
    pub max: f64,
}

/// Unconstrained parameters of K primitives, one flat array per group.
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianCloud {
    roi: RoiBox,
    scale_bounds: ScaleBounds,
    /// θx, 3 per primitive.
    pub centres: Vec<f64>,
    /// θs, 3 per primitive.
    pub scales: Vec<f64>,
    /// Raw quaternions (w, x, y, z), 4 per primitive.
    pub rotations: Vec<f64>,
    /// θρ, 1 per primitive.
    pub albedo: Vec<f64>,
}

/// Gradients with the same layout as [`GaussianCloud`]'s raw arrays.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RawGrads {
    /// ∂L/∂θx.
    pub centres: Vec<f64>,
    /// ∂L/∂θs.
    pub scales: Vec<f64>,
    /// ∂L/∂r.
    pub rotations: Vec<f64>,
    /// ∂L/∂θρ.
    pub albedo: Vec<f64>,
}

impl RawGrads {
    /// Zeroed gradients for `n` primitives.
    pub fn zeros(n: usize) -> Self {
        Self {
            centres: vec![0.0; 3 * n],
            scales: vec![0.0; 3 * n],
            rotations: vec![0.0; 4 * n],
            albedo: vec![0.0; n],
        }
    }
}

/// Why a cloud could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ModelError {
    /// The scale bounds are not `0 < min < max`, finite.
    #[error("invalid scale bounds {min} .. {max} m: they need 0 < min < max")]
    ScaleBounds {
        /// Lower bound.
        min: f64,
        /// Upper bound.
        max: f64,
    },
    /// A physical value cannot be represented (outside the ROI, the scale bounds, ...).
    #[error("primitive {index}: {reason}")]
    Value {
        /// Index of the primitive.
        index: usize,
        /// What is wrong.
        reason: String,
    },
}

fn softplus(x: f64) -> f64 {
    if x > 30.0 { x } else { x.exp().ln_1p() }
}

fn inv_softplus(y: f64) -> f64 {
    if y > 30.0 { y } else { y.exp_m1().ln() }
}

/// The slopes of one primitive's parameter maps at its raw parameters (the diagonal
/// of the maps' Jacobian; the rotation's is computed where it is used).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct MapSlopes {
    /// `∂x_j/∂θx_j = h_j (1 − tanh² θx_j)`.
    pub centre: DVec3,
    /// `∂s_j/∂θs_j = s_j (ln s_max − ln s_min) σ(θs_j) (1 − σ(θs_j))`.
    pub scale: DVec3,
    /// `∂ρ/∂θρ = σ(θρ)`.
    pub albedo: f64,
}

/// The physical description of one primitive.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Primitive {
    /// Centre, metres.
    pub centre: DVec3,
    /// Scales (standard deviations), metres.
    pub scale: DVec3,
    /// Orientation.
    pub rotation: DQuat,
    /// Albedo ρ.
    pub albedo: f64,
}

impl Primitive {
    /// What the primitive adds to a transient, up to the geometry of the pair: its
    /// albedo times the square of its largest projected area (the forward model's
    /// `ρ A⊥(ui) A⊥(ud)` seen face-on). Albedo alone is no measure: the model's
    /// amplitude grows with area², so half as wide a primitive needs 4× the albedo
    /// for the same signal.
    pub fn weight(&self) -> f64 {
        let mut s = self.scale.to_array();
        s.sort_by(f64::total_cmp);
        self.albedo * (s[1] * s[2]).powi(2)
    }
}

impl GaussianCloud {
    /// An empty cloud.
    pub fn new(roi: RoiBox, scale_bounds: ScaleBounds) -> Result<Self, ModelError> {
        let ScaleBounds { min, max } = scale_bounds;
        if !(min.is_finite() && max.is_finite() && min > 0.0 && min < max) {
            return Err(ModelError::ScaleBounds { min, max });
        }
        Ok(Self {
            roi,
            scale_bounds,
            centres: Vec::new(),
            scales: Vec::new(),
            rotations: Vec::new(),
            albedo: Vec::new(),
        })
    }

    /// Appends a primitive given physically; fails if it is outside the ROI, its scales
    /// outside the bounds, its albedo not positive or its rotation not finite.
    pub fn push(&mut self, p: Primitive) -> Result<(), ModelError> {
        let index = self.len();
        let (centre, scale, rotation, albedo) = self.raw_of(index, p)?;
        self.centres.extend(centre);
        self.scales.extend(scale);
        self.rotations.extend(rotation);
        self.albedo.push(albedo);
        Ok(())
    }

    /// Replaces primitive `k` (which must exist) with `p`, under the same rules as
    /// [`push`](Self::push); on error the cloud is unchanged.
    pub fn set(&mut self, k: usize, p: Primitive) -> Result<(), ModelError> {
        assert!(k < self.len(), "primitive {k} of {}", self.len());
        let (centre, scale, rotation, albedo) = self.raw_of(k, p)?;
        self.centres[3 * k..3 * k + 3].copy_from_slice(&centre);
        self.scales[3 * k..3 * k + 3].copy_from_slice(&scale);
        self.rotations[4 * k..4 * k + 4].copy_from_slice(&rotation);
        self.albedo[k] = albedo;
        Ok(())
    }

    /// The raw parameters of `p`, checked; `index` names it in errors.
    #[allow(clippy::type_complexity)]
    fn raw_of(&self, index: usize, p: Primitive) -> Result<([f64; 3], [f64; 3], [f64; 4], f64), ModelError> {
        let bad = |reason: String| ModelError::Value { index, reason };
        let rel = (p.centre - self.roi.centre) / self.roi.half;
        if !rel.is_finite() || rel.abs().max_element() >= 1.0 {
            return Err(bad(format!("centre {} is not strictly inside the ROI", p.centre)));
        }
        let (lmin, lspan) = self.log_scale_map();
        let mut raw_s = [0.0; 3];
        for (j, s) in p.scale.to_array().into_iter().enumerate() {
            let t = (s.ln() - lmin) / lspan;
            if !(t > 0.0 && t < 1.0) {
                return Err(bad(format!(
                    "scale {s} m is outside ({}, {}) m",
                    self.scale_bounds.min, self.scale_bounds.max
                )));
            }
            raw_s[j] = (t / (1.0 - t)).ln();
        }
        if !(p.albedo.is_finite() && p.albedo > 0.0) {
            return Err(bad(format!("albedo {} must be positive", p.albedo)));
        }
        let q = p.rotation;
        if !q.is_finite() || q.length() < 1e-12 {
            return Err(bad("rotation is not a finite, non-zero quaternion".into()));
        }
        let q = q.normalize();
        Ok((
            rel.to_array().map(f64::atanh),
            raw_s,
            [q.w, q.x, q.y, q.z],
            inv_softplus(p.albedo),
        ))
    }

    /// Number of primitives.
    pub fn len(&self) -> usize {
        self.albedo.len()
    }

    /// Whether the cloud is empty.
    pub fn is_empty(&self) -> bool {
        self.albedo.is_empty()
    }

    /// The ROI the centres are confined to.
    pub fn roi(&self) -> &RoiBox {
        &self.roi
    }

    /// The scale bounds.
    pub fn scale_bounds(&self) -> ScaleBounds {
        self.scale_bounds
    }

    pub(crate) fn log_scale_map(&self) -> (f64, f64) {
        let lmin = self.scale_bounds.min.ln();
        (lmin, self.scale_bounds.max.ln() - lmin)
    }

    fn raw_quat(&self, k: usize) -> DQuat {
        let r = &self.rotations[4 * k..4 * k + 4];
        DQuat::from_xyzw(r[1], r[2], r[3], r[0])
    }

    /// The centre that raw centre parameters `raw` (θx) map to.
    pub fn centre_of_raw(&self, raw: &[f64]) -> DVec3 {
        let t = DVec3::from_slice(raw);
        self.roi.centre + self.roi.half * DVec3::new(tanh_scalar(t.x), tanh_scalar(t.y), tanh_scalar(t.z))
    }

    /// The physical parameters of primitive `k`.
    pub fn primitive(&self, k: usize) -> Primitive {
        let m = crate::simd::dispatch(MapLanes {
            cloud: self,
            idx: [k; 4],
        });
        Primitive {
            centre: m.centre[0],
            scale: m.scale[0],
            rotation: self.raw_quat(k).normalize(),
            albedo: softplus(self.albedo[k]),
        }
    }

    /// The render kernel of primitive `k`.
    pub fn kernel(&self, k: usize) -> Kernel {
        let p = self.primitive(k);
        Kernel::new(p.centre, DMat3::from_quat(p.rotation), p.scale, p.albedo)
    }

    /// The render kernel of primitive `k` ([`GaussianCloud::kernel`], the same bits)
    /// and the slopes of its parameter maps, from one evaluation of each map: a
    /// training step refreshes both, and its backward pass then chains without
    /// evaluating a transcendental function again ([`GaussianCloud::chain_with`]).
    pub fn kernel_and_slopes(&self, k: usize) -> (Kernel, MapSlopes) {
        let m = crate::simd::dispatch(MapLanes {
            cloud: self,
            idx: [k; 4],
        });
        m.kernel_and_slopes(self, 0, k)
    }

    /// [`GaussianCloud::kernel_and_slopes`] of primitives `first..first + kernels.len()`
    /// into `kernels` and `slopes`, the maps four primitives at a time.
    pub fn kernels_and_slopes_into(&self, first: usize, kernels: &mut [Kernel], slopes: &mut [MapSlopes]) {
        crate::simd::dispatch(MapRange {
            cloud: self,
            first,
            kernels,
            slopes,
        });
    }

    /// The slopes of primitive `k`'s parameter maps.
    pub fn slopes(&self, k: usize) -> MapSlopes {
        self.kernel_and_slopes(k).1
    }

    /// Render kernels of all primitives.
    pub fn kernels(&self) -> Vec<Kernel> {
        (0..self.len()).map(|k| self.kernel(k)).collect()
    }

    /// Writes the raw-parameter gradient of primitive `k` given the gradient with
    /// respect to its physical parameters; returns the albedo's.
    pub fn chain(
        &self,
        k: usize,
        g: &PhysicalGrad,
        out_c: &mut [f64],
        out_s: &mut [f64],
        out_r: &mut [f64],
    ) -> f64 {
        self.chain_with(k, &self.slopes(k), g, out_c, out_s, out_r)
    }

    /// [`GaussianCloud::chain`] with the map slopes of primitive `k` already known
    /// ([`GaussianCloud::kernel_and_slopes`]).
    pub fn chain_with(
        &self,
        k: usize,
        slopes: &MapSlopes,
        g: &PhysicalGrad,
        out_c: &mut [f64],
        out_s: &mut [f64],
        out_r: &mut [f64],
    ) -> f64 {
        // Centres: x = c + h tanh θ → dx/dθ = h (1 − tanh² θ).
        // Scales: s = exp(lmin + lspan σ(θ)) → ds/dθ = s lspan σ (1 − σ).
        for j in 0..3 {
            out_c[j] = g.x[j] * slopes.centre[j];
            out_s[j] = g.s[j] * slopes.scale[j];
        }
        // Rotations: R(q) with q = r/‖r‖.
        let raw = self.raw_quat(k);
        let norm = raw.length();
        let q = raw / norm;
        let dq = quat_grad(q, &g.r);
        let radial = dq.dot(q);
        let dr = (dq - q * radial) / norm;
        out_r.copy_from_slice(&[dr.w, dr.x, dr.y, dr.z]);
        // Albedo: ρ = softplus(θ) → dρ/dθ = σ(θ).
        g.rho * slopes.albedo
    }

    /// Renormalises the raw quaternions to unit length (after an optimiser step), and
    /// resets any that collapsed to zero to the identity.
    pub fn renormalise_rotations(&mut self) {
        use rayon::prelude::*;
        self.rotations.par_chunks_exact_mut(4).for_each(renormalise);
    }

    /// Keeps only the primitives for which `keep(k)` is true.
    pub fn retain(&mut self, keep: impl Fn(usize) -> bool) {
        let kept: Vec<usize> = (0..self.len()).filter(|&k| keep(k)).collect();
        let gather = |v: &[f64], n: usize| kept.iter().flat_map(|&k| v[n * k..n * k + n].to_vec()).collect();
        self.centres = gather(&self.centres, 3);
        self.scales = gather(&self.scales, 3);
        self.rotations = gather(&self.rotations, 4);
        self.albedo = gather(&self.albedo, 1);
    }
}

/// The centre, scale and slope maps of four primitives (lanes), from one vector
/// evaluation of each map: `tanh` and the logistic function through
/// [`crate::simd::exp`], so any lane gives the bits any other path gives.
struct Mapped {
    centre: [DVec3; 4],
    scale: [DVec3; 4],
    /// Slopes without the albedo's, which [`Mapped::kernel_and_slopes`] adds.
    slopes: [MapSlopes; 4],
    /// σ(θρ), the albedo's slope.
    albedo_slope: [f64; 4],
}

impl Mapped {
    /// Lane `lane`, primitive `k` of `cloud`: its kernel and slopes. The rotation and
    /// the albedo's softplus are computed here, one primitive at a time.
    #[inline(always)]
    fn kernel_and_slopes(&self, cloud: &GaussianCloud, lane: usize, k: usize) -> (Kernel, MapSlopes) {
        let kernel = Kernel::new(
            self.centre[lane],
            DMat3::from_quat(cloud.raw_quat(k).normalize()),
            self.scale[lane],
            softplus(cloud.albedo[k]),
        );
        let slopes = MapSlopes {
            albedo: self.albedo_slope[lane],
            ..self.slopes[lane]
        };
        (kernel, slopes)
    }
}

/// The maps of primitives `idx` (an index may repeat), one lane each.
struct MapLanes<'a> {
    cloud: &'a GaussianCloud,
    idx: [usize; 4],
}

impl crate::simd::Work for MapLanes<'_> {
    type Output = Mapped;

    #[inline(always)]
    fn run<Q: Quad>(self, q: Q) -> Mapped {
        let Self { cloud, idx } = self;
        let (lmin, lspan) = cloud.log_scale_map();
        let one = q.splat(1.0);
        let mut out = Mapped {
            centre: [DVec3::ZERO; 4],
            scale: [DVec3::ZERO; 4],
            slopes: [MapSlopes::default(); 4],
            albedo_slope: [0.0; 4],
        };
        for j in 0..3 {
            let t = crate::simd::tanh(q, q.load(idx.map(|k| cloud.centres[3 * k + j])));
            let sg = crate::simd::sigmoid(q, q.load(idx.map(|k| cloud.scales[3 * k + j])));
            let scale = crate::simd::exp(q, q.add(q.splat(lmin), q.mul(q.splat(lspan), sg)));
            let (c, h) = (q.splat(cloud.roi.centre[j]), q.splat(cloud.roi.half[j]));
            let centre = q.store(q.add(c, q.mul(h, t)));
            let slope_c = q.store(q.mul(h, q.sub(one, q.mul(t, t))));
            let slope_s = q.store(q.mul(q.mul(q.mul(scale, q.splat(lspan)), sg), q.sub(one, sg)));
            let scale = q.store(scale);
            for l in 0..4 {
                out.centre[l][j] = centre[l];
                out.scale[l][j] = scale[l];
                out.slopes[l].centre[j] = slope_c[l];
                out.slopes[l].scale[j] = slope_s[l];
            }
        }
        out.albedo_slope = q.store(crate::simd::sigmoid(q, q.load(idx.map(|k| cloud.albedo[k]))));
        out
    }
}

/// [`GaussianCloud::kernels_and_slopes_into`]'s loop.
struct MapRange<'a> {
    cloud: &'a GaussianCloud,
    first: usize,
    kernels: &'a mut [Kernel],
    slopes: &'a mut [MapSlopes],
}

impl crate::simd::Work for MapRange<'_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: Quad>(self, q: Q) {
        let Self {
            cloud,
            first,
            kernels,
            slopes,
        } = self;
        let n = kernels.len().min(slopes.len());
        for start in (0..n).step_by(4) {
            let last = first + n - 1;
            let idx = [0, 1, 2, 3].map(|l| (first + start + l).min(last));
            let m = MapLanes { cloud, idx }.run(q);
            for l in 0..4.min(n - start) {
                (kernels[start + l], slopes[start + l]) = m.kernel_and_slopes(cloud, l, idx[l]);
            }
        }
    }
}

/// ∂L/∂q (as a quaternion w, x, y, z) from ∂L/∂R for R = R(q), q unit.
fn quat_grad(q: DQuat, g: &DMat3) -> DQuat {
    let (w, x, y, z) = (q.w, q.x, q.y, q.z);
    // G[m][j]: row m, column j.
    let gm = |m: usize, j: usize| g.col(j)[m];
    let (g00, g01, g02) = (gm(0, 0), gm(0, 1), gm(0, 2));
    let (g10, g11, g12) = (gm(1, 0), gm(1, 1), gm(1, 2));
    let (g20, g21, g22) = (gm(2, 0), gm(2, 1), gm(2, 2));
    let dw = 2.0 * (-z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21);
    let dx =
        2.0 * (y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22);
    let dy =
        2.0 * (-2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22);
    let dz =
        2.0 * (-2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21);
    DQuat::from_xyzw(dx, dy, dz, dw)
}

/// A raw quaternion back to unit length (after an optimiser step), or the identity
/// where it collapsed to zero.
pub(crate) fn renormalise(r: &mut [f64]) {
    let n = r.iter().map(|v| v * v).sum::<f64>().sqrt();
    if n.is_finite() && n > 1e-12 {
        r.iter_mut().for_each(|v| *v /= n);
    } else {
        r.copy_from_slice(&[1.0, 0.0, 0.0, 0.0]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `kernel_and_slopes` gives `kernel`'s bits, and slopes that are the maps'
    /// derivatives (central differences of `primitive` on each raw parameter).
    #[test]
    fn kernel_and_slopes_agree_with_the_maps() {
        let roi = RoiBox::from_bounds(DVec3::new(-0.4, -0.3, 0.3), DVec3::new(0.4, 0.5, 0.9)).unwrap();
        let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 2e-3, max: 0.2 }).unwrap();
        for (i, scale) in [0.003, 0.02, 0.15].into_iter().enumerate() {
            let f = i as f64;
            cloud
                .push(Primitive {
                    centre: DVec3::new(-0.39 + 0.3 * f, 0.1 * f, 0.35 + 0.2 * f),
                    scale: DVec3::new(scale, 0.5 * scale + 0.002, 0.01),
                    rotation: DQuat::from_axis_angle(DVec3::new(1.0, 2.0, -0.5).normalize(), 0.7 * f),
                    albedo: 0.01 + 3.0 * f,
                })
                .unwrap();
        }
        let h = 1e-6;
        // Four at a time (the last group partial) as one at a time.
        let mut kernels = vec![cloud.kernel(0); cloud.len()];
        let mut all_slopes = vec![MapSlopes::default(); cloud.len()];
        cloud.kernels_and_slopes_into(0, &mut kernels, &mut all_slopes);
        for k in 0..cloud.len() {
            let (kernel, slopes) = cloud.kernel_and_slopes(k);
            assert_eq!(kernel, cloud.kernel(k));
            assert_eq!((kernel, slopes), (kernels[k], all_slopes[k]));
            for j in 0..3 {
                let moved = |group: fn(&mut GaussianCloud) -> &mut Vec<f64>, idx: usize| {
                    let mut c = cloud.clone();
                    group(&mut c)[idx] += h;
                    let up = c.primitive(k);
                    group(&mut c)[idx] -= 2.0 * h;
                    let down = c.primitive(k);
                    (up, down)
                };
                let (up, down) = moved(|c| &mut c.centres, 3 * k + j);
                let fd = (up.centre[j] - down.centre[j]) / (2.0 * h);
                assert!(
                    (fd - slopes.centre[j]).abs() <= 1e-7 * fd.abs().max(1e-3),
                    "centre {k}.{j}: {fd} vs {}",
                    slopes.centre[j]
                );
                let (up, down) = moved(|c| &mut c.scales, 3 * k + j);
                let fd = (up.scale[j] - down.scale[j]) / (2.0 * h);
                assert!(
                    (fd - slopes.scale[j]).abs() <= 1e-7 * fd.abs().max(1e-6),
                    "scale {k}.{j}: {fd} vs {}",
                    slopes.scale[j]
                );
            }
            let mut c = cloud.clone();
            c.albedo[k] += h;
            let up = c.primitive(k).albedo;
            c.albedo[k] -= 2.0 * h;
            let fd = (up - c.primitive(k).albedo) / (2.0 * h);
            assert!(
                (fd - slopes.albedo).abs() <= 1e-7,
                "albedo {k}: {fd} vs {}",
                slopes.albedo
            );
        }
    }
}

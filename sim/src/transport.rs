//! Light transport on the scene's meshes: ray casting, the first-bounce (LOS) return
//! of a SPAD ray under diffused illumination, and the third-bounce (NLOS) transient of
//! an illumination/detection pair, integrated over stratified samples of the hidden
//! surfaces with visibility.
//!
//! Independent of the 3D-GTR renderer by construction: surfaces are triangles, the
//! integral is a sum over area samples, visibility is ray cast, and time is binned by
//! the detector model.
//!
//! Visibility between a relay point and the hidden scene is decided per hidden
//! triangle (one shadow ray to its centroid) and shared by that triangle's samples:
//! shadow edges are resolved to the triangle size (centimetres for the shipped
//! shapes), and the cost no longer grows with the sampling density. Scenes that cannot
//! occlude (a planar relay and one planar hidden object) cast no shadow rays. Interreflections within the relay and fourth and later bounces
//! are not modelled.
use std::collections::HashMap;

use glam::DVec3;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;

use crate::bvh::Bvh;
use crate::detector::{Detector, OVERSAMPLE};
use crate::mesh::Mesh;
use crate::scene::Scene;

/// Offset that keeps shadow rays off the surfaces they start and end on, metres.
const EPS: f64 = 1e-6;

/// A point on a hidden surface standing for a small patch of it.
#[derive(Clone, Copy, Debug)]
struct Sample {
    p: DVec3,
    n: DVec3,
    /// ρ/π · patch area, m².
    weight: f64,
    /// Index of its hidden triangle (visibility is decided per triangle).
    tri: u32,
}

/// Where a ray met the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SurfaceHit {
    /// The point.
    pub point: DVec3,
    /// Unit normal facing the ray's origin.
    pub normal: DVec3,
    /// Lambertian albedo there.
    pub albedo: f64,
    /// Distance from the ray's origin.
    pub distance: f64,
    /// Whether it is on the relay (else on a hidden object).
    pub on_relay: bool,
}

/// The positions of the laser and SPAD galvo origins.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Instrument {
    /// Laser galvo pair origin L.
    pub laser: DVec3,
    /// SPAD galvo pair origin S.
    pub spad: DVec3,
}

/// An illumination/detection pair as the instrument realises it: both spots on the
/// relay, with true normals (facing the instrument) and albedos.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SpotPair {
    /// Laser spot.
    pub illumination: SurfaceHit,
    /// SPAD spot.
    pub detection: SurfaceHit,
}

/// A scene prepared for transport.
pub struct World {
    scene: Scene,
    /// Every surface merged; `owner[t]` is the surface of triangle t (0 = relay).
    mesh: Mesh,
    owner: Vec<usize>,
    bvh: Bvh,
    hidden_bvh: Bvh,
    hidden_owner: Vec<usize>,
    samples: Vec<Sample>,
    /// Centroid and normal of every hidden triangle.
    centroids: Vec<(DVec3, DVec3)>,
    /// What can block light between the relay and the hidden scene; `None` when
    /// nothing can (a planar relay and a single planar hidden object).
    occluders: Option<Bvh>,
}

impl World {
    /// Prepares `scene`, sampling hidden surfaces about every `spacing` metres
    /// (stratified, jittered from `seed`; [`samples_needed`] samples in all).
    pub fn new(scene: Scene, spacing: f64, seed: u64) -> World {
        let mut mesh = scene.relay.mesh.clone();
        let mut owner = vec![0; mesh.triangles.len()];
        let mut hidden_mesh = Mesh::default();
        let mut hidden_owner = Vec::new();
        for (k, s) in scene.hidden.iter().enumerate() {
            mesh.append(&s.mesh);
            owner.extend(std::iter::repeat_n(k + 1, s.mesh.triangles.len()));
            hidden_mesh.append(&s.mesh);
            hidden_owner.extend(std::iter::repeat_n(k + 1, s.mesh.triangles.len()));
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x05A3_B1E5);
        let mut samples = Vec::new();
        let mut centroids = Vec::new();
        for s in &scene.hidden {
            for t in 0..s.mesh.triangles.len() {
                let [a, b, c] = s.mesh.corners(t);
                let tri = centroids.len() as u32;
                centroids.push(((a + b + c) / 3.0, s.mesh.normal(t)));
                let area = s.mesh.area(t);
                // m × m strata of the unit square, mapped onto the triangle.
                let m = strata(area, spacing);
                if m == 0 {
                    continue;
                }
                let n = s.mesh.normal(t);
                let w = s.albedo / std::f64::consts::PI * area / (m * m) as f64;
                for i in 0..m {
                    for j in 0..m {
                        let u = (i as f64 + rng.random::<f64>()) / m as f64;
                        let v = (j as f64 + rng.random::<f64>()) / m as f64;
                        let su = u.sqrt();
                        let p = a * (1.0 - su) + b * (su * (1.0 - v)) + c * (su * v);
                        samples.push(Sample { p, n, weight: w, tri });
                    }
                }
            }
        }
        let relay_planar = is_planar(&scene.relay.mesh);
        let occluders = if relay_planar && scene.hidden.len() == 1 && is_planar(&scene.hidden[0].mesh) {
            None
        } else {
            let mut m = hidden_mesh.clone();
            if !relay_planar {
                m.append(&scene.relay.mesh);
            }
            Some(Bvh::new(&m))
        };
        World {
            centroids,
            occluders,
            bvh: Bvh::new(&mesh),
            hidden_bvh: Bvh::new(&hidden_mesh),
            scene,
            mesh,
            owner,
            hidden_owner,
            samples,
        }
    }

    /// The scene.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// Number of hidden-surface samples.
    pub fn sample_count(&self) -> usize {
        self.samples.len()
    }

    /// First surface along the ray from `origin` in direction `dir`.
    pub fn cast(&self, origin: DVec3, dir: DVec3) -> Option<SurfaceHit> {
        let dir = dir.try_normalize()?;
        let hit = self.bvh.closest(origin, dir, EPS, f64::INFINITY)?;
        let surface = self.owner[hit.triangle];
        let mut normal = self.mesh.normal(hit.triangle);
        if normal.dot(-dir) < 0.0 {
            normal = -normal;
        }
        let point = origin + dir * hit.t;
        let albedo = if surface == 0 {
            self.scene.relay.albedo_at(point)
        } else {
            self.scene.hidden[surface - 1].albedo
        };
        Some(SurfaceHit {
            point,
            normal,
            albedo,
            distance: hit.t,
            on_relay: surface == 0,
        })
    }

    /// First hidden surface along a ray (hidden objects only), for ground truth.
    pub fn cast_hidden(&self, origin: DVec3, dir: DVec3) -> Option<(DVec3, usize)> {
        let dir = dir.try_normalize()?;
        let hit = self.hidden_bvh.closest(origin, dir, EPS, f64::INFINITY)?;
        Some((origin + dir * hit.t, self.hidden_owner[hit.triangle] - 1))
    }

    /// Photons per pulse a spot at `hit` sends into the SPAD's aperture per unit
    /// irradiance-independent factor: (ρ/π) · A_spot · cos · A_ap / |x − S|².
    fn collection(&self, hit: &SurfaceHit, spad: DVec3, det: &Detector) -> f64 {
        let to_s = spad - hit.point;
        let d2 = to_s.length_squared();
        let cos = (hit.normal.dot(to_s) / d2.sqrt()).max(0.0);
        hit.albedo / std::f64::consts::PI * det.spot_area * cos * det.aperture_area / d2
    }

    /// The LOS (first-bounce) histogram's expected counts for a SPAD ray under the
    /// diffused laser, and the point it saw. No gating.
    pub fn first_bounce(
        &self,
        inst: &Instrument,
        dir: DVec3,
        det: &Detector,
        dwell: f64,
    ) -> Option<(SurfaceHit, Vec<f64>)> {
        let hit = self.cast(inst.spad, dir)?;
        let to_l = inst.laser - hit.point;
        let dl2 = to_l.length_squared();
        let occluded = self.bvh.occluded(hit.point, inst.laser, EPS);
        let irradiance = if occluded {
            0.0
        } else {
            det.photons_per_pulse() / det.diffuser_solid_angle * (hit.normal.dot(to_l) / dl2.sqrt()).max(0.0)
                / dl2
        };
        let photons = irradiance * self.collection(&hit, inst.spad, det);
        let path = dl2.sqrt() + hit.distance;
        let mut fine = vec![0.0; det.bins * OVERSAMPLE];
        let before = deposit_pulses(&mut fine, det, path, photons);
        let signal = det.blur(&fine);
        Some((hit, det.expected_counts_after(&signal, before, None, dwell)))
    }

    /// Where the laser and SPAD rays land: the pair the instrument measures, if both
    /// hit the relay.
    pub fn spots(&self, inst: &Instrument, laser_dir: DVec3, spad_dir: DVec3) -> Option<SpotPair> {
        let illumination = self.cast(inst.laser, laser_dir)?;
        let detection = self.cast(inst.spad, spad_dir)?;
        (illumination.on_relay && detection.on_relay).then_some(SpotPair {
            illumination,
            detection,
        })
    }

    /// Expected counts over `dwell` for each pair (NLOS mode: focused laser spot,
    /// gated SPAD), computed in parallel over pairs.
    pub fn third_bounce(
        &self,
        inst: &Instrument,
        pairs: &[SpotPair],
        det: &Detector,
        dwell: f64,
    ) -> Vec<Vec<f64>> {
        // Visibility of every sample from every distinct relay point, computed once.
        let mut points: Vec<DVec3> = Vec::new();
        let mut index: HashMap<[u64; 3], usize> = HashMap::new();
        let mut key_of = |p: DVec3| -> usize {
            *index.entry(p.to_array().map(f64::to_bits)).or_insert_with(|| {
                points.push(p);
                points.len() - 1
            })
        };
        let pair_points: Vec<(usize, usize)> = pairs
            .iter()
            .map(|p| (key_of(p.illumination.point), key_of(p.detection.point)))
            .collect();
        let visible: Vec<Vec<bool>> = match &self.occluders {
            None => vec![vec![true; self.centroids.len()]; points.len()],
            Some(occluders) => points
                .par_iter()
                .map(|&x| {
                    self.centroids
                        .iter()
                        .map(|&(c, n)| !occluders.occluded(c + n * EPS * n.dot(x - c).signum(), x, 1e-5))
                        .collect()
                })
                .collect(),
        };
        pairs
            .par_iter()
            .zip(&pair_points)
            .map(|(pair, &(vi, vd))| self.pair_counts(inst, pair, &visible[vi], &visible[vd], det, dwell))
            .collect()
    }

    fn pair_counts(
        &self,
        inst: &Instrument,
        pair: &SpotPair,
        vis_i: &[bool],
        vis_d: &[bool],
        det: &Detector,
        dwell: f64,
    ) -> Vec<f64> {
        let (xi, xd) = (pair.illumination, pair.detection);
        let first_leg = xi.point.distance(inst.laser);
        let last_leg = xd.point.distance(inst.spad);
        // Photons per pulse leaving the laser spot per unit (ρ_y/π dA · geometry).
        let scale =
            det.photons_per_pulse() * xi.albedo / std::f64::consts::PI * self.collection(&xd, inst.spad, det);
        let mut fine = vec![0.0; det.bins * OVERSAMPLE];
        // Signal photons a cycle arriving before the window (an ungated direct return).
        let mut before = 0.0;
        for s in &self.samples {
            if !(vis_i[s.tri as usize] && vis_d[s.tri as usize]) {
                continue;
            }
            let a = s.p - xi.point;
            let b = s.p - xd.point;
            let (r1, r2) = (a.length(), b.length());
            let ci = xi.normal.dot(a) / r1;
            let cd = xd.normal.dot(b) / r2;
            let (cy1, cy2) = (-s.n.dot(a) / r1, -s.n.dot(b) / r2);
            // Light must arrive on and leave from the same side of the hidden patch.
            if ci <= 0.0 || cd <= 0.0 || cy1 * cy2 <= 0.0 {
                continue;
            }
            let photons = scale * ci * cd * cy1.abs() * cy2.abs() * s.weight / (r1 * r1 * r2 * r2);
            before += deposit_pulses(&mut fine, det, first_leg + r1 + r2 + last_leg, photons);
        }
        // The direct return when the SPAD looks at the laser spot (confocal pairs).
        let spot_radius = (det.spot_area / std::f64::consts::PI).sqrt();
        let separation = xi.point.distance(xd.point);
        if separation < 2.0 * spot_radius {
            // Overlap of two discs of the same radius, as a fraction of one.
            let d = separation / (2.0 * spot_radius);
            let overlap = 2.0 / std::f64::consts::PI * (d.acos() - d * (1.0 - d * d).sqrt());
            let direct =
                det.photons_per_pulse() * overlap * self.collection(&xi, inst.spad, det) / det.spot_area;
            before += deposit_pulses(&mut fine, det, first_leg + xi.point.distance(inst.spad), direct);
        }
        let signal = det.blur(&fine);
        let gate = det
            .gate_margin
            .map(|m| det.bin_of_path(first_leg + separation + last_leg + m));
        det.expected_counts_after(&signal, before, gate, dwell)
    }
}

/// Strata a side that [`World::new`] lays on a hidden triangle of `area` m², sampled
/// about every `spacing` metres: m × m samples, m = ⌈√(area / spacing²)⌉ and at least
/// one however small the triangle; none for a degenerate one (no area).
fn strata(area: f64, spacing: f64) -> usize {
    if area <= 0.0 {
        return 0;
    }
    ((area / (spacing * spacing)).sqrt().ceil() as usize).max(1)
}

/// How many samples [`World::new`] makes of `scene`'s hidden surfaces at `spacing`
/// metres: m² a triangle (`strata`, the sampler's own rule), saturating at
/// `usize::MAX`. What it will allocate, to bound before anything is: the hidden area
/// over spacing² counts too few where the triangles are small, since each gets a
/// whole sample however small it is (a mesh of 10⁶ slivers needs 10⁶ samples
/// whatever its area).
pub fn samples_needed(scene: &Scene, spacing: f64) -> usize {
    let mut total = 0usize;
    for s in &scene.hidden {
        for t in 0..s.mesh.triangles.len() {
            let m = strata(s.mesh.area(t), spacing);
            total = total.saturating_add(m.saturating_mul(m));
        }
    }
    total
}

/// Whether every vertex lies on the plane of the first non-degenerate triangle.
fn is_planar(mesh: &Mesh) -> bool {
    let Some(t) = (0..mesh.triangles.len()).find(|&t| mesh.area(t) > 0.0) else {
        return true;
    };
    let (p, n) = (mesh.corners(t)[0], mesh.normal(t));
    mesh.vertices.iter().all(|v| (*v - p).dot(n).abs() < 1e-9)
}

/// Adds `value` at fractional bin `f` into the oversampled histogram, split linearly
/// between the two nearest sub-bin centres (the mean arrival time is kept exactly).
/// [`deposit`]s an arrival of path `path` once for each pulse of a TDC cycle
/// ([`Detector::bins_of_path`]): with a sync divider of N the window sees N pulses.
/// Returns what of `value` arrives before the window ([`deposit`]).
fn deposit_pulses(fine: &mut [f64], det: &Detector, path: f64, value: f64) -> f64 {
    det.bins_of_path(path).map(|f| deposit(fine, f, value)).sum()
}

/// Returns the part of `value` that arrives before the window's first sub-bin (for
/// [`Detector::expected_counts_after`]: a detection then takes the cycle's one);
/// what arrives after the window is dropped.
fn deposit(fine: &mut [f64], f: f64, value: f64) -> f64 {
    let u = f * OVERSAMPLE as f64 - 0.5;
    if !(u.is_finite() && value > 0.0) || u >= fine.len() as f64 {
        return 0.0;
    }
    if u < -1.0 {
        return value;
    }
    let j = u.floor();
    let t = u - j;
    let j = j as isize;
    let mut early = 0.0;
    if j >= 0 {
        fine[j as usize] += value * (1.0 - t);
    } else {
        early = value * (1.0 - t);
    }
    if ((j + 1) as usize) < fine.len() {
        fine[(j + 1) as usize] += value * t;
    }
    early
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{ShapeKind, Surface};
    use crate::shapes;

    fn surface(label: &str, shape: ShapeKind, mesh: Mesh) -> Surface {
        Surface {
            label: label.into(),
            shape,
            mesh,
            albedo: 0.9,
            variation: None,
        }
    }

    /// [`samples_needed`] is the count the sampler makes, not the hidden area over
    /// spacing²: a triangle far smaller than the spacing still gets a whole sample, so
    /// a mesh of many small triangles needs many times what its area says (here over
    /// 3,250 samples for 1.5·10⁻² m² at 1 cm, which the area puts at 150), and the
    /// daemon's bound on the samples must count them so.
    #[test]
    fn the_sample_count_is_what_the_sampler_makes_of_many_small_triangles() {
        // 3,200 triangles of 3 mm² (a 10 cm square as a 40 × 40 grid), a 10 × 5 cm
        // rectangle of two triangles, and a sliver with no area, sampled every 1 cm.
        let mut hidden = Mesh::parametric(40, 40, |u, v| DVec3::new(0.1 * u, 0.1 * v, 0.5));
        hidden.append(
            &Mesh::rectangle([0.0, 0.1], [0.0, 0.05])
                .transformed(glam::DMat3::IDENTITY, DVec3::new(0.2, 0.0, 0.6)),
        );
        let base = hidden.vertices.len() as u32;
        hidden.vertices.extend([
            DVec3::new(0.0, 0.0, 0.7),
            DVec3::new(0.1, 0.0, 0.7),
            DVec3::new(0.2, 0.0, 0.7),
        ]);
        hidden.triangles.push([base, base + 1, base + 2]);
        let scene = Scene {
            name: "small triangles".into(),
            relay: surface("relay", ShapeKind::Plane, shapes::plane([2.0, 2.0])),
            hidden: vec![surface("hidden[0]", ShapeKind::Mesh, hidden)],
        };
        let spacing = 0.01;
        let area = scene.hidden[0].mesh.total_area();
        let needed = samples_needed(&scene, spacing);
        let world = World::new(scene, spacing, 7);
        assert_eq!(world.sample_count(), needed);
        // One for each small triangle, at least 5 × 5 for each half of the rectangle,
        // none for the sliver.
        assert!(needed >= 3_200 + 2 * 25, "{needed} samples");
        assert!(
            needed as f64 > 20.0 * area / (spacing * spacing),
            "{needed} samples against {area} m² at {spacing} m"
        );
    }
}

//! Scene files: the relay surface and the hidden objects of a simulated capture.
//!
//! A scene is TOML (see docs/simulation.md and `configs/scenes/`). This module holds
//! the raw serde form and its validation into meshes; the daemon parses the file with
//! its config source so errors name file, line and key, and maps the key paths of
//! [`SceneError`] onto lines.
use std::path::{Path, PathBuf};

use glam::{DMat3, DVec3, EulerRot};
use serde::Deserialize;

use crate::mesh::Mesh;
use crate::shapes;

/// The raw scene file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RawScene {
    /// Scene name.
    pub name: String,
    /// Free text.
    #[serde(default)]
    pub description: Option<String>,
    /// The relay surface.
    pub relay: RawSurface,
    /// Hidden objects (`[[hidden]]` tables).
    #[serde(default)]
    pub hidden: Vec<RawSurface>,
}

/// Which shape a surface is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ShapeKind {
    /// A flat rectangle (`size`).
    Plane,
    /// Sinusoidal panel (`size`, `amplitude`, `periods`, `direction`).
    SPanel,
    /// Parabolic panel (`size`, `amplitude`, `direction`).
    CPanel,
    /// Two human backs side by side (`width`, `depth`, `height`, `spacing`).
    TorsoPair,
    /// Planar text (`text`, `height`, `stroke`).
    Letter,
    /// The bar resolution target (`count`, `width`, `length`, `gap`).
    Bars,
    /// A child-like figure (`height`).
    Mannequin,
    /// A triangle mesh file, OBJ or PLY (`path`, `scale`).
    Mesh,
}

/// Which way a panel undulates.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Direction {
    /// Varies along x.
    Horizontal,
    /// Varies along y.
    Vertical,
}

/// One surface as written; which keys apply depends on `shape`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RawSurface {
    /// The shape.
    pub shape: ShapeKind,
    /// Lambertian albedo in [0, 1].
    pub albedo: f64,
    /// Position of the shape's local origin, metres.
    #[serde(default, deserialize_with = "periscope_drivers::exact::array")]
    pub position: [f64; 3],
    /// Rotation, degrees, applied x then y then z (intrinsic XYZ).
    #[serde(default, deserialize_with = "periscope_drivers::exact::array")]
    pub rotation_deg: [f64; 3],
    /// Width and height, metres.
    #[serde(default, deserialize_with = "periscope_drivers::exact::option")]
    pub size: Option<[f64; 2]>,
    /// Panel depth amplitude, metres.
    pub amplitude: Option<f64>,
    /// S-panel periods across the panel.
    pub periods: Option<f64>,
    /// Panel direction.
    pub direction: Option<Direction>,
    /// Panel tessellation.
    pub segments: Option<usize>,
    /// Letters.
    pub text: Option<String>,
    /// Letter / figure / torso height, metres.
    pub height: Option<f64>,
    /// Letter stroke width, metres.
    pub stroke: Option<f64>,
    /// Bars: how many.
    pub count: Option<usize>,
    /// Bar or torso width, metres.
    pub width: Option<f64>,
    /// Bar length, metres.
    pub length: Option<f64>,
    /// Gap between bars, metres.
    pub gap: Option<f64>,
    /// Torso depth, metres.
    pub depth: Option<f64>,
    /// Torso centre spacing, metres.
    pub spacing: Option<f64>,
    /// Mesh file, relative to the scene file.
    pub path: Option<PathBuf>,
    /// Mesh scale factor.
    pub scale: Option<f64>,
    /// How the albedo varies from spot to spot (the relay only).
    pub albedo_variation: Option<RawAlbedoVariation>,
}

/// `[relay.albedo-variation]`: a relay whose albedo varies from spot to spot, as a
/// real wall's paint, a poster or a person's clothes do, so every transient carries a
/// gain no capture file states. The albedo at a point is `albedo` times a smooth ramp
/// and a per-cell factor, never above `albedo`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub struct RawAlbedoVariation {
    /// The ramp: the brightest end over the darkest, across the relay's footprint
    /// along `direction` (1: no ramp), exponential along it.
    #[serde(default = "unity")]
    pub smooth: f64,
    /// The ramp's direction in the world x–y plane (need not be a unit vector).
    #[serde(
        default = "ramp_direction",
        deserialize_with = "periscope_drivers::exact::array"
    )]
    pub direction: [f64; 2],
    /// Each cell's own factor, uniform in [1 − random, 1 + random] (0: none).
    #[serde(default)]
    pub random: f64,
    /// The cells' size in world x and y, metres.
    #[serde(default = "cell_size")]
    pub cell_m: f64,
    /// Seed of the cells' factors.
    #[serde(default)]
    pub seed: u64,
}

fn unity() -> f64 {
    1.0
}

fn ramp_direction() -> [f64; 2] {
    [0.6, 0.4]
}

fn cell_size() -> f64 {
    0.02
}

/// A validated [`RawAlbedoVariation`] on a surface's footprint.
#[derive(Clone, Debug, PartialEq)]
pub struct AlbedoVariation {
    /// `ln(smooth)`.
    log_ramp: f64,
    /// Unit ramp direction in x–y.
    direction: [f64; 2],
    /// The footprint's extent along `direction`: its least and its span.
    start: f64,
    span: f64,
    random: f64,
    cell: f64,
    seed: u64,
}

impl AlbedoVariation {
    /// The factor at `p`, in (0, 1]: the ramp, 1 at its bright end, times the
    /// point's cell's factor over the largest a cell can have.
    pub fn factor(&self, p: DVec3) -> f64 {
        let along = p.x * self.direction[0] + p.y * self.direction[1];
        let t = ((along - self.start) / self.span).clamp(0.0, 1.0);
        let ramp = (self.log_ramp * (t - 1.0)).exp();
        if self.random == 0.0 {
            return ramp;
        }
        let cell = |v: f64| (v / self.cell).floor() as i64 as u64;
        let u = unit_hash(cell(p.x), cell(p.y), self.seed);
        ramp * (1.0 + self.random * (2.0 * u - 1.0)) / (1.0 + self.random)
    }
}

/// A uniform number in [0, 1) from a cell's indices and a seed (SplitMix64's
/// finaliser over their mix), the same wherever the cell is asked for.
fn unit_hash(ix: u64, iy: u64, seed: u64) -> f64 {
    let mut z = ix
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(iy.wrapping_mul(0xC2B2_AE3D_27D4_EB4F))
        .wrapping_add(seed.wrapping_mul(0x1656_67B1_9E37_79F9));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    (z >> 11) as f64 / (1u64 << 53) as f64
}

/// A validated surface: its mesh in the world frame and its albedo.
#[derive(Clone, Debug)]
pub struct Surface {
    /// What it is, for messages (`relay`, `hidden[0]`).
    pub label: String,
    /// The shape kind.
    pub shape: ShapeKind,
    /// World-frame mesh.
    pub mesh: Mesh,
    /// Lambertian albedo (the largest, where it varies).
    pub albedo: f64,
    /// How the albedo varies from spot to spot; `None`: the same everywhere.
    pub variation: Option<AlbedoVariation>,
}

impl Surface {
    /// The albedo at `p`, a point on the surface.
    pub fn albedo_at(&self, p: DVec3) -> f64 {
        self.variation
            .as_ref()
            .map_or(self.albedo, |v| self.albedo * v.factor(p))
    }
}

/// A validated scene.
#[derive(Clone, Debug)]
pub struct Scene {
    /// Scene name.
    pub name: String,
    /// The relay.
    pub relay: Surface,
    /// The hidden objects.
    pub hidden: Vec<Surface>,
}

/// A scene value that does not validate; `key` is the dotted path in the file.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("key `{key}`: {message}")]
pub struct SceneError {
    /// Dotted key path with `[i]` for array items, e.g. `hidden[0].stroke`.
    pub key: String,
    /// What is wrong and what to do.
    pub message: String,
}

impl Scene {
    /// Validates a raw scene; mesh paths resolve against `base_dir`.
    pub fn from_raw(raw: &RawScene, base_dir: &Path) -> Result<Scene, SceneError> {
        let relay = surface(&raw.relay, "relay", base_dir, true)?;
        let hidden = raw
            .hidden
            .iter()
            .enumerate()
            .map(|(i, s)| surface(s, &format!("hidden[{i}]"), base_dir, false))
            .collect::<Result<Vec<_>, _>>()?;
        if hidden.is_empty() {
            return Err(SceneError {
                key: "hidden".into(),
                message: "a scene needs at least one [[hidden]] object to image".into(),
            });
        }
        Ok(Scene {
            name: raw.name.clone(),
            relay,
            hidden,
        })
    }
}

fn surface(raw: &RawSurface, key: &str, base: &Path, relay: bool) -> Result<Surface, SceneError> {
    let err = |field: &str, message: String| SceneError {
        key: format!("{key}.{field}"),
        message,
    };
    let positive = |field: &str, v: Option<f64>| -> Result<f64, SceneError> {
        match v {
            Some(v) if v.is_finite() && v > 0.0 && v <= 100.0 => Ok(v),
            Some(v) => Err(err(
                field,
                format!("{v} must be a positive length in metres, at most 100"),
            )),
            None => Err(err(
                field,
                format!("shape `{:?}` needs `{field}`", raw.shape).to_lowercase(),
            )),
        }
    };
    if !(0.0..=1.0).contains(&raw.albedo) {
        return Err(err("albedo", format!("{} is not in [0, 1]", raw.albedo)));
    }
    if !raw
        .position
        .iter()
        .chain(&raw.rotation_deg)
        .all(|v| v.is_finite())
    {
        return Err(err("position", "position and rotation-deg must be finite".into()));
    }
    let relay_only = matches!(
        raw.shape,
        ShapeKind::Plane | ShapeKind::SPanel | ShapeKind::CPanel | ShapeKind::TorsoPair
    );
    let hidden_only = matches!(
        raw.shape,
        ShapeKind::Letter | ShapeKind::Bars | ShapeKind::Mannequin
    );
    if (relay && hidden_only) || (!relay && relay_only && raw.shape != ShapeKind::Plane) {
        return Err(err(
            "shape",
            format!(
                "{:?} cannot be a {} surface",
                raw.shape,
                if relay { "relay" } else { "hidden" }
            )
            .to_lowercase(),
        ));
    }
    let segments = raw.segments.unwrap_or(64).clamp(1, 4096);
    let horizontal = raw.direction.unwrap_or(Direction::Horizontal) == Direction::Horizontal;
    let size = |field: &str| -> Result<[f64; 2], SceneError> {
        match raw.size {
            Some(s) if s.iter().all(|v| v.is_finite() && *v > 0.0) => Ok(s),
            Some(s) => Err(err(
                field,
                format!("{s:?} must be two positive lengths in metres"),
            )),
            None => Err(err(field, "this shape needs `size = [width, height]`".into())),
        }
    };
    let mesh = match raw.shape {
        ShapeKind::Plane => shapes::plane(size("size")?),
        ShapeKind::SPanel => shapes::s_panel(
            size("size")?,
            positive("amplitude", raw.amplitude)?,
            positive("periods", raw.periods)?,
            horizontal,
            segments,
        ),
        ShapeKind::CPanel => shapes::c_panel(
            size("size")?,
            positive("amplitude", raw.amplitude)?,
            horizontal,
            segments,
        ),
        ShapeKind::TorsoPair => shapes::torso_pair(
            positive("width", raw.width)?,
            positive("depth", raw.depth)?,
            positive("height", raw.height)?,
            positive("spacing", raw.spacing)?,
            segments.min(64),
        ),
        ShapeKind::Letter => {
            let text = raw
                .text
                .as_deref()
                .filter(|t| !t.is_empty())
                .ok_or_else(|| err("text", "letters need `text`".into()))?;
            let height = positive("height", raw.height)?;
            let stroke = positive("stroke", raw.stroke)?;
            if stroke * 3.0 > height || stroke * 100.0 < height {
                return Err(err(
                    "stroke",
                    format!(
                        "{stroke} m does not suit letters {height} m tall: give a stroke between a hundredth and a third of the height"
                    ),
                ));
            }
            if text.chars().count() > 32 {
                return Err(err("text", "is longer than 32 letters".into()));
            }
            if let Some(c) = text.chars().find(|c| !shapes::has_glyph(*c)) {
                return Err(err("text", format!("no glyph for `{c}`: use the letters A–Z")));
            }
            shapes::text(text, height, stroke).expect("glyphs checked above")
        }
        ShapeKind::Bars => {
            let count = raw.count.unwrap_or(3);
            if !(1..=64).contains(&count) {
                return Err(err("count", format!("{count} bars: use 1 to 64")));
            }
            shapes::bars(
                count,
                positive("width", raw.width.or(Some(0.02)))?,
                positive("length", raw.length.or(Some(0.30)))?,
                positive("gap", raw.gap.or(Some(0.02)))?,
            )
        }
        ShapeKind::Mannequin => shapes::mannequin(positive("height", raw.height)?),
        ShapeKind::Mesh => {
            let path = raw
                .path
                .as_ref()
                .ok_or_else(|| err("path", "a mesh needs `path` (OBJ or PLY)".into()))?;
            let full = base.join(path);
            let mut mesh = Mesh::load(&full).map_err(|e| err("path", format!("{e}")))?;
            let scale = positive("scale", raw.scale.or(Some(1.0)))?;
            mesh.vertices.iter_mut().for_each(|v| *v *= scale);
            if mesh.vertices.iter().any(|v| !(v.abs().max_element() <= 100.0)) {
                return Err(err(
                    "scale",
                    format!("the scaled mesh reaches beyond 100 m of its origin (scale {scale})"),
                ));
            }
            mesh
        }
    };
    let [rx, ry, rz] = raw.rotation_deg.map(f64::to_radians);
    let rotation = DMat3::from_euler(EulerRot::XYZ, rx, ry, rz);
    let mesh = mesh.transformed(rotation, DVec3::from_array(raw.position));
    let variation = match &raw.albedo_variation {
        None => None,
        Some(_) if !relay => {
            return Err(err(
                "albedo-variation",
                "only the relay's albedo can vary from spot to spot; remove it from this hidden object"
                    .into(),
            ));
        }
        Some(v) => Some(albedo_variation(v, &mesh, &|field, message| {
            err(&format!("albedo-variation.{field}"), message)
        })?),
    };
    Ok(Surface {
        label: key.to_string(),
        shape: raw.shape,
        mesh,
        albedo: raw.albedo,
        variation,
    })
}

/// Validates `[relay.albedo-variation]` against the relay's world-frame `mesh`.
fn albedo_variation(
    raw: &RawAlbedoVariation,
    mesh: &Mesh,
    err: &dyn Fn(&str, String) -> SceneError,
) -> Result<AlbedoVariation, SceneError> {
    if !(raw.smooth.is_finite() && (1.0..=100.0).contains(&raw.smooth)) {
        return Err(err(
            "smooth",
            format!(
                "{} must be from 1 (no ramp) to 100 (the bright end over the dark)",
                raw.smooth
            ),
        ));
    }
    if !(raw.random.is_finite() && (0.0..=0.9).contains(&raw.random)) {
        return Err(err(
            "random",
            format!("{} must be from 0 (none) to 0.9 (each cell ±90 %)", raw.random),
        ));
    }
    if !(raw.cell_m.is_finite() && raw.cell_m > 0.0 && raw.cell_m <= 10.0) {
        return Err(err(
            "cell-m",
            format!("{} must be a positive size in metres, at most 10", raw.cell_m),
        ));
    }
    let [dx, dy] = raw.direction;
    let norm = dx.hypot(dy);
    if !(norm.is_finite() && norm > 0.0) {
        return Err(err(
            "direction",
            format!(
                "{:?} must be a non-zero direction in the x–y plane",
                raw.direction
            ),
        ));
    }
    let direction = [dx / norm, dy / norm];
    let (lo, hi) = mesh
        .vertices
        .iter()
        .map(|v| v.x * direction[0] + v.y * direction[1])
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), a| {
            (l.min(a), h.max(a))
        });
    Ok(AlbedoVariation {
        log_ramp: raw.smooth.ln(),
        direction,
        start: lo,
        span: (hi - lo).max(f64::MIN_POSITIVE),
        random: raw.random,
        cell: raw.cell_m,
        seed: raw.seed,
    })
}

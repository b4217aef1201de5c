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
    #[serde(default)]
    pub position: [f64; 3],
    /// Rotation, degrees, applied x then y then z (intrinsic XYZ).
    #[serde(default)]
    pub rotation_deg: [f64; 3],
    /// Width and height, metres.
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
    /// Lambertian albedo.
    pub albedo: f64,
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
    Ok(Surface {
        label: key.to_string(),
        shape: raw.shape,
        mesh: mesh.transformed(rotation, DVec3::from_array(raw.position)),
        albedo: raw.albedo,
    })
}

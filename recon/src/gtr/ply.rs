//! Export of primitives as a binary PLY in the standard 3D Gaussian Splatting layout,
//! so common splat viewers open it.
//!
//! Properties, in order (all `float`): `x y z` (centre, metres), `nx ny nz` (zero, kept
//! for viewers that expect them), `f_dc_0..2` (grey colour from the normalised albedo
//! as a degree-0 spherical-harmonic coefficient), `opacity` (logit of the normalised
//! albedo), `scale_0..2` (natural log of the scales, metres), `rot_0..3` (unit
//! quaternion w, x, y, z), and `albedo` (the fitted ρ, unnormalised).
use std::io::{self, Write};

use super::model::GaussianCloud;

/// SH degree-0 basis constant: colour = 0.5 + C0 · f_dc.
const SH_C0: f64 = 0.282_094_791_773_878_14;

/// Writes `cloud` as a binary little-endian PLY to `out`.
pub fn write_ply(cloud: &GaussianCloud, out: &mut impl Write) -> io::Result<()> {
    let names = [
        "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1",
        "scale_2", "rot_0", "rot_1", "rot_2", "rot_3", "albedo",
    ];
    let mut header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment periscope 3D-GTR primitives; albedo = fitted rho\nelement vertex {}\n",
        cloud.len()
    );
    for name in names {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    out.write_all(header.as_bytes())?;
    let prims: Vec<_> = (0..cloud.len()).map(|k| cloud.primitive(k)).collect();
    let max_albedo = prims.iter().map(|p| p.albedo).fold(0.0, f64::max);
    let mut row = Vec::with_capacity(names.len() * 4);
    for p in &prims {
        let a = if max_albedo > 0.0 {
            p.albedo / max_albedo
        } else {
            0.0
        };
        let clamped = a.clamp(1e-6, 1.0 - 1e-6);
        let dc = (a - 0.5) / SH_C0;
        let q = p.rotation;
        let values = [
            p.centre.x,
            p.centre.y,
            p.centre.z,
            0.0,
            0.0,
            0.0,
            dc,
            dc,
            dc,
            (clamped / (1.0 - clamped)).ln(),
            p.scale.x.ln(),
            p.scale.y.ln(),
            p.scale.z.ln(),
            q.w,
            q.x,
            q.y,
            q.z,
            p.albedo,
        ];
        row.clear();
        for v in values {
            row.extend_from_slice(&(v as f32).to_le_bytes());
        }
        out.write_all(&row)?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use glam::{DQuat, DVec3};

    use super::*;
    use crate::gtr::{Primitive, ScaleBounds};
    use crate::roi::RoiBox;

    #[test]
    fn writes_the_3dgs_layout() {
        let roi = RoiBox::from_bounds(DVec3::splat(-1.0), DVec3::splat(1.0)).unwrap();
        let mut cloud = GaussianCloud::new(roi, ScaleBounds { min: 1e-3, max: 0.5 }).unwrap();
        let rotation = DQuat::from_rotation_z(0.3);
        for (i, albedo) in [0.5, 2.0].into_iter().enumerate() {
            cloud
                .push(Primitive {
                    centre: DVec3::new(0.1 * i as f64, -0.2, 0.3),
                    scale: DVec3::new(0.01, 0.02, 0.04),
                    rotation,
                    albedo,
                })
                .unwrap();
        }
        let mut bytes = Vec::new();
        write_ply(&cloud, &mut bytes).unwrap();
        let end = bytes.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = std::str::from_utf8(&bytes[..end]).unwrap();
        assert!(header.contains("element vertex 2\n"));
        let props: Vec<&str> = header
            .lines()
            .filter_map(|l| l.strip_prefix("property float "))
            .collect();
        assert_eq!(&props[..3], ["x", "y", "z"]);
        assert!(props.contains(&"scale_2") && props.contains(&"rot_3") && props.contains(&"opacity"));
        let body = &bytes[end..];
        assert_eq!(body.len(), 2 * props.len() * 4);
        let field = |row: usize, name: &str| {
            let i = props.iter().position(|p| *p == name).unwrap();
            let at = (row * props.len() + i) * 4;
            f32::from_le_bytes(body[at..at + 4].try_into().unwrap()) as f64
        };
        assert!((field(1, "x") - 0.1).abs() < 1e-6);
        assert!((field(0, "scale_2") - 0.04f64.ln()).abs() < 1e-5);
        assert!((field(0, "rot_0") - rotation.w).abs() < 1e-6);
        assert!((field(1, "albedo") - 2.0).abs() < 1e-5);
    }
}

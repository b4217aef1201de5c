//! The shapes simulated scenes are built from: relay panels (plane, S- and C-shaped,
//! a pair of human backs) and hidden objects (stroke letters, the bar resolution
//! target, a child-sized mannequin). All are built in a local frame, centred on the
//! origin, facing +z (toward the instrument side), with y up; scenes place them by pose.
use std::f64::consts::PI;

use glam::{DMat3, DVec2, DVec3};

use crate::mesh::Mesh;

/// Letter strokes on a 4 × 6 grid (x right, y up), as segments.
fn glyph(c: char) -> Option<&'static [(f64, f64, f64, f64)]> {
    Some(match c.to_ascii_uppercase() {
        'A' => &[(0., 0., 2., 6.), (2., 6., 4., 0.), (1., 3., 3., 3.)],
        'B' => &[
            (0., 0., 0., 6.),
            (0., 6., 3., 6.),
            (3., 6., 4., 5.),
            (4., 5., 4., 4.),
            (4., 4., 3., 3.),
            (0., 3., 3., 3.),
            (3., 3., 4., 2.),
            (4., 2., 4., 1.),
            (4., 1., 3., 0.),
            (3., 0., 0., 0.),
        ],
        'C' => &[(4., 6., 0., 6.), (0., 6., 0., 0.), (0., 0., 4., 0.)],
        'D' => &[
            (0., 0., 0., 6.),
            (0., 6., 3., 6.),
            (3., 6., 4., 5.),
            (4., 5., 4., 1.),
            (4., 1., 3., 0.),
            (3., 0., 0., 0.),
        ],
        'E' => &[
            (0., 0., 0., 6.),
            (0., 6., 4., 6.),
            (0., 3., 3., 3.),
            (0., 0., 4., 0.),
        ],
        'F' => &[(0., 0., 0., 6.), (0., 6., 4., 6.), (0., 3., 3., 3.)],
        'G' => &[
            (4., 6., 0., 6.),
            (0., 6., 0., 0.),
            (0., 0., 4., 0.),
            (4., 0., 4., 3.),
            (4., 3., 2., 3.),
        ],
        'H' => &[(0., 0., 0., 6.), (4., 0., 4., 6.), (0., 3., 4., 3.)],
        'I' => &[(2., 0., 2., 6.), (1., 6., 3., 6.), (1., 0., 3., 0.)],
        'J' => &[(4., 6., 4., 0.), (4., 0., 0., 0.), (0., 0., 0., 2.)],
        'K' => &[(0., 0., 0., 6.), (4., 6., 0., 3.), (0., 3., 4., 0.)],
        'L' => &[(0., 6., 0., 0.), (0., 0., 4., 0.)],
        'M' => &[
            (0., 0., 0., 6.),
            (0., 6., 2., 3.),
            (2., 3., 4., 6.),
            (4., 6., 4., 0.),
        ],
        'N' => &[(0., 0., 0., 6.), (0., 6., 4., 0.), (4., 0., 4., 6.)],
        'O' => &[
            (0., 0., 0., 6.),
            (0., 6., 4., 6.),
            (4., 6., 4., 0.),
            (4., 0., 0., 0.),
        ],
        'P' => &[
            (0., 0., 0., 6.),
            (0., 6., 4., 6.),
            (4., 6., 4., 3.),
            (4., 3., 0., 3.),
        ],
        'Q' => &[
            (0., 0., 0., 6.),
            (0., 6., 4., 6.),
            (4., 6., 4., 0.),
            (4., 0., 0., 0.),
            (2., 2., 4., 0.),
        ],
        'R' => &[
            (0., 0., 0., 6.),
            (0., 6., 4., 6.),
            (4., 6., 4., 3.),
            (4., 3., 0., 3.),
            (1., 3., 4., 0.),
        ],
        'S' => &[
            (4., 6., 0., 6.),
            (0., 6., 0., 3.),
            (0., 3., 4., 3.),
            (4., 3., 4., 0.),
            (4., 0., 0., 0.),
        ],
        'T' => &[(0., 6., 4., 6.), (2., 6., 2., 0.)],
        'U' => &[(0., 6., 0., 0.), (0., 0., 4., 0.), (4., 0., 4., 6.)],
        'V' => &[(0., 6., 2., 0.), (2., 0., 4., 6.)],
        'W' => &[
            (0., 6., 1., 0.),
            (1., 0., 2., 3.),
            (2., 3., 3., 0.),
            (3., 0., 4., 6.),
        ],
        'X' => &[(0., 0., 4., 6.), (0., 6., 4., 0.)],
        'Y' => &[(0., 6., 2., 3.), (4., 6., 2., 3.), (2., 3., 2., 0.)],
        'Z' => &[(0., 6., 4., 6.), (4., 6., 0., 0.), (0., 0., 4., 0.)],
        _ => return None,
    })
}

/// Whether `c` has a glyph.
pub fn has_glyph(c: char) -> bool {
    glyph(c).is_some()
}

fn segment_distance(p: DVec2, a: DVec2, b: DVec2) -> f64 {
    let ab = b - a;
    let t = ((p - a).dot(ab) / ab.length_squared().max(1e-30)).clamp(0.0, 1.0);
    p.distance(a + ab * t)
}

/// Planar text `height` tall with strokes `stroke` wide (round caps), letters spaced
/// by one stroke, centred on the origin in the xy plane. Rasterised at a sixth of the
/// stroke and meshed as one rectangle per run of filled cells, so strokes that cross
/// never overlap (no doubled albedo). Returns `None` for a character without a glyph.
pub fn text(text: &str, height: f64, stroke: f64) -> Option<Mesh> {
    let scale = (height - stroke) / 6.0;
    let advance = 4.0 * scale + 2.0 * stroke;
    let width = advance * text.chars().count() as f64 - stroke;
    let mut segments = Vec::new();
    for (k, c) in text.chars().enumerate() {
        let x0 = k as f64 * advance + 0.5 * stroke - 0.5 * width;
        for &(ax, ay, bx, by) in glyph(c)? {
            let at = |x: f64, y: f64| DVec2::new(x0 + x * scale, 0.5 * stroke + y * scale - 0.5 * height);
            segments.push((at(ax, ay), at(bx, by)));
        }
    }
    let cell = stroke / 6.0;
    let (nx, ny) = ((width / cell).ceil() as usize, (height / cell).ceil() as usize);
    let mut mesh = Mesh::default();
    for j in 0..ny {
        let y = -0.5 * height + (j as f64 + 0.5) * cell;
        let filled = |i: usize| {
            let p = DVec2::new(-0.5 * width + (i as f64 + 0.5) * cell, y);
            segments
                .iter()
                .any(|(a, b)| segment_distance(p, *a, *b) <= 0.5 * stroke)
        };
        let mut i = 0;
        while i < nx {
            if filled(i) {
                let start = i;
                while i < nx && filled(i) {
                    i += 1;
                }
                let x = |k: usize| -0.5 * width + k as f64 * cell;
                let y0 = -0.5 * height + j as f64 * cell;
                mesh.append(&Mesh::rectangle([x(start), x(i)], [y0, y0 + cell]));
            } else {
                i += 1;
            }
        }
    }
    Some(mesh)
}

/// The resolution target: `count` bars `width` × `length` (length along y) with `gap`
/// between them, centred on the origin.
pub fn bars(count: usize, width: f64, length: f64, gap: f64) -> Mesh {
    let total = count as f64 * width + (count.saturating_sub(1)) as f64 * gap;
    let mut mesh = Mesh::default();
    for k in 0..count {
        let x0 = -0.5 * total + k as f64 * (width + gap);
        mesh.append(&Mesh::rectangle([x0, x0 + width], [-0.5 * length, 0.5 * length]));
    }
    mesh
}

/// A child-like mannequin `height` tall (about 1 m for a small child) from ellipsoids
/// and cylinders, feet at y = 0, facing +z.
pub fn mannequin(height: f64) -> Mesh {
    let s = height;
    let mut m = Mesh::default();
    let place = |mesh: Mesh, at: DVec3| mesh.transformed(DMat3::IDENTITY, at * s);
    m.append(&place(
        Mesh::ellipsoid(DVec3::new(0.075, 0.095, 0.085) * s, 24),
        DVec3::new(0.0, 0.88, 0.0),
    ));
    m.append(&place(
        Mesh::ellipsoid(DVec3::new(0.13, 0.2, 0.075) * s, 24),
        DVec3::new(0.0, 0.57, 0.0),
    ));
    for side in [-1.0, 1.0] {
        m.append(&Mesh::cylinder(
            DVec3::new(0.14 * side, 0.72, 0.0) * s,
            DVec3::new(0.21 * side, 0.40, 0.02) * s,
            0.035 * s,
            16,
        ));
        m.append(&Mesh::cylinder(
            DVec3::new(0.065 * side, 0.42, 0.0) * s,
            DVec3::new(0.075 * side, 0.0, 0.0) * s,
            0.048 * s,
            16,
        ));
    }
    m
}

/// A flat panel `size[0]` × `size[1]` facing +z, `segments` quads along its width.
pub fn plane(size: [f64; 2]) -> Mesh {
    Mesh::rectangle([-0.5 * size[0], 0.5 * size[0]], [-0.5 * size[1], 0.5 * size[1]])
}

/// A panel displaced along z by `profile(s)`, s ∈ [−½, ½] across the undulating axis
/// (x when `horizontal`, else y).
fn panel(size: [f64; 2], segments: usize, horizontal: bool, profile: impl Fn(f64) -> f64) -> Mesh {
    let (nu, nv) = if horizontal { (segments, 1) } else { (1, segments) };
    Mesh::parametric(nu, nv, |u, v| {
        let (x, y) = ((u - 0.5) * size[0], (v - 0.5) * size[1]);
        let s = if horizontal { u - 0.5 } else { v - 0.5 };
        DVec3::new(x, y, profile(s))
    })
}

/// An S-shaped panel: z = amplitude·sin(2π·periods·s).
pub fn s_panel(size: [f64; 2], amplitude: f64, periods: f64, horizontal: bool, segments: usize) -> Mesh {
    panel(size, segments, horizontal, |s| {
        amplitude * (2.0 * PI * periods * s).sin()
    })
}

/// A C-shaped panel curving toward +z at its edges: z = amplitude·(2s)², so its
/// centre is `amplitude` behind its edges.
pub fn c_panel(size: [f64; 2], amplitude: f64, horizontal: bool, segments: usize) -> Mesh {
    panel(size, segments, horizontal, |s| amplitude * (2.0 * s).powi(2))
}

/// Two human-back-like surfaces side by side: each the rear half of a tapered
/// elliptic cylinder `width` wide, `depth` deep and `height` tall, their centres
/// `spacing` apart along x, bulging toward +z.
pub fn torso_pair(width: f64, depth: f64, height: f64, spacing: f64, segments: usize) -> Mesh {
    let mut m = Mesh::default();
    for side in [-0.5, 0.5] {
        let back = Mesh::parametric(segments, segments, |u, v| {
            let phi = (u - 0.5) * 0.85 * PI;
            let y = (v - 0.5) * height;
            // Shoulders wider than the waist.
            let taper = 0.82 + 0.18 * (PI * v * 0.9).sin();
            DVec3::new(
                side * spacing + 0.5 * width * taper * phi.sin(),
                y,
                0.5 * depth * (phi.cos() - 1.0),
            )
        });
        m.append(&back);
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn letter_area_and_extent() {
        let t = text("T", 0.4, 0.06).unwrap();
        // Bar 0.4 wide-ish plus stem: area between the two strokes' sum and with caps.
        let area = t.total_area();
        let (w, h) = (4.0 * (0.4 - 0.06) / 6.0 + 0.06, 0.4);
        let stems = w * 0.06 + (h - 0.06) * 0.06;
        assert!((area - stems).abs() < 0.15 * stems, "area {area} vs {stems}");
        let (lo, hi) = t
            .vertices
            .iter()
            .fold((DVec3::splat(9.0), DVec3::splat(-9.0)), |(a, b), v| {
                (a.min(*v), b.max(*v))
            });
        assert!(
            (hi.y - lo.y - 0.4).abs() < 0.02 && (lo.y + hi.y).abs() < 0.02,
            "{lo:?} {hi:?}"
        );
        assert!(text("T€", 0.4, 0.06).is_none());
    }

    #[test]
    fn bars_are_the_papers_target() {
        let b = bars(3, 0.02, 0.30, 0.02);
        assert!((b.total_area() - 3.0 * 0.02 * 0.30).abs() < 1e-12);
        assert!(mannequin(1.0).triangles.len() > 1000);
    }
}

//! Regions of the relay where the instrument may illuminate or detect.
use glam::{DVec2, DVec3};

use crate::linalg::FittedPlane;

/// A selection of relay points.
#[derive(Clone, Debug, PartialEq)]
pub enum Region {
    /// Every point.
    All,
    /// Points inside an axis-aligned box (inclusive), world frame.
    Box {
        /// Lower corner.
        min: DVec3,
        /// Upper corner.
        max: DVec3,
    },
    /// Points whose projection onto `plane` falls inside a polygon given in the plane's
    /// (u, v) coordinates, metres from its centre (even-odd rule; any simple polygon).
    Polygon {
        /// The plane, usually fitted to the relay.
        plane: FittedPlane,
        /// Vertices in order, at least three.
        vertices: Vec<DVec2>,
    },
    /// Points whose label (one per point, e.g. from a segmentation or a scan mask) is
    /// one of `keep`.
    Labels {
        /// One label per point, in point order.
        labels: Vec<u32>,
        /// Accepted labels.
        keep: Vec<u32>,
    },
}

impl Region {
    /// Whether point `index` at `p` is selected.
    pub fn contains(&self, index: usize, p: DVec3) -> bool {
        match self {
            Region::All => true,
            Region::Box { min, max } => p.cmpge(*min).all() && p.cmple(*max).all(),
            Region::Polygon { plane, vertices } => {
                let d = p - plane.centre;
                inside_polygon(DVec2::new(d.dot(plane.u), d.dot(plane.v)), vertices)
            }
            Region::Labels { labels, keep } => labels.get(index).is_some_and(|l| keep.contains(l)),
        }
    }

    /// Indices of the selected points.
    pub fn select(&self, points: &[DVec3]) -> Vec<usize> {
        points
            .iter()
            .enumerate()
            .filter(|(i, p)| self.contains(*i, **p))
            .map(|(i, _)| i)
            .collect()
    }
}

/// Even-odd point-in-polygon test.
fn inside_polygon(q: DVec2, vertices: &[DVec2]) -> bool {
    if vertices.len() < 3 {
        return false;
    }
    let mut inside = false;
    let mut j = vertices.len() - 1;
    for i in 0..vertices.len() {
        let (a, b) = (vertices[i], vertices[j]);
        if (a.y > q.y) != (b.y > q.y) && q.x < (b.x - a.x) * (q.y - a.y) / (b.y - a.y) + a.x {
            inside = !inside;
        }
        j = i;
    }
    inside
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn polygon_and_box_selection() {
        let plane = FittedPlane {
            centre: DVec3::ZERO,
            normal: DVec3::Z,
            u: DVec3::X,
            v: DVec3::Y,
            rms: 0.0,
        };
        // An L shape.
        let l = Region::Polygon {
            plane,
            vertices: [
                (0.0, 0.0),
                (2.0, 0.0),
                (2.0, 1.0),
                (1.0, 1.0),
                (1.0, 2.0),
                (0.0, 2.0),
            ]
            .map(|(x, y)| DVec2::new(x, y))
            .to_vec(),
        };
        assert!(l.contains(0, DVec3::new(0.5, 1.5, 3.0)));
        assert!(!l.contains(0, DVec3::new(1.5, 1.5, 0.0)));
        let b = Region::Box {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        assert_eq!(b.select(&[DVec3::splat(0.5), DVec3::splat(1.5)]), vec![0]);
        let labels = Region::Labels {
            labels: vec![1, 2, 1],
            keep: vec![1],
        };
        assert_eq!(labels.select(&[DVec3::ZERO; 4]), vec![0, 2]);
    }
}

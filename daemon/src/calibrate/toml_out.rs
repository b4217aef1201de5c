//! The calibrated instrument config: the input file with each arm's `origin`,
//! `boresight` and `up` replaced, everything else (comments, order, other tables)
//! kept byte for byte. `toml_edit` edits the document in place, keeping each value's
//! surrounding whitespace and trailing comment.
use glam::DVec3;
use periscope_drivers::GalvoPose;
use toml_edit::{Array, DocumentMut, Item, Value};

use super::{CalibrateError, Geometry};

/// `text` (an instrument config) with the arms' poses set to `fitted`'s.
pub fn calibrated_toml(text: &str, fitted: &Geometry) -> Result<String, CalibrateError> {
    let mut doc: DocumentMut = text
        .parse()
        .map_err(|e| CalibrateError::Output(format!("the instrument config does not parse: {e}")))?;
    for (arm, pose) in [("laser", &fitted.laser), ("spad", &fitted.spad)] {
        let table = doc
            .get_mut("galvo")
            .and_then(|g| g.get_mut(arm))
            .and_then(Item::as_table_like_mut)
            .ok_or_else(|| CalibrateError::Output(format!("it has no [galvo.{arm}] table")))?;
        for (key, v, digits) in vectors(pose) {
            let mut value = Value::Array(array(v, digits));
            match table.get_mut(key).and_then(Item::as_value_mut) {
                Some(old) => {
                    *value.decor_mut() = old.decor().clone();
                    *old = value;
                }
                None => {
                    table.insert(key, Item::Value(value));
                }
            }
        }
    }
    Ok(doc.to_string())
}

/// The keys written, their vectors and the decimals kept: a micrometre for the origin,
/// about a nanoradian for the unit vectors.
fn vectors(pose: &GalvoPose) -> [(&'static str, DVec3, i32); 3] {
    [
        ("origin", pose.origin, 6),
        ("boresight", pose.rotation.z_axis, 9),
        ("up", pose.rotation.y_axis, 9),
    ]
}

fn array(v: DVec3, digits: i32) -> Array {
    let scale = 10f64.powi(digits);
    // `+ 0.0` turns a rounded −0 into 0.
    let mut a: Array = v
        .to_array()
        .iter()
        .map(|c| (c * scale).round() / scale + 0.0)
        .collect();
    a.fmt();
    a
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::calibrate::Plane;

    const SIM: &str = include_str!("../../../configs/instrument/sim.toml");

    fn geometry() -> Geometry {
        Geometry {
            laser: GalvoPose::looking(
                DVec3::new(-0.1012, 0.0004, 2.003),
                DVec3::new(0.002, 0.0, -1.0),
                DVec3::new(-0.001, 1.0, 0.0),
            )
            .unwrap(),
            spad: GalvoPose::looking(
                DVec3::new(0.1, 0.0, 1.9985),
                DVec3::new(0.0, -0.001, -1.0),
                DVec3::new(0.003, 1.0, 0.0),
            )
            .unwrap(),
            target: Plane {
                point: DVec3::ZERO,
                normal: DVec3::Z,
            },
        }
    }

    #[test]
    fn only_the_poses_change() {
        let out = calibrated_toml(SIM, &geometry()).unwrap();
        // The SPAD arm had no `up`: it is added (at the end of its table).
        let added: Vec<&str> = out.lines().filter(|l| l.starts_with("up = [0.00299")).collect();
        assert_eq!(added.len(), 1, "{out}");
        let kept: Vec<&str> = out.lines().filter(|l| *l != added[0]).collect();
        assert_eq!(kept.len(), SIM.lines().count());
        let changed: Vec<(&str, &str)> = SIM.lines().zip(kept).filter(|(a, b)| a != b).collect();
        // origin, boresight and up of the laser arm; origin and boresight of the SPAD.
        assert_eq!(changed.len(), 5, "{changed:#?}");
        for (old, new) in &changed {
            let key = new.split('=').next().unwrap().trim();
            assert!(["origin", "boresight", "up"].contains(&key), "{new}");
            assert_eq!(old.split('=').next(), new.split('=').next());
        }
        // Trailing comments stay.
        assert!(
            out.contains("origin = [-0.1012, 0.0004, 2.003]  # metres, world frame"),
            "{out}"
        );
    }

    #[test]
    fn the_written_config_loads_with_the_fitted_poses() {
        let g = geometry();
        let out = calibrated_toml(SIM, &g).unwrap();
        let c = crate::config::InstrumentConfig::from_source(&crate::config::TomlSource::from_text(
            "cal.toml", &out,
        ))
        .unwrap();
        for (got, want) in [(c.laser_arm.pose, g.laser), (c.spad_arm.pose, g.spad)] {
            assert!((got.origin - want.origin).length() < 1e-6);
            assert!(crate::calibrate::rotation_between(got.rotation, want.rotation) < 1e-8);
        }
    }

    #[test]
    fn a_config_without_arms_is_refused() {
        let err = calibrated_toml("name = \"x\"\n", &geometry()).unwrap_err();
        assert!(err.to_string().contains("[galvo.laser]"), "{err}");
    }
}

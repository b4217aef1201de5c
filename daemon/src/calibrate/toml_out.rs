//! The calibrated instrument config: the input file with each arm's `origin`,
//! `boresight` and `up` replaced, everything else (comments, order, other tables)
//! kept byte for byte. `toml_edit` edits the document in place, keeping each value's
//! surrounding whitespace and trailing comment.
use std::path::Path;

use glam::DVec3;
use periscope_drivers::GalvoPose;
use toml_edit::{Array, DocumentMut, Item, Value};

use super::{CalibrateError, Geometry};

/// `text` (an instrument config read from `from`) with the arms' poses set to
/// `fitted`'s, to be written at `to`. A relative `sim.scene` (the one path a config
/// resolves against its own folder) is rewritten to resolve from `to` as it did from
/// `from`: kept where both are in one folder, else made absolute; from the built-in
/// config (no file), left out where it names no file from `to` (the built-in scene,
/// as the built-in config used).
pub fn calibrated_toml(
    text: &str,
    fitted: &Geometry,
    from: &Path,
    to: &Path,
) -> Result<String, CalibrateError> {
    let mut doc: DocumentMut = text
        .parse()
        .map_err(|e| CalibrateError::Output(format!("the instrument config does not parse: {e}")))?;
    let folder = |p: &Path| {
        let f = p.parent().unwrap_or(Path::new(""));
        let f = if f.as_os_str().is_empty() {
            Path::new(".")
        } else {
            f
        };
        std::fs::canonicalize(f).unwrap_or_else(|_| f.to_owned())
    };
    // A config held in memory (the built-in default) has no folder: its scene is the
    // built-in one wherever its relative path does not resolve, and so is the written
    // config's (no `scene` key) unless the path resolves from where it is written.
    if !from.is_file()
        && let Some(sim) = doc.get_mut("sim").and_then(Item::as_table_like_mut)
        && let Some(rel) = sim
            .get("scene")
            .and_then(Item::as_str)
            .map(std::path::PathBuf::from)
        && rel.is_relative()
        && !folder(to).join(&rel).is_file()
    {
        sim.remove("scene");
    }
    if let Some(scene) = doc
        .get_mut("sim")
        .and_then(|s| s.get_mut("scene"))
        .and_then(Item::as_value_mut)
        && let Some(rel) = scene.as_str().map(std::path::PathBuf::from)
        && rel.is_relative()
        && from.is_file()
        && folder(from) != folder(to)
    {
        let resolved = folder(from).join(&rel);
        let resolved = std::fs::canonicalize(&resolved).unwrap_or(resolved);
        let resolved = resolved.to_str().ok_or_else(|| {
            CalibrateError::Output(format!("sim.scene {} is not a UTF-8 path", resolved.display()))
        })?;
        let mut value = Value::from(resolved);
        *value.decor_mut() = scene.decor().clone();
        *scene = value;
    }
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

    /// Where `SIM` comes from.
    fn sim_toml() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/instrument/sim.toml")
    }

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
        let out = calibrated_toml(
            SIM,
            &geometry(),
            &sim_toml(),
            &sim_toml().with_file_name("cal.toml"),
        )
        .unwrap();
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
        let out = calibrated_toml(SIM, &g, &sim_toml(), &sim_toml().with_file_name("cal.toml")).unwrap();
        let c = crate::config::InstrumentConfig::from_source(&crate::config::TomlSource::from_text(
            "cal.toml", &out,
        ))
        .unwrap();
        for (got, want) in [(c.laser_arm.pose, g.laser), (c.spad_arm.pose, g.spad)] {
            assert!((got.origin - want.origin).length() < 1e-6);
            assert!(crate::calibrate::rotation_between(got.rotation, want.rotation) < 1e-8);
        }
    }

    /// Written to another folder, the config's relative scene still names the same
    /// file; written beside its source, it is left as it was.
    #[test]
    fn a_relative_scene_resolves_from_where_the_config_is_written() {
        let repo = Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
        let from = repo.join("configs/instrument/sim.toml");
        let elsewhere = tempfile::tempdir().unwrap();
        let to = elsewhere.path().join("calibrated.toml");
        let out = calibrated_toml(SIM, &geometry(), &from, &to).unwrap();
        let c =
            crate::config::InstrumentConfig::from_source(&crate::config::TomlSource::from_text(&to, &out))
                .unwrap();
        let crate::config::Backend::Sim(sim) = c.backend else {
            panic!("the simulated instrument")
        };
        let scene = sim.scene.expect("a scene file");
        assert_eq!(
            std::fs::canonicalize(scene).unwrap(),
            std::fs::canonicalize(repo.join("configs/scenes/wall-letter.toml")).unwrap()
        );
        assert!(
            out.contains("wall-letter.toml\"   # relative to this file"),
            "{out}"
        );
        let beside = calibrated_toml(SIM, &geometry(), &from, &from.with_file_name("cal.toml")).unwrap();
        assert!(
            beside.contains("scene = \"../scenes/wall-letter.toml\""),
            "{beside}"
        );
        // From the built-in config (no file): the scene it could not find is left out,
        // so the written config takes the built-in scene as the built-in one did.
        let built_in = Path::new("configs/instrument/sim.toml (built in)");
        let out = calibrated_toml(SIM, &geometry(), built_in, &to).unwrap();
        assert!(!out.contains("scene ="), "{out}");
        std::fs::write(&to, &out).unwrap();
        let c = crate::config::InstrumentConfig::load(&to).unwrap();
        let crate::config::Backend::Sim(sim) = c.backend else {
            panic!("the simulated instrument")
        };
        assert_eq!(sim.scene, None);
    }

    #[test]
    fn a_config_without_arms_is_refused() {
        let err = calibrated_toml(
            "name = \"x\"\n",
            &geometry(),
            Path::new("x.toml"),
            Path::new("y.toml"),
        )
        .unwrap_err();
        assert!(err.to_string().contains("[galvo.laser]"), "{err}");
    }
}

//! Each public format's fixture (recon/tests/data/public-formats.py, written by the
//! writers the format comes from) holds one point target; each transient's peak holds
//! a count naming its relay point and lies in the bin of its path. A swapped or
//! mirrored axis, a wrong time origin, bin width or bounce puts a count where the
//! geometry says nothing is, and fails here.
use std::path::{Path, PathBuf};

use glam::DVec3;

use super::*;
use crate::io::ytal::HFormat;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(name)
}

/// Checks every transient of `c`: its largest bin holds `count(c)` and lies where the
/// path through `target` falls (a path within a micrometre of a bin edge may fall on
/// either side: the fixtures' positions are stored in single precision).
fn lands_on_the_target(c: &YtalCapture, target: DVec3, count: impl Fn(usize) -> f32) {
    for k in 0..c.len() {
        let p = c.pair(k);
        let bins: Vec<f32> = c.transient(k).collect();
        let (peak, &v) = bins.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap();
        assert_eq!(v, count(k), "transient {k} ({p:?})");
        let path = p.xi.distance(target) + p.xd.distance(target);
        let at = (path - c.hidden_start(k)) / c.delta_t;
        let near = [(at - 1e-6 / c.delta_t).floor(), (at + 1e-6 / c.delta_t).floor()];
        assert!(
            near.contains(&(peak as f64)),
            "transient {k}: peak in bin {peak}, the path {path} m falls in bin {at}"
        );
    }
}

#[test]
fn znlos_confocal_sums_the_third_bounce_on_and_takes_the_legs_out() {
    let c = read_capture(&fixture("znlos-point.hdf5")).unwrap();
    assert_eq!(c.h_shape, vec![640, 6, 8]);
    assert_eq!(c.h_format, HFormat::TSxSy);
    assert!(c.t_accounts_first_and_last_bounces);
    let target = DVec3::new(0.1, -0.5, 0.05);
    lands_on_the_target(&c, target, |k| (100 + 10 * (k / 8) + k % 8) as f32);
    for k in 0..c.len() {
        let p = c.pair(k);
        assert_eq!(p.xi, p.xd, "confocal");
        assert_eq!(p.nd, DVec3::NEG_Y);
        let (i, j) = (k / 8, k % 8);
        assert!((p.xd.x - (-0.35 + 0.7 * j as f64 / 7.0)).abs() < 1e-6, "{p:?}");
        assert!((p.xd.z - (-0.25 + 0.5 * i as f64 / 5.0)).abs() < 1e-6, "{p:?}");
        // The 3rd bounce and the 4th (7 counts), never the wall's own 2nd (5000).
        let sum: f32 = c.transient(k).sum();
        assert_eq!(sum, (100 + 10 * i + j) as f32 + 7.0, "transient {k}");
    }
    let row_major = read_capture(&fixture("znlos-point-rowmajor.hdf5")).unwrap();
    assert_eq!(
        row_major.h, c.h,
        "a row-major file reads as its column-major twin"
    );
    assert_eq!(row_major.sensor_grid, c.sensor_grid);
}

#[test]
fn znlos_exhaustive_pairs_every_laser_point_with_every_camera_point() {
    let c = read_capture(&fixture("znlos-exhaustive.hdf5")).unwrap();
    assert_eq!(c.h_format, HFormat::TLxLySxSy);
    assert_eq!(c.h_shape, vec![256, 2, 3, 3, 4]);
    lands_on_the_target(&c, DVec3::new(0.0, -0.4, 0.1), |k| {
        let (l, s) = (k / 12, k % 12);
        let (a, b, i, j) = (l / 3, l % 3, s / 4, s % 4);
        (1000 * i + 100 * j + 10 * a + b + 1) as f32
    });
    assert_eq!(c.laser_xyz, Some(DVec3::new(0.4, -1.1, 0.2).as_vec3().as_dvec3()));
}

#[test]
fn fk_rectifies_each_histogram_with_tofgrid_from_tof_mat() {
    let c = read_capture(&fixture("fk-point/meas_10min.mat")).unwrap();
    assert_eq!(c.h_format, HFormat::TSxSy);
    assert_eq!(c.h_shape[1..], [8, 8]);
    assert_eq!(
        c.h_shape[0],
        1024 - ((3000.0 + 37.0 * 7.0 + 11.0 * 7.0) / 32.0f64).floor() as usize
    );
    assert!((c.delta_t - C * 32e-12).abs() < 1e-15);
    lands_on_the_target(&c, DVec3::new(0.25, -0.1, 0.6), |k| {
        (100 + 10 * (k / 8) + k % 8) as f32
    });
    for k in 0..64 {
        let p = c.pair(k);
        let (y, x) = (k / 8, k % 8);
        assert!((p.xd.x - (-1.0 + 2.0 * x as f64 / 7.0)).abs() < 1e-12);
        assert!((p.xd.y - (-1.0 + 2.0 * y as f64 / 7.0)).abs() < 1e-12);
        assert_eq!(c.hidden_start(k), 0.0, "bin 0 is the wall");
    }
    // Without its tof.mat the measurement cannot be placed in time: refused, naming it.
    let dir = tempfile::tempdir().unwrap();
    let alone = dir.path().join("meas_10min.mat");
    std::fs::copy(fixture("fk-point/meas_10min.mat"), &alone).unwrap();
    let e = read_capture(&alone).unwrap_err().to_string();
    assert!(e.contains("tof.mat") && e.contains("tofgrid"), "{e}");
}

/// A MAT v5 f-k capture whose `tofgrid` holds 1e30 ps (finite, non-negative, and
/// far past any histogram): refused naming `tofgrid`, where the shift saturated its
/// cast and indexed past `meas`.
#[test]
fn an_fk_shift_past_any_histogram_is_refused_by_name() {
    let e = read_capture(&fixture("fk-hostile.mat")).unwrap_err().to_string();
    assert!(
        e.contains("tofgrid") && e.contains("do not belong together"),
        "{e}"
    );
}

#[test]
fn phasor_field_2019_dataset_struct_reads_every_laser_point() {
    let c = read_capture(&fixture("pf2019-point.mat")).unwrap();
    assert_eq!(c.h_format, HFormat::TLiSi);
    assert_eq!(c.h_shape, vec![1024, 30, 1]);
    assert_eq!(c.sensor_grid.points, vec![DVec3::new(0.05, 0.02, 0.0)]);
    assert_eq!(c.laser_xyz, Some(DVec3::new(0.3, 0.1, 1.5)));
    assert_eq!(c.sensor_xyz, Some(DVec3::new(-0.4, 0.0, 1.2)));
    lands_on_the_target(&c, DVec3::new(-0.1, 0.05, 0.5), |k| (100 + k) as f32);
    for (i, p) in c.laser_grid.points.iter().enumerate() {
        let (a, b) = (i / 5, i % 5);
        assert!(p.distance(DVec3::new(-0.25 + 0.1 * a as f64, -0.2 + 0.1 * b as f64, 0.0)) < 1e-12);
    }
}

#[test]
fn phasor_field_2020_rect_data_puts_the_spad_on_its_grid_point() {
    let c = read_capture(&fixture("pf2020-point.mat")).unwrap();
    assert_eq!(c.h_format, HFormat::TLxLySxSy);
    assert_eq!(c.h_shape, vec![1024, 16, 12, 1, 1]);
    let spacing = 0.025;
    let at = |i: usize, j: usize| DVec3::new((i as f64 - 7.5) * spacing, (j as f64 - 5.5) * spacing, 0.0);
    assert!(
        c.sensor_grid.points[0].distance(at(6, 4)) < 1e-12,
        "SPAD_index [7 5] is 1-based"
    );
    for k in 0..c.len() {
        assert!(c.pair(k).xi.distance(at(k / 12, k % 12)) < 1e-12);
    }
    lands_on_the_target(&c, DVec3::new(0.03, -0.02, 0.4), |k| {
        (100 + 10 * (k / 12) + k % 12) as f32
    });
}

/// An empty `sampling_spacing` (`[]`, stored in MAT v7.3 as its dims marked
/// `MATLAB_empty`) is absent, as in a v5 file: the pitch comes from
/// `aperturefullsize`. It was read as the two numbers of its dims and refused.
#[test]
fn an_empty_mat_v73_array_is_read_as_absent() {
    let c = read_capture(&fixture("pf2020-empty-spacing.mat")).unwrap();
    let whole = read_capture(&fixture("pf2020-point.mat")).unwrap();
    assert_eq!(c.laser_grid, whole.laser_grid);
    assert_eq!(c.sensor_grid, whole.sensor_grid);
    assert_eq!(c.h, whole.h);
}

#[test]
fn the_lct_release_layout_reads_through_the_same_entry() {
    let c = read_capture(&fixture("lct-point.mat")).unwrap();
    assert_eq!(c, crate::io::lct::read_lct(&fixture("lct-point.mat")).unwrap());
    lands_on_the_target(&c, DVec3::new(0.1, -0.05, 0.3), |k| {
        (100 + 10 * (k / 8) + k % 8) as f32
    });
}

/// An HDF5 file cut short is said to be damaged, not of a layout Periscope does not
/// read: until 2026-12-06 one cut inside its root group's records was refused with
/// "no variable of a capture format Periscope reads (it has: )".
#[test]
fn a_truncated_hdf5_file_is_called_damaged() {
    let whole = std::fs::read(fixture("znlos-point.hdf5")).unwrap();
    for len in [600, 1000, 2048, 4096] {
        let e = capture_from_bytes(whole[..len].to_vec(), Path::new("cut.hdf5"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("cut.hdf5")
                && (e.contains("damaged or truncated") || e.contains("beyond the end of the file"))
                && !e.contains("it has: )"),
            "{len} bytes: {e}"
        );
    }
}

#[test]
fn frequency_domain_and_unknown_layouts_are_refused_by_name() {
    let e = read_capture(&fixture("ytal-frequency.hdf5"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("F_Sx_Sy") && e.contains("frequency-domain") && e.contains("time domain"),
        "{e}"
    );
    let dir = tempfile::tempdir().unwrap();
    let text = dir.path().join("notes.mat");
    std::fs::write(&text, "no capture here").unwrap();
    let e = read_capture(&text).unwrap_err().to_string();
    assert!(e.contains("neither HDF5 nor a MATLAB"), "{e}");
    // A MATLAB file of none of the formats lists what it has.
    let bytes = std::fs::read(fixture("fk-point/tof.mat")).unwrap();
    let e = capture_from_bytes(bytes, Path::new("tof.mat"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("it has: tofgrid") && e.contains("docs/formats.md"),
        "{e}"
    );
}

// ---- Hostile MAT v5 files (a review, 2026-12-06), written byte by byte here --------

/// A MAT v5 data element: tag, data, padding to 8 bytes.
fn element(kind: u32, data: &[u8]) -> Vec<u8> {
    let mut e = kind.to_le_bytes().to_vec();
    e.extend_from_slice(&(data.len() as u32).to_le_bytes());
    e.extend_from_slice(data);
    e.resize(e.len().next_multiple_of(8), 0);
    e
}

/// A `miMATRIX` element: flags (class, complex), dims, name, then `parts` (the real
/// part's and imaginary part's elements, or nested arrays).
fn matrix(name: &str, class: u8, complex: bool, dims: &[i32], parts: &[Vec<u8>]) -> Vec<u8> {
    let mut body = Vec::new();
    let flags = u32::from(class) | if complex { 0x0800 } else { 0 };
    body.extend(element(6, &[flags.to_le_bytes(), 0u32.to_le_bytes()].concat()));
    body.extend(element(
        5,
        &dims.iter().flat_map(|d| d.to_le_bytes()).collect::<Vec<u8>>(),
    ));
    body.extend(element(1, name.as_bytes()));
    for p in parts {
        body.extend_from_slice(p);
    }
    element(14, &body)
}

fn doubles(v: &[f64]) -> Vec<u8> {
    element(9, &v.iter().flat_map(|x| x.to_le_bytes()).collect::<Vec<u8>>())
}

fn compressed(inner: &[u8]) -> Vec<u8> {
    use std::io::Write as _;
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    z.write_all(inner).unwrap();
    // Compressed elements are not padded (MATLAB writes them back to back).
    let data = z.finish().unwrap();
    let mut e = 15u32.to_le_bytes().to_vec();
    e.extend_from_slice(&(data.len() as u32).to_le_bytes());
    e.extend_from_slice(&data);
    e
}

/// A MAT v5 file of these top-level elements.
fn mat_v5(elements: &[Vec<u8>]) -> Vec<u8> {
    let mut f = vec![b' '; 116];
    f[..10].copy_from_slice(b"MATLAB 5.0");
    f.extend_from_slice(&[0; 8]);
    f.extend_from_slice(&[0x00, 0x01]);
    f.extend_from_slice(b"IM");
    for e in elements {
        f.extend_from_slice(e);
    }
    f
}

fn read_bytes(bytes: Vec<u8>) -> String {
    match capture_from_bytes(bytes, Path::new("hostile.mat")) {
        Ok(_) => panic!("a hostile file was read"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn hostile_mat_v5_structures_are_refused_by_name_before_they_are_parsed() {
    let width = matrix("width", 6, false, &[1, 1], &[doubles(&[0.3])]);
    let rect = matrix("rect_data", 6, false, &[2, 2, 2], &[doubles(&[1.0; 8])]);
    // A compressed element inside a compressed element: the parser would inflate it
    // without a bound, recursing once a level.
    let e = read_bytes(mat_v5(&[compressed(&compressed(&rect)), width.clone()]));
    assert!(e.contains("type 15, not a MATLAB array"), "{e}");
    // The same hidden after a well-formed array in one compressed element: the
    // parser read the bytes past the array as more top-level elements and inflated
    // them without a bound.
    let hidden = [rect.clone(), compressed(&compressed(&rect))].concat();
    let e = read_bytes(mat_v5(&[compressed(&hidden), width.clone()]));
    assert!(e.contains("more bytes after its MATLAB array"), "{e}");
    // One inside an array.
    let inner = matrix(
        "rect_data",
        6,
        false,
        &[2, 2, 2],
        &[compressed(&doubles(&[1.0; 8]))],
    );
    let e = read_bytes(mat_v5(&[compressed(&inner), width.clone()]));
    assert!(e.contains("compressed element inside an array"), "{e}");
    // Cells nested past the limit (iteratively walked: no stack to exhaust).
    let mut deep = matrix("", 6, false, &[1, 1], &[doubles(&[1.0])]);
    for _ in 0..200 {
        deep = matrix("", 1, false, &[1, 1], &[deep]);
    }
    let e = read_bytes(mat_v5(&[compressed(&deep), width.clone()]));
    assert!(e.contains("nest more than 64 deep"), "{e}");
    // Dims whose product wraps in 32 bits onto the values held (2 × 2^16 × (2^16 + 1)
    // ≡ 2^17): it allocated 34 GB for a phasor-field file of 2 KB.
    let wrap = matrix(
        "rect_data",
        6,
        false,
        &[2, 1 << 16, (1 << 16) + 1],
        &[doubles(&vec![1.0; 1 << 17])],
    );
    let ts = matrix("ts", 6, false, &[1, 1], &[doubles(&[4e-12])]);
    let e = read_bytes(mat_v5(&[compressed(&wrap), ts]));
    assert!(
        e.contains("but holds 131072 values") && e.contains("damaged"),
        "{e}"
    );
    // Complex counts: read as their real part before.
    let complex = matrix(
        "rect_data",
        6,
        true,
        &[2, 2, 2],
        &[doubles(&[1.0; 8]), doubles(&[5.0; 8])],
    );
    let e = read_bytes(mat_v5(&[compressed(&complex), width.clone()]));
    assert!(e.contains("`rect_data` is complex"), "{e}");
    // Text where a number belongs.
    let text = matrix("width", 4, false, &[1, 1], &[element(4, &[b'0', 0])]);
    let e = read_bytes(mat_v5(&[compressed(&rect), compressed(&text)]));
    assert!(e.contains("`width` is a char array"), "{e}");
    // A struct `dataset` (the phasor-field 2019 layout) in MAT v5: the documented
    // advice, not "no variable of a capture format (it has: )".
    let field = matrix("", 6, false, &[1, 1], &[doubles(&[1.0])]);
    let names = [element(5, &4i32.to_le_bytes()), element(1, b"t\0\0\0")].concat();
    let dataset = matrix("dataset", 2, false, &[1, 1], &[names, field]);
    let e = read_bytes(mat_v5(&[compressed(&dataset)]));
    assert!(e.contains("-v7.3"), "{e}");
    // A big-endian file: named, not "neither HDF5 nor a MATLAB .mat file".
    let mut be = mat_v5(&[]);
    be[124..128].copy_from_slice(&[0x01, 0x00, b'M', b'I']);
    let e = read_bytes(be);
    assert!(e.contains("big-endian"), "{e}");
    // The same file, well formed, reads.
    let ok = mat_v5(&[compressed(&rect), compressed(&width)]);
    assert!(capture_from_bytes(ok, Path::new("fine.mat")).is_ok());
    // A `width` past any relay: at 1e308 the grid's points were infinite (2·width
    // overflows) and read as a capture until 2026-12-07.
    for w in [1e308, 51.0] {
        let huge = matrix("width", 6, false, &[1, 1], &[doubles(&[w])]);
        let e = read_bytes(mat_v5(&[compressed(&rect), compressed(&huge)]));
        assert!(e.contains("`width` is") && e.contains("at most 50"), "{w}: {e}");
    }
}

#[test]
fn attributes_are_read_whatever_type_holds_them() {
    use hdf5_pure::AttrValue as A;
    for v in [
        A::F32Array(vec![2.0]),
        A::U8Array(vec![2]),
        A::I16Array(vec![2]),
        A::U16(2),
        A::U64Array(vec![2]),
    ] {
        assert_eq!(number_attr(&v), Some(2.0), "{v:?}");
    }
    assert_eq!(number_attr(&A::String("2".into())), None);
    for v in [
        A::AsciiString("row-major\0\0".into()),
        A::VarLenString("row-major".into()),
        A::AsciiStringArray(vec!["row-major".into()]),
        A::ascii_string_sized("row-major", 20).unwrap(),
    ] {
        assert_eq!(text_attr(&v).as_deref(), Some("row-major"), "{v:?}");
    }
}

#[test]
fn counts_past_what_single_precision_sums_hold_are_refused() {
    let e = check_counts(&[1.0, 3e38, 2.0], "rect_data").unwrap_err();
    assert!(e.contains("index 1") && e.contains("at most 1e30"), "{e}");
    assert!(check_counts(&[0.0, 1e30], "rect_data").is_ok());
}

/// The `scene_info` a format reader writes names the source file as a YAML
/// double-quoted scalar: a path holding `: ` or ` #` made PyYAML refuse the export of
/// an import run (`mapping values are not allowed`) or cut it short, until 2026-12-07.
#[test]
fn the_source_path_in_scene_info_is_one_quoted_yaml_scalar() {
    let dir = tempfile::tempdir().unwrap();
    let odd = dir.path().join("bench: take 2 #3.hdf5");
    std::fs::copy(fixture("znlos-point.hdf5"), &odd).unwrap();
    let c = read_capture(&odd).unwrap();
    let info = c.scene_info.expect("a scene_info");
    let value = info.strip_prefix("source: \"").expect(&info);
    assert!(
        value.ends_with('"') && !value[..value.len() - 1].contains('"'),
        "{info}"
    );
    assert!(value.contains("bench: take 2 #3.hdf5"), "{info}");
    assert!(!info.contains('\n'), "one line: {info}");
}

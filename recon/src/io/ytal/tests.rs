//! Unit tests of the y-tal reader and writer: a capture round-trips through a file,
//! transients are indexed and timed as y-tal lays them out, and files that are not
//! captures, or captures whose parts do not fit together, are refused by name.
use glam::DVec3;
use hdf5_pure::FileBuilder;

use super::*;
use crate::volume::VolumeGrid;

fn sample() -> YtalCapture {
    let points: Vec<DVec3> = (0..6)
        .map(|i| DVec3::new(0.1 * i as f64, -0.05 * i as f64, 0.0))
        .collect();
    let grid = |points: Vec<DVec3>, shape: Vec<usize>, format| Grid {
        normals: vec![DVec3::Z; points.len()],
        points,
        format,
        shape,
    };
    YtalCapture {
        h: (0..5 * 6 * 2).map(|v| v as f32 * 0.5).collect(),
        h_shape: vec![5, 2, 6],
        h_format: HFormat::TLiSi,
        sensor_grid: grid(points.clone(), vec![2, 3], GridFormat::XY3),
        laser_grid: grid(points[..2].to_vec(), vec![2], GridFormat::N3),
        sensor_xyz: Some(DVec3::new(0.2, 0.0, 1.0)),
        laser_xyz: None,
        delta_t: 0.004,
        t_start: 1.5,
        t_accounts_first_and_last_bounces: false,
        scene_info: Some("original_format: test\n".into()),
        flags: Some(vec![0, 1, 2, 3, 0, 0, 0, 0, 0, 0, 0, 0]),
    }
}

/// Six points scanned confocally (`T_Si`), `bins` bins of 1 cm from `t_start`
/// holding `h`, no flags, legs not in the times.
fn confocal_six(bins: usize, t_start: f64, h: Vec<f32>) -> YtalCapture {
    let c = sample();
    YtalCapture {
        h_format: HFormat::TSi,
        h_shape: vec![bins, 6],
        laser_grid: c.sensor_grid.clone(),
        delta_t: 0.01,
        t_start,
        h,
        flags: None,
        ..c
    }
}

#[test]
fn a_rendered_capture_is_told_from_its_scene_info() {
    let with = |info: Option<&str>| YtalCapture {
        scene_info: info.map(str::to_string),
        ..sample()
    };
    // The validation harness's mitransient captures.
    let harness = "description: a letter\nrenderer: 'mitransient 1.3.1 / mitsuba 3.9.1'\nspp: 262144\n";
    assert_eq!(
        with(Some(harness)).rendered_by().as_deref(),
        Some("mitransient 1.3.1 / mitsuba 3.9.1")
    );
    // `tal render`'s, as PyYAML dumps them (keys sorted, the config a mapping).
    let tal = "args:\n  threads: 2\nconfig:\n  laser_x: -0.5\n  scan_type: confocal\ntal_version: 0.20.0\n";
    assert_eq!(
        with(Some(tal)).rendered_by().as_deref(),
        Some("y-tal's `tal render`")
    );
    // Measured or exported captures, and keys that only mention a renderer.
    for info in [
        None,
        Some(""),
        Some("original_format: periscope\nrun: 'x'\n"),
        Some("original_format: HDF5_ZNLOS\nvolume:\n  config: 1\n"),
        Some("notes: the renderer: was not used\n"),
    ] {
        assert_eq!(with(info).rendered_by(), None, "{info:?}");
    }
}

#[test]
fn a_written_capture_reads_back_identically() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.hdf5");
    let c = sample();
    c.write(&path).unwrap();
    let back = YtalCapture::read(&path).unwrap();
    // Points go through f32 in the file, as y-tal stores them.
    let round = |g: &Grid| Grid {
        points: g.points.iter().map(|p| p.as_vec3().as_dvec3()).collect(),
        ..g.clone()
    };
    assert_eq!(back.sensor_grid, round(&c.sensor_grid));
    assert_eq!(back.laser_grid, round(&c.laser_grid));
    assert_eq!(back.h, c.h);
    assert_eq!(back.h_shape, c.h_shape);
    assert_eq!(back.h_format, c.h_format);
    assert_eq!(back.laser_xyz, None);
    assert_eq!(back.sensor_xyz, c.sensor_xyz.map(|p| p.as_vec3().as_dvec3()));
    assert_eq!((back.delta_t, back.t_start), (c.delta_t, c.t_start));
    assert!(!back.t_accounts_first_and_last_bounces);
    assert_eq!(back.scene_info, c.scene_info);
}

/// The legs in the times, with both origins, and normals off the axes: the flag, the
/// origins and the normals (through f32, renormalised) read back as written, and with
/// them each transient's hidden start.
#[test]
fn a_capture_with_its_legs_and_tilted_normals_reads_back_as_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("legs.hdf5");
    let mut c = sample();
    c.t_accounts_first_and_last_bounces = true;
    c.laser_xyz = Some(DVec3::new(-0.3, 0.1, 1.2));
    let tilt = DVec3::new(0.3, -0.2, 1.0).normalize();
    c.sensor_grid.normals = vec![tilt; c.sensor_grid.points.len()];
    c.write(&path).unwrap();
    let back = YtalCapture::read(&path).unwrap();
    assert!(back.t_accounts_first_and_last_bounces);
    assert_eq!(back.laser_xyz, c.laser_xyz.map(|p| p.as_vec3().as_dvec3()));
    for n in &back.sensor_grid.normals {
        assert!(n.distance(tilt) < 1e-6, "{n} against {tilt}");
    }
    for i in 0..c.len() {
        assert!(
            (back.hidden_start(i) - c.hidden_start(i)).abs() < 1e-6,
            "transient {i}"
        );
    }
}

/// What the reader would refuse is not written (until 2026-12-07 the writer checked
/// nothing: flags of the wrong length wrote a file our own reader refuses, an empty
/// shape panicked), and nothing is left under the name.
#[test]
fn a_capture_that_does_not_fit_together_is_not_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.hdf5");
    let mut flags = sample();
    flags.flags = Some(vec![0; 3]);
    let mut legs = sample();
    legs.t_accounts_first_and_last_bounces = true;
    let mut shapeless = sample();
    shapeless.h_shape.clear();
    for (c, says) in [(flags, "flags"), (legs, "laser_xyz"), (shapeless, "no shape")] {
        let e = c.write(&path).unwrap_err().to_string();
        assert!(
            e.contains("bad.hdf5") && e.contains("not written") && e.contains(says),
            "{e}"
        );
        assert!(!path.exists());
    }
}

#[test]
fn transients_are_indexed_laser_major_and_time_first() {
    let c = sample();
    // H is (T=5, L=2, S=6): transient c = l·6 + s, value at (t, c) = h[t·12 + c].
    assert_eq!(c.indices(7), (1, 1));
    let t: Vec<f32> = c.transient(7).collect();
    assert_eq!(t, (0..5).map(|k| (k * 12 + 7) as f32 * 0.5).collect::<Vec<_>>());
    assert_eq!(c.pair(7).xi, c.laser_grid.points[1]);
    assert_eq!(c.pair(7).xd, c.sensor_grid.points[1]);
}

#[test]
fn legs_are_subtracted_when_the_file_includes_them() {
    let mut c = sample();
    c.t_accounts_first_and_last_bounces = true;
    c.laser_xyz = Some(DVec3::new(0.0, 0.0, 1.0));
    let p = c.pair(3);
    let legs = p.xi.distance(c.laser_xyz.unwrap()) + p.xd.distance(c.sensor_xyz.unwrap());
    assert!((c.hidden_start(3) - (1.5 - legs)).abs() < 1e-12);
    c.laser_xyz = None;
    assert!(c.check().unwrap_err().contains("laser_xyz"));
}

/// The hidden axis stops where the file's recording does: a volume whose far paths
/// reach beyond the time window gets no bins past it (they would be zeros nobody
/// measured), the recorded counts all land on the axis, and a volume the window
/// does not reach is refused with the file and the remedy named.
#[test]
fn the_hidden_axis_keeps_to_the_recorded_window() {
    // 64 bins of 1 cm from 0.5 m: paths 0.5 to 1.14 m, seen confocally from six
    // points with no legs in the times.
    let c = confocal_six(64, 0.5, (0..64 * 6).map(|v| (v % 7) as f32).collect());
    c.check().unwrap();
    // Paths from 2 × 0.2 m to past 2 m: beyond the recording at both ends.
    let deep = VolumeGrid::new([-0.3, 0.3], [-0.3, 0.3], [0.2, 1.0], [8, 8, 8]).unwrap();
    let set = c.transients(&deep).unwrap();
    let axis = *set.axis();
    assert!(axis.start >= 0.5 - 1e-9, "{axis:?}");
    assert!(axis.end() <= 1.14 + 1e-9, "{axis:?}");
    assert_eq!(axis.bins, 64, "every recorded bin is kept: {axis:?}");
    let recorded: f64 = c.h.iter().map(|&v| f64::from(v)).sum();
    let kept: f64 = (0..set.len())
        .map(|i| set.histogram(i).iter().map(|&v| f64::from(v)).sum::<f64>())
        .sum();
    assert!(
        (kept - recorded).abs() < 1e-6 * recorded,
        "{kept} of {recorded} counts"
    );
    // A volume 3 m away: its paths start beyond the recording's end.
    let far = VolumeGrid::new([-0.3, 0.3], [-0.3, 0.3], [3.0, 3.5], [8, 8, 8]).unwrap();
    let e = c.transients(&far).unwrap_err().to_string();
    assert!(e.contains("do not reach") && e.contains("[volume]"), "{e}");
}

#[test]
fn mismatched_grids_are_refused_with_the_dataset_named() {
    let mut c = sample();
    c.h_format = HFormat::TSi;
    c.h_shape = vec![5, 12];
    let e = c.check().unwrap_err();
    assert!(e.contains("sensor_grid_xyz") && e.contains("12"), "{e}");
    let mut c = sample();
    c.laser_grid.points.push(DVec3::ZERO);
    c.laser_grid.normals.push(DVec3::Z);
    assert!(c.check().unwrap_err().contains("laser grid has 3 points"));
    // `T_Sx_Sy` with a laser point per sensor point: a laser grid of the same count
    // but transposed shape would pair each transient with another's laser (a review,
    // 2026-12-06: accepted, the image moved).
    let c = sample();
    let both = |laser_shape: Vec<usize>| YtalCapture {
        h_format: HFormat::TSxSy,
        h_shape: vec![5, 2, 3],
        h: vec![0.0; 30],
        laser_grid: Grid {
            shape: laser_shape,
            ..c.sensor_grid.clone()
        },
        flags: None,
        ..c.clone()
    };
    assert!(both(vec![2, 3]).check().is_ok());
    let e = both(vec![3, 2]).check().unwrap_err();
    assert!(e.contains("laser_grid_xyz") && e.contains("[3, 2]"), "{e}");
}

#[test]
fn files_that_are_not_y_tal_captures_get_a_clear_message() {
    let dir = tempfile::tempdir().unwrap();
    let text = dir.path().join("notes.hdf5");
    std::fs::write(&text, "not hdf5").unwrap();
    let e = YtalCapture::read(&text).unwrap_err().to_string();
    assert!(e.contains("notes.hdf5") && e.contains("HDF5"), "{e}");
    let other = dir.path().join("znlos.hdf5");
    let mut b = FileBuilder::new();
    b.create_dataset("data").with_f32_data(&[0.0; 4]);
    std::fs::write(&other, b.finish().unwrap()).unwrap();
    let e = YtalCapture::read(&other).unwrap_err().to_string();
    assert!(e.contains("no dataset `H`") && e.contains("`data`"), "{e}");
}

/// A dataset read as one value (`H_format`, `delta_t`) or a point is refused from its
/// shape, before it is read: a chunked, deflated run of zeros takes a thousandth of its
/// size in the file, so a few MB could declare GiBs that every check on the file lets
/// through. Here 4 M values in about 20 KB; until 2026-12-07 all of them were read (32
/// MiB here, 8 GiB at the limit) before the count was looked at.
#[test]
fn a_scalar_declared_huge_is_refused_from_its_shape() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("huge-format.hdf5");
    let n = 1usize << 22;
    let mut b = FileBuilder::new();
    b.create_dataset("H").with_f32_data(&[0.0; 4]);
    b.create_dataset("H_format")
        .with_f64_data(&vec![0.0; n])
        .with_shape(&[n as u64])
        .with_chunks(&[1 << 16])
        .with_deflate(9);
    let bytes = b.finish().unwrap();
    assert!(bytes.len() < n / 64, "{} bytes", bytes.len());
    std::fs::write(&path, bytes).unwrap();
    let e = YtalCapture::read(&path).unwrap_err().to_string();
    assert!(
        e.contains("`H_format` should hold one value") && e.contains(&format!("holds {n} values")),
        "{e}"
    );
}

/// The bins outside every path through the volume, which the transients are cut away
/// from, are counted as the ambient level's evidence: here 2 counts in each bin before
/// the volume's shortest path (less 5 bins of margin), 9 in the rest.
#[test]
fn the_bins_no_path_through_the_volume_reaches_are_kept_as_the_ambient_level() {
    let h = (0..200 * 6)
        .map(|v| if v / 6 < 115 { 2.0 } else { 9.0 })
        .collect();
    let c = confocal_six(200, 0.0, h);
    // Volume z 0.6–1.2 m over the points: every path at least 1.2 m (bin 120), and
    // the longest past the recording's end (2 m).
    let volume = VolumeGrid::new([-0.1, 0.6], [-0.3, 0.1], [0.6, 1.2], [8, 8, 8]).unwrap();
    c.check().unwrap();
    let set = c.transients(&volume).unwrap();
    let (mean, bins) = set.ambient().expect("bins before the volume's paths");
    assert_eq!(
        mean, 2.0,
        "only bins wholly before the shortest path, less the margin"
    );
    assert_eq!(bins, 6 * 114, "bins 0 to 113: wholly before 1.2 m less 5 bins");
    assert!(
        set.axis().start >= 1.1,
        "the set itself is cut to the volume: {:?}",
        set.axis()
    );
    // A volume whose paths fill the recording leaves none.
    let wide = VolumeGrid::new([-3.0, 3.0], [-3.0, 3.0], [0.001, 1.0], [8, 8, 8]).unwrap();
    assert!(c.transients(&wide).unwrap().ambient().is_none());
}

/// Where the file's times include the legs, each transient's window lands on the
/// hidden paths shifted by its own legs, so the union the axis spans is more than any
/// one of them recorded: each transient is marked with the bins its own window holds
/// whole ([`TransientSet::recorded`]), which the fit keeps to.
#[test]
fn each_transient_keeps_to_its_own_window_when_the_legs_differ() {
    let c = YtalCapture {
        t_accounts_first_and_last_bounces: true,
        laser_xyz: Some(DVec3::new(-0.2, 0.0, 1.0)),
        ..confocal_six(64, 2.5, vec![1.0; 64 * 6])
    };
    c.check().unwrap();
    let deep = VolumeGrid::new([-0.3, 0.6], [-0.4, 0.3], [0.2, 1.0], [8, 8, 8]).unwrap();
    let set = c.transients(&deep).unwrap();
    let axis = *set.axis();
    assert_eq!(set.len(), 6);
    let span = 64.0 * c.delta_t;
    let mut narrowed = 0;
    for i in 0..set.len() {
        let (from, to) = (c.hidden_start(i), c.hidden_start(i) + span);
        let kept = set.recorded(i);
        assert!(!kept.is_empty());
        // Every bin kept lies wholly inside the window, and the bins beside it do not.
        assert!(
            axis.edge(kept.start as isize) >= from - 1e-9,
            "{i}: {kept:?} from {from}"
        );
        assert!(axis.edge(kept.end as isize) <= to + 1e-9, "{i}: {kept:?} to {to}");
        assert!(
            kept.start == 0 || axis.edge(kept.start as isize - 1) < from,
            "{i}"
        );
        assert!(
            kept.end == axis.bins || axis.edge(kept.end as isize + 1) > to,
            "{i}"
        );
        // Inside, the window's counts: 1 a bin.
        assert!(
            set.histogram(i)[kept.clone()]
                .iter()
                .all(|&v| (v - 1.0).abs() < 1e-5)
        );
        narrowed += usize::from(kept.len() < axis.bins);
    }
    assert!(
        narrowed >= 4,
        "the legs differ, so most windows cover part of the axis"
    );
}

/// A run's own export holds its counts with pile-up and dead time undone: no longer
/// whole numbers, but each at or a little above one. The reader reads them as counts
/// (Poisson noise) from the values alone, as it reads whole numbers; values a render
/// or a processing step leaves are not read as counts.
#[test]
fn counts_with_pile_up_undone_are_read_as_photon_counts() {
    let volume = VolumeGrid::new([-0.1, 0.6], [-0.3, 0.1], [0.2, 0.6], [8, 8, 8]).unwrap();
    let bins = 200;
    // Counts 0–5 in a repeating pattern, each bin raised as a first-photon counter's
    // correction raises it: by a factor growing along the histogram to 1.12.
    let counted: Vec<f32> = (0..bins * 6).map(|v| ((v * 7 + v / 6) % 6) as f32).collect();
    let corrected: Vec<f32> = counted
        .iter()
        .enumerate()
        .map(|(v, &n)| n * (1.0 + 0.12 * (v / 6) as f32 / bins as f32))
        .collect();
    let counts = |h: Vec<f32>| {
        let c = confocal_six(bins, 0.0, h);
        c.check().unwrap();
        c.transients(&volume).unwrap().is_photon_counts()
    };
    assert!(counts(counted.clone()), "whole numbers are counts");
    assert!(
        counts(corrected.clone()),
        "counts raised by at most a quarter are counts"
    );
    // A render: values anywhere, most of them under one.
    let rendered: Vec<f32> = (0..bins * 6).map(|v| 1e-3 * (1.0 + (v % 97) as f32)).collect();
    assert!(!counts(rendered.clone()), "a render is not counts");
    // The same render scaled until every value is large: nothing says counts.
    assert!(
        !counts(rendered.iter().map(|v| v * 1e6).collect()),
        "large values alone are not evidence of counts"
    );
    // One small value between whole numbers' bands (1.6: neither 1 raised by a
    // quarter nor 2) is no count.
    let mut off = corrected;
    off[6 * 50] = 1.6;
    assert!(!counts(off), "1.6 is no corrected count");
    // Nor is a value under one (a background subtracted, a count scaled down).
    let mut under = counted;
    under[6 * 50] = 0.5;
    assert!(!counts(under), "0.5 is no count");
}

/// A capture's flags and `scene_info` come back as they were written, and a capture
/// with no `scene_info` stores the empty mapping (y-tal's reader fails on a file
/// without one) and reads back as having none.
#[test]
fn flags_and_an_absent_scene_info_read_back_as_written() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.hdf5");
    let c = sample();
    c.write(&path).unwrap();
    let back = YtalCapture::read(&path).unwrap();
    assert_eq!(back.flags, c.flags);
    assert_eq!(back.scene_info, c.scene_info);
    for flags in [None, c.flags.clone()] {
        let bare = YtalCapture {
            scene_info: None,
            flags: flags.clone(),
            ..sample()
        };
        bare.write(&path).unwrap();
        let back = YtalCapture::read(&path).unwrap();
        assert_eq!(back.scene_info, None, "flags {flags:?}");
        assert_eq!(back.flags, flags);
        let file = hdf5_pure::File::open(&path).unwrap();
        let text = file.dataset("scene_info").unwrap().read_string().unwrap();
        assert!(!text[0].trim().is_empty(), "scene_info left empty: {text:?}");
    }
}

/// y-tal reads `scene_info` into a dict and writes it back with PyYAML's `yaml.dump`,
/// which puts a non-empty list one item a line (checked with PyYAML 6.0.4 on a file
/// of ours): those flags read as the flow-style ones do. Until 2026-12-07 such a file
/// was refused ("should be a list like [3, 17]").
#[test]
fn flags_in_yamls_block_style_are_read() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.hdf5");
    let dumped = YtalCapture {
        scene_info: Some(
            "original_format: test\nperiscope_overflow:\n- 3\n- 11\nperiscope_saturated: []\nrun: demo\n"
                .into(),
        ),
        flags: None,
        ..sample()
    };
    dumped.write(&path).unwrap();
    let back = YtalCapture::read(&path).unwrap();
    let mut want = vec![0u8; 12];
    want[3] = FLAG_OVERFLOW;
    want[11] = FLAG_OVERFLOW;
    assert_eq!(back.flags, Some(want));
    assert_eq!(
        back.scene_info.as_deref(),
        Some("original_format: test\nrun: demo\n")
    );
    // An item that is not an index is named.
    let bad = YtalCapture {
        scene_info: Some("periscope_saturated:\n  - 2\n  - x\n".into()),
        flags: None,
        ..sample()
    };
    bad.write(&path).unwrap();
    let e = YtalCapture::read(&path).unwrap_err().to_string();
    assert!(e.contains("`periscope_saturated` lists \"x\""), "{e}");
}

/// A capture file written the way y-tal's converter writes one from a phasor-field
/// `.mat` with a single normal: the points `(N, 3)`, their normals `(N, 1, 3)`; and a
/// polarised render's `H` with its Stokes axis last.
fn hand_written(normals_shape: &[u64], h_shape: &[u64]) -> Vec<u8> {
    let mut b = FileBuilder::new();
    let n = 3usize;
    let h_len: u64 = h_shape.iter().product();
    b.create_dataset("H")
        .with_f32_data(&vec![1.0; h_len as usize])
        .with_shape(h_shape);
    b.create_dataset("H_format").with_i32_data(&[3]);
    let points: Vec<f32> = (0..n).flat_map(|i| [0.1 * i as f32, 0.0, 0.0]).collect();
    let count = normals_shape.iter().product::<u64>() as usize / 3;
    let normals: Vec<f32> = (0..count).flat_map(|_| [0.0, 0.0, 1.0]).collect();
    for side in ["sensor", "laser"] {
        b.create_dataset(&format!("{side}_grid_xyz"))
            .with_f32_data(&points)
            .with_shape(&[n as u64, 3]);
        b.create_dataset(&format!("{side}_grid_normals"))
            .with_f32_data(&normals)
            .with_shape(normals_shape);
        b.create_dataset(&format!("{side}_grid_format"))
            .with_i32_data(&[1]);
    }
    b.create_dataset("delta_t").with_f64_data(&[0.01]).with_shape(&[]);
    b.create_dataset("t_start").with_f64_data(&[0.5]).with_shape(&[]);
    b.create_dataset("t_accounts_first_and_last_bounces")
        .with_i32_data(&[0])
        .with_shape(&[]);
    b.finish().unwrap()
}

#[test]
fn normals_with_an_axis_of_one_and_a_polarised_h_are_read_or_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.hdf5");
    std::fs::write(&path, hand_written(&[3, 1, 3], &[4, 3])).unwrap();
    let c = YtalCapture::read(&path).unwrap();
    assert_eq!(c.sensor_grid.normals, vec![DVec3::Z; 3]);
    std::fs::write(&path, hand_written(&[1, 3, 3], &[4, 3])).unwrap();
    assert!(YtalCapture::read(&path).is_ok(), "(1, N, 3) is (N, 3) too");
    // Normals of another count are still refused, naming both datasets.
    std::fs::write(&path, hand_written(&[2, 3], &[4, 3])).unwrap();
    let e = YtalCapture::read(&path).unwrap_err().to_string();
    assert!(
        e.contains("`sensor_grid_normals` has shape [2, 3] but `sensor_grid_xyz` has [3, 3]"),
        "{e}"
    );
    // A polarised render: its Stokes parameters on a last axis of 4.
    std::fs::write(&path, hand_written(&[3, 3], &[4, 3, 4])).unwrap();
    let e = YtalCapture::read(&path).unwrap_err().to_string();
    assert!(e.contains("polarised") && e.contains("f['H'][..., 0]"), "{e}");
}

//! The phasor-field captures of Liu et al. (docs/research/nlos-capture-formats.md §4),
//! two layouts, both MAT v7.3 as y-tal reads them:
//!
//! - **2019** (Nature, "Non-line-of-sight imaging using phasor-field virtual wave
//!   optics"): a `dataset` struct. `data` (laser point, SPAD point, t); `t` bins of
//!   `deltat` from `t0`, metres of the whole path from `laserOrigin` through
//!   `laserPos` and the scene and `cameraPos` to `cameraOrigin` (y-tal's reading, bin
//!   k from 0); `laserPos`/`cameraPos` n × 3 lists with `laserNorm`/`cameraNorm` (one
//!   normal or one per point). Read as `T_Li_Si`, every laser point with every SPAD
//!   point.
//! - **2020** (Nat. Commun., "Phasor field diffraction based reconstruction"):
//!   `rect_data` (x, y, t), the laser scanned over an x × y grid at `sampling_spacing`
//!   metres (or `aperturefullsize(1) / (x − 1)`), one SPAD on the grid point
//!   `SPAD_index` (`[x y]`, MATLAB's 1-based indices), bins of `ts` seconds from the
//!   wall (the paths from the laser's wall point to the SPAD's). Read as
//!   `T_Lx_Ly_Sx_Sy` with one SPAD point; the grid is centred on the relay's origin,
//!   normals +z.
use glam::DVec3;

use super::mat::{Mat, points};
use super::{C, check_counts, grid, list};
use crate::io::ytal::{HFormat, YtalCapture, YtalError, unit};

/// Reads the 2019 `dataset` layout.
pub(crate) fn from_dataset(mat: &Mat<'_>) -> Result<YtalCapture, YtalError> {
    if matches!(mat, Mat::V5 { .. }) {
        return Err(mat.error(
            "a `dataset` struct in a MAT v5 file, which Periscope does not parse: save it again with \
             `save(file, 'dataset', '-v7.3')`",
        ));
    }
    let field = |f: &str| format!("dataset/{f}");
    let data = mat
        .var_f32(&field("data"))?
        .ok_or_else(|| mat.error("no `dataset.data` (the transients, laser point × SPAD point × t)"))?;
    let (nl, ns, nt) = match data.dims.as_slice() {
        &[nl, ns, nt] => (nl, ns, nt),
        &[nl, nt] => (nl, 1, nt),
        dims => {
            return Err(mat.error(format!(
                "`dataset.data` has dims {dims:?}; expected (laser point, SPAD point, t)"
            )));
        }
    };
    check_counts(&data.values, "dataset.data").map_err(|m| mat.error(m))?;
    if let Some(t) = mat.scalar(&field("t"))?
        && t != nt as f64
    {
        return Err(mat.error(format!(
            "`dataset.t` says {t} bins but `dataset.data` has {nt} on its last dim"
        )));
    }
    let deltat = mat.required_scalar(&field("deltat"), "the bin width, metres of path")?;
    if !(deltat > 0.0 && deltat <= 10.0) {
        return Err(mat.error(format!(
            "`dataset.deltat` is {deltat}; it must be a positive bin width in metres of path"
        )));
    }
    let t0 = mat.scalar(&field("t0"))?.unwrap_or(0.0);
    if t0.abs() > 1e4 {
        return Err(mat.error(format!(
            "`dataset.t0` is {t0}; it must be a path length in metres"
        )));
    }
    let side = |pos: &str,
                norm: &str,
                origin: &str,
                n: usize|
     -> Result<(Vec<DVec3>, Vec<DVec3>, DVec3), YtalError> {
        let p = points(
            mat,
            &mat.required(&field(pos), "the relay points, n × 3")?,
            &field(pos),
        )?;
        if p.len() != n {
            return Err(mat.error(format!(
                "`dataset.{pos}` has {} points but `dataset.data` has {n} on that side",
                p.len()
            )));
        }
        let normals = match mat.var(&field(norm))? {
            Some(v) => points(mat, &v, &field(norm))?,
            None => vec![DVec3::Z],
        };
        let normals: Vec<DVec3> = match normals.len() {
            // Scaled first, as y-tal's normals are: one stored at 1e-200 or 1e200 is
            // a direction, not a zero.
            1 => vec![unit(normals[0]); n],
            k if k == n => normals.into_iter().map(unit).collect(),
            k => {
                return Err(mat.error(format!("`dataset.{norm}` has {k} normals for {n} points")));
            }
        };
        if normals.contains(&DVec3::ZERO) {
            return Err(mat.error(format!("`dataset.{norm}` has a zero normal")));
        }
        let o = points(
            mat,
            &mat.required(&field(origin), "where the light starts or ends")?,
            &field(origin),
        )?;
        Ok((p, normals, o[0]))
    };
    let (lp, ln, laser) = side("laserPos", "laserNorm", "laserOrigin", nl)?;
    let (sp, sn, sensor) = side("cameraPos", "cameraNorm", "cameraOrigin", ns)?;
    // H (T, Li, Si), C order, from data (l, s, t) column-major.
    let mut h = vec![0f32; nt * nl * ns];
    for t in 0..nt {
        for l in 0..nl {
            for s in 0..ns {
                h[(t * nl + l) * ns + s] = data.values[l + nl * (s + ns * t)];
            }
        }
    }
    let capture = YtalCapture {
        h,
        h_shape: vec![nt, nl, ns],
        h_format: HFormat::TLiSi,
        sensor_grid: list(sp, sn),
        laser_grid: list(lp, ln),
        sensor_xyz: Some(sensor),
        laser_xyz: Some(laser),
        delta_t: deltat,
        t_start: t0,
        t_accounts_first_and_last_bounces: true,
        scene_info: Some(super::source_info(format!(
            "phasor-field capture, 2019 `dataset` layout ({}), {nl} laser points by {ns} SPAD points, \
             {nt} bins of {deltat} m from {t0} m (laser origin to SPAD origin)",
            mat.path().display()
        ))),
        flags: None,
    };
    capture.check().map_err(|m| mat.error(m))?;
    Ok(capture)
}

/// Reads the 2020 `rect_data` + `ts` + `SPAD_index` layout.
pub(crate) fn from_rect_data(mat: &Mat<'_>) -> Result<YtalCapture, YtalError> {
    let rect = mat
        .var_f32("rect_data")?
        .ok_or_else(|| mat.error("`rect_data` is empty"))?;
    let &[m, n, nt] = rect.dims.as_slice() else {
        return Err(mat.error(format!(
            "`rect_data` has dims {:?}; a phasor-field capture's are (x, y, t)",
            rect.dims
        )));
    };
    if m < 2 || n < 2 || nt < 2 {
        return Err(mat.error(format!("`rect_data` of dims ({m}, {n}, {nt}) is too small")));
    }
    check_counts(&rect.values, "rect_data").map_err(|e| mat.error(e))?;
    let ts = mat.required_scalar("ts", "the bin width, seconds")?;
    if !(ts > 0.0 && ts < 1e-6) {
        return Err(mat.error(format!(
            "`ts` is {ts}; it must be a bin width in seconds (under 1 µs)"
        )));
    }
    let spacing = match mat.scalar("sampling_spacing")? {
        Some(s) => s,
        None => match mat.var("aperturefullsize")? {
            Some(a) => a.values[0] / (m - 1) as f64,
            None => {
                return Err(mat.error(
                    "neither `sampling_spacing` nor `aperturefullsize`: the laser grid's pitch is unknown",
                ));
            }
        },
    };
    if !(spacing.is_finite() && spacing > 0.0 && spacing < 10.0) {
        return Err(mat.error(format!(
            "the grid pitch is {spacing} m (`sampling_spacing`, or `aperturefullsize` over the points); it \
             must be a positive length under 10 m"
        )));
    }
    let spad = mat.required("SPAD_index", "the SPAD's [x y] grid point, 1-based")?;
    let [sx, sy] = match spad.values.as_slice() {
        &[x, y]
            if x.fract() == 0.0
                && y.fract() == 0.0
                && x >= 1.0
                && y >= 1.0
                && x <= m as f64
                && y <= n as f64 =>
        {
            [x as usize - 1, y as usize - 1]
        }
        v => {
            return Err(mat.error(format!(
                "`SPAD_index` is {v:?}; it must be the SPAD's [x y] grid point, whole numbers from 1 to ({m}, \
                 {n})"
            )));
        }
    };
    let at = |i: usize, j: usize| {
        DVec3::new(
            (i as f64 - (m - 1) as f64 / 2.0) * spacing,
            (j as f64 - (n - 1) as f64 / 2.0) * spacing,
            0.0,
        )
    };
    let lasers: Vec<DVec3> = (0..m).flat_map(|i| (0..n).map(move |j| at(i, j))).collect();
    // H (T, x, y, 1, 1), C order, from rect_data (x, y, t) column-major.
    let columns = m * n;
    let mut h = vec![0f32; nt * columns];
    for t in 0..nt {
        for i in 0..m {
            for j in 0..n {
                h[t * columns + i * n + j] = rect.values[i + m * (j + n * t)];
            }
        }
    }
    let capture = YtalCapture {
        h,
        h_shape: vec![nt, m, n, 1, 1],
        h_format: HFormat::TLxLySxSy,
        sensor_grid: grid(vec![at(sx, sy)], vec![DVec3::Z], [1, 1]),
        laser_grid: grid(lasers, vec![DVec3::Z; columns], [m, n]),
        sensor_xyz: None,
        laser_xyz: None,
        delta_t: C * ts,
        t_start: 0.0,
        t_accounts_first_and_last_bounces: false,
        scene_info: Some(super::source_info(format!(
            "phasor-field capture, 2020 `rect_data` layout ({}), laser over {m} x {n} points at {spacing} \
             m, SPAD at grid point ({}, {}), {nt} bins of {} ps from the wall",
            mat.path().display(),
            sx + 1,
            sy + 1,
            ts * 1e12
        ))),
        flags: None,
    };
    capture.check().map_err(|e| mat.error(e))?;
    Ok(capture)
}

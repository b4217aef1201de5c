//! Stanford's f-k migration captures (Lindell, Wetzstein and O'Toole 2019,
//! `computational-imaging/nlos-fk`; docs/research/nlos-capture-formats.md §2).
//!
//! A scene's directory holds `meas_<minutes>min.mat` with `meas`, MATLAB dims
//! (y, x, t), counts in 32 ps bins as the gated SPAD recorded them, and `tof.mat` with
//! `tofgrid`, (y, x), the time of flight to each scan point in picoseconds. The
//! reference code (`cnlos_reconstruction.m`) shifts each histogram by
//! `floor(tofgrid / 32)` bins toward 0 so that bin 0 is the light at the wall; this
//! reader does the same, without wrapping bins around: every histogram keeps the bins
//! all of them recorded after the shift (`T − max shift`). The files hold no geometry:
//! the release's planar scenes scan 2 m × 2 m of wall (`wall_size = 2` in `demo.m`), so
//! the scan points are `linspace(−1, 1, n)` m along x and y unless the file has a
//! `width` (half the side, as in the LCT files). Non-planar scenes (`tof.mat` with
//! `pos`) and the interactive 4-D `meas` are refused, naming what is missing.
use std::path::Path;

use glam::DVec3;

use super::mat::Mat;
use super::{C, check_counts};
use crate::io::ytal::{YtalCapture, YtalError};

/// The release's bin, seconds (`bin_resolution = 32e-12`).
pub const BIN_S: f64 = 32e-12;

/// Half the side of the release's planar scans, metres (`wall_size = 2`).
pub const DEFAULT_WIDTH_M: f64 = 1.0;

/// Reads an f-k measurement; `dir` is where to look for `tof.mat` when the file does
/// not hold `tofgrid` itself.
pub(crate) fn from_mat(mat: &Mat<'_>, dir: Option<&Path>) -> Result<YtalCapture, YtalError> {
    let meas = mat.var_f32("meas")?.ok_or_else(|| mat.error("`meas` is empty"))?;
    let &[ny, nx, nt] = meas.dims.as_slice() else {
        return Err(mat.error(format!(
            "`meas` has dims {:?}; an f-k capture's are (y, x, t) (an interactive sequence's 4-D (frame, y, \
             x, t) is not read: save one frame, `meas = squeeze(meas(k, :, :, :))`)",
            meas.dims
        )));
    };
    if nx < 2 || ny < 2 || nt < 2 {
        return Err(mat.error(format!("`meas` of dims ({ny}, {nx}, {nt}) is too small")));
    }
    if Some(meas.values.len()) != ny.checked_mul(nx).and_then(|n| n.checked_mul(nt)) {
        return Err(mat.error(format!(
            "`meas` holds {} values for dims ({ny}, {nx}, {nt})",
            meas.values.len()
        )));
    }
    check_counts(&meas.values, "meas").map_err(|m| mat.error(m))?;
    let (tof, tof_from) = tofgrid(mat, dir)?;
    if tof.dims != [ny, nx] {
        return Err(mat.error(format!(
            "`tofgrid` ({tof_from}) has dims {:?} but `meas` has ({ny}, {nx}) scan points: it belongs to \
             another scene or resolution",
            tof.dims
        )));
    }
    if let Some(i) = tof.values.iter().position(|t| !(t.is_finite() && *t >= 0.0)) {
        return Err(mat.error(format!(
            "`tofgrid` ({tof_from}) value {} at index {i} is not a time of flight (ps, non-negative)",
            tof.values[i]
        )));
    }
    let bin_ps = BIN_S * 1e12;
    // Judged as a real number first: a huge time would saturate the cast.
    if let Some(t) = tof
        .values
        .iter()
        .copied()
        .find(|t| (t / bin_ps).floor() + 2.0 > nt as f64)
    {
        return Err(mat.error(format!(
            "`tofgrid` ({tof_from}) shifts a histogram by {:.0} bins of 32 ps but `meas` has {nt}: \
             the two do not belong together",
            (t / bin_ps).floor()
        )));
    }
    let shifts: Vec<usize> = tof.values.iter().map(|t| (t / bin_ps).floor() as usize).collect();
    let max_shift = shifts.iter().copied().max().unwrap_or(0);
    let bins = nt - max_shift;
    let width = match mat.scalar("width")? {
        Some(w) if w.is_finite() && w > 0.0 && w <= super::MAX_HALF_SIDE_M => w,
        Some(w) => {
            return Err(mat.error(format!(
                "`width` is {w}: it must be a positive half side in metres, at most {}",
                super::MAX_HALF_SIDE_M
            )));
        }
        None => DEFAULT_WIDTH_M,
    };
    // H (T, y, x) in C order from meas (y, x, t) column-major, each pixel shifted.
    let columns = ny * nx;
    let mut h = vec![0f32; bins * columns];
    for y in 0..ny {
        for x in 0..nx {
            let pixel = y + ny * x;
            let s = shifts[pixel];
            for t in 0..bins {
                h[t * columns + y * nx + x] = meas.values[pixel + columns * (t + s)];
            }
        }
    }
    let along = |n: usize, i: usize| -width + 2.0 * width * i as f64 / (n - 1) as f64;
    let points: Vec<DVec3> = (0..ny)
        .flat_map(|y| (0..nx).map(move |x| DVec3::new(along(nx, x), along(ny, y), 0.0)))
        .collect();
    let capture = super::confocal_wall(
        h,
        [bins, ny, nx],
        points,
        C * BIN_S,
        super::source_info(format!(
            "Stanford f-k capture ({}), {ny} x {nx} confocal points over [-{width}, {width}] m{}, \
         rectified with `tofgrid` from {tof_from} (shifts of {} to {max_shift} bins), {bins} bins of 32 ps \
         from the wall",
            mat.path().display(),
            if mat.has("width") {
                ""
            } else {
                " (the release's 2 m scan)"
            },
            shifts.iter().min().copied().unwrap_or(0),
        )),
    );
    capture.check().map_err(|m| mat.error(m))?;
    Ok(capture)
}

/// `tofgrid` from the measurement itself, or from `tof.mat` in `dir`, with where it
/// came from (for messages).
fn tofgrid(mat: &Mat<'_>, dir: Option<&Path>) -> Result<(super::mat::Var<f64>, String), YtalError> {
    if let Some(t) = mat.var("tofgrid")? {
        return Ok((t, "the file itself".into()));
    }
    let missing = || {
        mat.error(
            "no `tofgrid`, and no `tof.mat` beside it holding one: an f-k measurement needs the time of \
             flight to each scan point (the release's `tof.mat`, in the scene's directory) to know where the \
             wall is in each histogram",
        )
    };
    let tof_path = dir
        .map(|d| d.join("tof.mat"))
        .filter(|p| p.is_file())
        .ok_or_else(missing)?;
    let bytes = crate::io::read_regular_capped(&tof_path, 1 << 30).map_err(|e| YtalError::Hdf5 {
        path: tof_path.clone(),
        message: e.to_string(),
    })?;
    let named = tof_path.display().to_string();
    let var = super::with_mat(bytes, &tof_path, |tof| {
        if tof.has("pos") {
            return Err(tof.error(
                "it has `pos`: a non-planar scan, whose per-point surface offsets Periscope does not read \
                 from f-k files yet; convert the capture to y-tal HDF5 with the scan points as `sensor_grid_xyz`",
            ));
        }
        tof.var("tofgrid")?
            .ok_or_else(|| tof.error("no `tofgrid` (time of flight to each scan point, ps)"))
    })?;
    Ok((var, named))
}

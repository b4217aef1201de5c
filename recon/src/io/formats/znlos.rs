//! Zaragoza's NLOS data set (ZNLOS, Galindo et al. 2019): HDF5 files rendered by their
//! transient renderer, with the fields of `mjgalindo/nlos_loader`'s README
//! (docs/research/nlos-capture-formats.md §3).
//!
//! | field | meaning | as read |
//! |---|---|---|
//! | `data` | transients, one channel, bounces stored apart | h5py `(channel, T, bounces, cy, cx)` confocal, `(channel, T, bounces, cy, cx, ly, lx)` exhaustive; the channel may be absent; all reversed when the root attribute `data order` is `row-major` |
//! | `data` attribute `third_bounce` | index of the 3rd bounce on the bounce axis (default 1: bounces start at the 2nd) | bounces from the 3rd to the last are summed (the 2nd is the wall's own return) |
//! | `cameraGridPositions`, `cameraGridNormals` | SPAD points on the wall | h5py `(3, cy, cx)` (row-major files: `(cx, cy, 3)`) |
//! | `laserGridPositions`, `laserGridNormals` | laser points, likewise | `(3, ly, lx)` |
//! | `cameraPosition`, `laserPosition` | the SPAD's and the laser's origins | `sensor_xyz`, `laser_xyz`; a confocal file's legs both run to `cameraPosition`, as Galindo's backprojector takes them |
//! | `deltaT`, `t0` | bin width and start of bin 0, metres of path | `delta_t`, `t_start`, paths from the laser's origin to the SPAD's (`t_accounts_first_and_last_bounces`) |
//! | `t` | bins | checked against `data` |
//! | `isConfocal` | whether laser and SPAD share points | confocal data without a laser grid of its own take the camera's |
use glam::DVec3;

use super::{check_counts, grid};
use crate::io::ytal::{HFormat, Reader, YtalCapture, YtalError, memory_check, unit};

/// The logical axes of `data`, in the order a column-major file's h5py shape lists
/// them.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Axis {
    Channel,
    Time,
    Bounce,
    CamY,
    CamX,
    LasY,
    LasX,
}

/// Reads a ZNLOS capture from an open HDF5 file (it has `data`).
pub(crate) fn from_reader(r: &Reader<'_>) -> Result<YtalCapture, YtalError> {
    // Attributes that cannot be decoded are an error, not an absent `data order`: the
    // axes would be read in the wrong order.
    let root = r.file.root().attrs().map_err(|e| {
        r.format(format!(
            "the file's root attributes cannot be read ({e}), so its `data order` is unknown"
        ))
    })?;
    let row_major = match root.get("data order") {
        None => false,
        Some(v) => match super::text_attr(v) {
            Some(o) if o.eq_ignore_ascii_case("column-major") => false,
            Some(o) if o.eq_ignore_ascii_case("row-major") => true,
            Some(o) => {
                return Err(r.format(format!(
                    "the root attribute `data order` is {o:?}; ZNLOS files say \"row-major\" or \"column-major\""
                )));
            }
            None => {
                return Err(r.format(format!(
                    "the root attribute `data order` is not text ({v:?}); ZNLOS files say \"row-major\" or \
                     \"column-major\""
                )));
            }
        },
    };
    let ds = r
        .file
        .dataset("data")
        .map_err(|e| r.format(format!("dataset `data`: {e}")))?;
    let shape = r.checked_shape(&ds, "data", 4)?;
    use Axis::*;
    let mut axes: Vec<Axis> = match shape.len() {
        7 => vec![Channel, Time, Bounce, CamY, CamX, LasY, LasX],
        6 => vec![Time, Bounce, CamY, CamX, LasY, LasX],
        5 => vec![Channel, Time, Bounce, CamY, CamX],
        4 => vec![Time, Bounce, CamY, CamX],
        n => {
            return Err(r.format(format!(
                "`data` has {n} dimensions (shape {shape:?}); a ZNLOS capture's are (channel, T, bounces, \
                 cy, cx) confocal or (channel, T, bounces, cy, cx, ly, lx) exhaustive"
            )));
        }
    };
    if row_major {
        axes.reverse();
    }
    if shape.contains(&0) {
        return Err(r.format(format!("`data` of shape {shape:?} is empty")));
    }
    let size = |a: Axis| axes.iter().position(|&b| b == a).map_or(1, |i| shape[i]);
    // C-order strides of the file's array, by logical axis.
    let mut strides = vec![0usize; shape.len()];
    let mut s = 1;
    for i in (0..shape.len()).rev() {
        strides[i] = s;
        s *= shape[i];
    }
    let stride = |a: Axis| axes.iter().position(|&b| b == a).map_or(0, |i| strides[i]);
    let (nt, nb) = (size(Time), size(Bounce));
    let cam = [size(CamY), size(CamX)];
    let las = [size(LasY), size(LasX)];
    let exhaustive = axes.contains(&LasX);
    let attrs = ds.attrs().map_err(|e| {
        r.format(format!(
            "the attributes of `data` cannot be read ({e}), so its `third_bounce` is unknown"
        ))
    })?;
    let third = match attrs.get("third_bounce").map(|v| (v, super::number_attr(v))) {
        None => 1usize.min(nb - 1),
        Some((v, None)) => {
            return Err(r.format(format!(
                "`data`'s attribute `third_bounce` is not a number ({v:?}); it must index the bounce axis (0 to {})",
                nb - 1
            )));
        }
        Some((_, Some(v))) if v.fract() == 0.0 && v >= 0.0 && (v as usize) < nb => v as usize,
        Some((_, Some(v))) => {
            return Err(r.format(format!(
                "`data`'s attribute `third_bounce` is {v}; it must index the bounce axis (0 to {})",
                nb - 1
            )));
        }
    };
    if let Some(t) = r.scalar("t")?
        && t != nt as f64
    {
        return Err(r.format(format!(
            "`t` says {t} bins but `data` has {nt} on its time axis (shape {shape:?}, {} order): the file's \
             `data order` attribute may be wrong",
            if row_major { "row-major" } else { "column-major" }
        )));
    }
    memory_check(&shape, "data").map_err(|m| r.format(m))?;
    let data = ds
        .read_f32()
        .map_err(|e| r.format(format!("dataset `data` is not numeric: {e}")))?;
    check_counts(&data, "data").map_err(|m| r.format(m))?;

    let delta_t = r.required_scalar("deltaT")?;
    if !(delta_t > 0.0 && delta_t <= 10.0) {
        return Err(r.format(format!(
            "`deltaT` is {delta_t}; it must be a positive bin width in metres of path (at most 10)"
        )));
    }
    let t0 = r.scalar("t0")?.unwrap_or(0.0);
    if !(t0.is_finite() && t0.abs() <= 1e4) {
        return Err(r.format(format!("`t0` is {t0}; it must be a path length in metres")));
    }
    let camera = r.point("cameraPosition")?.ok_or_else(|| {
        r.format(
            "no `cameraPosition` (the SPAD's origin; the legs to and from the wall are part of every path)"
                .into(),
        )
    })?;
    let laser = r.point("laserPosition")?.unwrap_or(camera);
    let (cam_points, cam_normals) = relay(r, "camera", cam, row_major)?;
    let laser_grid = if exhaustive {
        let (p, n) = relay(r, "laser", las, row_major)?;
        grid(p, n, las)
    } else if r.has("laserGridPositions") {
        // Confocal data: the laser's points are the camera's, or one fixed point.
        // From its shape: the positions themselves are read with the relay's.
        let one = r
            .shape_of("laserGridPositions")?
            .is_some_and(|s| s.iter().product::<usize>() == 3);
        let shape = if one { [1, 1] } else { cam };
        let (p, n) = relay(r, "laser", shape, row_major)?;
        grid(p, n, shape)
    } else {
        grid(cam_points.clone(), cam_normals.clone(), cam)
    };
    let confocal = !exhaustive && laser_grid.points == cam_points;

    // H: (T, cy, cx) or (T, ly, lx, cy, cx), the bounces from the 3rd summed.
    let columns = if exhaustive { las[0] * las[1] } else { 1 } * cam[0] * cam[1];
    let mut h = vec![0f32; nt * columns];
    let mut column = 0;
    for ly in 0..if exhaustive { las[0] } else { 1 } {
        for lx in 0..if exhaustive { las[1] } else { 1 } {
            for cy in 0..cam[0] {
                for cx in 0..cam[1] {
                    let base = ly * stride(LasY) + lx * stride(LasX) + cy * stride(CamY) + cx * stride(CamX);
                    for t in 0..nt {
                        let mut v = 0f32;
                        for ch in 0..size(Channel) {
                            for b in third..nb {
                                v +=
                                    data[base + t * stride(Time) + b * stride(Bounce) + ch * stride(Channel)];
                            }
                        }
                        h[t * columns + column] = v;
                    }
                    column += 1;
                }
            }
        }
    }
    // Each count was checked; their sum over channels and bounces is checked too, so a
    // summed `H` keeps the readers' 1e30 promise (three channels at 1e30 made 3e30,
    // and enough of them infinity, blamed on a pair's histogram).
    check_counts(&h, "data summed over channels and bounces").map_err(|m| r.format(m))?;
    let h_shape = if exhaustive {
        vec![nt, las[0], las[1], cam[0], cam[1]]
    } else {
        vec![nt, cam[0], cam[1]]
    };
    let capture = YtalCapture {
        h,
        h_shape,
        h_format: if exhaustive {
            HFormat::TLxLySxSy
        } else {
            HFormat::TSxSy
        },
        sensor_grid: grid(cam_points, cam_normals, cam),
        laser_grid,
        sensor_xyz: Some(camera),
        laser_xyz: Some(if confocal { camera } else { laser }),
        delta_t,
        t_start: t0,
        t_accounts_first_and_last_bounces: true,
        scene_info: Some(super::source_info(format!(
            "ZNLOS capture ({}), {} {} x {} camera points{}, {nt} bins of {delta_t} m from {t0} m \
             (laser origin to SPAD origin), bounces {} to {} summed",
            r.path.display(),
            if confocal { "confocal" } else { "non-confocal" },
            cam[0],
            cam[1],
            if exhaustive {
                format!(" by {} x {} laser points", las[0], las[1])
            } else {
                String::new()
            },
            3,
            nb - 1 - third + 3,
        ))),
        flags: None,
    };
    capture.check().map_err(|m| r.format(m))?;
    Ok(capture)
}

/// One side's points and normals, flattened `[a, b]` with `b` fastest, from
/// `<side>GridPositions` / `<side>GridNormals`: h5py `(3, a, b)` in a column-major
/// file, `(b, a, 3)` in a row-major one.
fn relay(
    r: &Reader<'_>,
    side: &str,
    [na, nb]: [usize; 2],
    row_major: bool,
) -> Result<(Vec<DVec3>, Vec<DVec3>), YtalError> {
    let read = |name: String| -> Result<Vec<DVec3>, YtalError> {
        let (v, shape) = r.floats(&name)?.ok_or_else(|| {
            r.format(format!(
                "no `{name}` (the {side} points on the wall, with their normals)"
            ))
        })?;
        let want: [usize; 3] = if row_major { [nb, na, 3] } else { [3, na, nb] };
        let pts: Vec<DVec3> = if shape == want {
            let mut pts = Vec::with_capacity(na * nb);
            for a in 0..na {
                for b in 0..nb {
                    let at = |k: usize| {
                        if row_major {
                            v[(b * na + a) * 3 + k]
                        } else {
                            v[(k * na + a) * nb + b]
                        }
                    };
                    pts.push(DVec3::new(at(0), at(1), at(2)));
                }
            }
            pts
        } else if na * nb == 1 && v.len() == 3 {
            vec![DVec3::new(v[0], v[1], v[2])]
        } else {
            return Err(r.format(format!(
                "`{name}` has shape {shape:?}; with `data` as it is it must be {want:?}"
            )));
        };
        if let Some(i) = pts.iter().position(|p| !p.is_finite()) {
            return Err(r.format(format!("`{name}` point {i} is not finite")));
        }
        Ok(pts)
    };
    let cap = |s: &str| format!("{side}Grid{s}");
    let points = read(cap("Positions"))?;
    let normals: Vec<DVec3> = read(cap("Normals"))?.into_iter().map(unit).collect();
    if let Some(i) = normals.iter().position(|n| *n == DVec3::ZERO) {
        return Err(r.format(format!("`{}` normal {i} is zero", cap("Normals"))));
    }
    Ok((points, normals))
}

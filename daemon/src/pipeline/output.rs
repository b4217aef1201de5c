//! Run outputs (`DESIGN.md` §6): `volume.npy` (float32 [nz, ny, nx]), `volume.json`,
//! `depth.npy` (float32 [ny, nx], metres, NaN where nothing was found), `depth.png`,
//! `albedo.png`, `gaussians.ply` (3D-GTR only); and the relay point cloud `relay.ply`.
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::Path;

use glam::DVec3;
use periscope_recon::io::{write_albedo_png, write_depth_png, write_npy, write_volume};
use serde::Serialize;

use super::PipelineError;
use super::los::RelayPoint;
use super::reconstruct::ReconResult;
use crate::events::{EventSink, RunEvent};

/// The relay point cloud's file name.
pub const RELAY_PLY: &str = "relay.ply";

/// What a reconstruction wrote, with its statistics.
#[derive(Clone, Debug, Serialize)]
pub struct RunOutputs {
    /// File names written.
    pub files: Vec<String>,
    /// Largest voxel value.
    pub volume_max: f32,
    /// Depth-map pixels with a depth.
    pub depth_pixels: usize,
    /// Depth-map pixels in all.
    pub pixels: usize,
    /// Gaussians after pruning (3D-GTR).
    pub primitives: Option<usize>,
    /// Final training loss (3D-GTR).
    pub final_loss: Option<f64>,
    /// Seconds per reconstruction step.
    pub timings: Vec<(String, f64)>,
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> PipelineError + '_ {
    move |e| PipelineError::storage(path, e)
}

fn recon_io(path: &Path) -> impl Fn(periscope_recon::io::IoError) -> PipelineError + '_ {
    move |e| PipelineError::Recon(format!("{}: {e}", path.display()))
}

/// Writes the relay as a binary PLY: x y z nx ny nz intensity (float32), written to a
/// temporary name and renamed.
pub(crate) fn write_relay_ply(dir: &Path, relay: &[RelayPoint]) -> Result<(), PipelineError> {
    let path = dir.join(RELAY_PLY);
    let tmp = dir.join("relay.ply.tmp");
    {
        let mut w = BufWriter::new(File::create(&tmp).map_err(io(&tmp))?);
        let header = format!(
            "ply\nformat binary_little_endian 1.0\ncomment Periscope relay: LOS first-bounce points, normals toward the instrument, peak counts\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty float intensity\nend_header\n",
            relay.len()
        );
        w.write_all(header.as_bytes()).map_err(io(&tmp))?;
        for p in relay {
            for v in [p.x.x, p.x.y, p.x.z, p.n.x, p.n.y, p.n.z, p.intensity] {
                w.write_all(&(v as f32).to_le_bytes()).map_err(io(&tmp))?;
            }
        }
        w.into_inner()
            .map_err(|e| PipelineError::storage(&tmp, e.into_error()))?
            .sync_all()
            .map_err(io(&tmp))?;
    }
    std::fs::rename(&tmp, &path).map_err(io(&path))
}

/// Reads `relay.ply` back (resume, the dashboard's 3-D view), or `None` if the run has
/// none yet.
pub fn read_relay_ply(dir: &Path) -> Result<Option<Vec<RelayPoint>>, PipelineError> {
    let path = dir.join(RELAY_PLY);
    if !path.exists() {
        return Ok(None);
    }
    let bytes = std::fs::read(&path).map_err(io(&path))?;
    parse_relay_ply(&bytes).map(Some).map_err(|m| {
        PipelineError::storage(
            &path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("not a Periscope relay PLY ({m}); delete it to measure the relay again"),
            ),
        )
    })
}

/// The vertex properties of a relay PLY, in order.
const RELAY_PROPERTIES: [&str; 7] = ["x", "y", "z", "nx", "ny", "nz", "intensity"];

/// Decodes a relay PLY as the capture writes it (`write_relay_ply`): the header must declare
/// exactly its layout, the body must be exactly the declared vertices, and every
/// point finite with a unit normal. Any input gives an answer; nothing here panics.
pub fn parse_relay_ply(bytes: &[u8]) -> Result<Vec<RelayPoint>, String> {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .ok_or("no end_header line")?
        + 11;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "the header is not text")?;
    let lines: Vec<&str> = header.lines().filter(|l| !l.starts_with("comment")).collect();
    let n: usize = match lines.as_slice() {
        [
            "ply",
            "format binary_little_endian 1.0",
            vertex,
            props @ ..,
            "end_header",
        ] if props.len() == RELAY_PROPERTIES.len()
            && props
                .iter()
                .zip(RELAY_PROPERTIES)
                .all(|(l, name)| l.strip_prefix("property float ") == Some(name)) =>
        {
            vertex
                .strip_prefix("element vertex ")
                .and_then(|v| v.trim().parse().ok())
                .ok_or("no vertex count")?
        }
        _ => return Err("the header is not the relay layout (x y z nx ny nz intensity, float)".into()),
    };
    let body = &bytes[end..];
    if n.checked_mul(28) != Some(body.len()) {
        return Err(format!(
            "the header declares {n} vertices but the body has {} bytes",
            body.len()
        ));
    }
    let f = |i: usize| {
        f64::from(f32::from_le_bytes(
            body[4 * i..4 * i + 4].try_into().expect("4 bytes"),
        ))
    };
    (0..n)
        .map(|k| {
            let p = RelayPoint {
                x: DVec3::new(f(7 * k), f(7 * k + 1), f(7 * k + 2)),
                n: DVec3::new(f(7 * k + 3), f(7 * k + 4), f(7 * k + 5)),
                intensity: f(7 * k + 6),
            };
            let ok = p.x.is_finite() && p.intensity.is_finite() && (p.n.length() - 1.0).abs() < 1e-3;
            ok.then_some(p)
                .ok_or_else(|| format!("vertex {k} is not finite or its normal is not of unit length"))
        })
        .collect()
}

#[derive(Serialize)]
struct VolumeJson<'a> {
    shape_zyx: [usize; 3],
    x: [f64; 2],
    y: [f64; 2],
    z: [f64; 2],
    voxel_m: [f64; 3],
    order: &'static str,
    method: &'a crate::plan::Method,
    solver: String,
    pairs: usize,
    max: f32,
    depth_threshold: f64,
    timings_s: &'a [(String, f64)],
}

/// Writes every output of a reconstruction into `dir`.
pub fn write_outputs(dir: &Path, r: &ReconResult, events: &EventSink) -> Result<RunOutputs, PipelineError> {
    let mut files = Vec::new();
    let wrote = |name: &str, files: &mut Vec<String>| {
        events.emit(RunEvent::Output { name: name.into() });
        files.push(name.to_owned());
    };
    let g = &r.volume.grid;
    let p = dir.join("volume.npy");
    write_volume(&p, &r.volume).map_err(recon_io(&p))?;
    wrote("volume.npy", &mut files);
    let max = r.volume.max_value();
    let json = VolumeJson {
        shape_zyx: [g.shape[2], g.shape[1], g.shape[0]],
        x: g.x,
        y: g.y,
        z: g.z,
        voxel_m: g.voxel().to_array(),
        order: "C order [nz, ny, nx]; voxel centres at min + (i + 0.5) * voxel",
        method: &r.settings.method,
        solver: r.settings.solver.to_string(),
        pairs: r.pairs,
        max,
        depth_threshold: r.settings.depth_threshold,
        timings_s: &r.timings,
    };
    let p = dir.join("volume.json");
    crate::store::write_atomic(
        &p,
        serde_json::to_string_pretty(&json)
            .expect("serialises")
            .as_bytes(),
    )
    .map_err(io(&p))?;
    wrote("volume.json", &mut files);
    let depth = r.volume.depth_map(r.settings.depth_threshold as f32);
    let p = dir.join("depth.npy");
    write_npy(&p, &[depth.shape[1], depth.shape[0]], &depth.depth).map_err(recon_io(&p))?;
    wrote("depth.npy", &mut files);
    let p = dir.join("depth.png");
    write_depth_png(&p, &depth).map_err(recon_io(&p))?;
    wrote("depth.png", &mut files);
    let p = dir.join("albedo.png");
    write_albedo_png(&p, &depth).map_err(recon_io(&p))?;
    wrote("albedo.png", &mut files);
    if let Some(cloud) = &r.cloud {
        let p = dir.join("gaussians.ply");
        let tmp = dir.join("gaussians.ply.tmp");
        let mut w = BufWriter::new(File::create(&tmp).map_err(io(&tmp))?);
        periscope_recon::gtr::write_ply(cloud, &mut w).map_err(io(&tmp))?;
        w.into_inner()
            .map_err(|e| PipelineError::storage(&tmp, e.into_error()))?
            .sync_all()
            .map_err(io(&tmp))?;
        std::fs::rename(&tmp, &p).map_err(io(&p))?;
        wrote("gaussians.ply", &mut files);
    }
    Ok(RunOutputs {
        files,
        volume_max: max,
        depth_pixels: depth.depth.iter().filter(|d| d.is_finite()).count(),
        pixels: depth.depth.len(),
        primitives: r.cloud.as_ref().map(|c| c.len()),
        final_loss: r.train.as_ref().map(|t| t.final_loss),
        timings: r.timings.clone(),
    })
}

//! Run outputs (`DESIGN.md` §6): `volume.npy` (float32 [nz, ny, nx]), `volume.json`,
//! `depth.npy` (float32 [ny, nx] for a relay facing ±z, else over the volume's two
//! axes across the relay's normal; metres, NaN where nothing was found), `depth.png`,
//! `albedo.png`, `gaussians.ply` (3D-GTR only); and the relay point cloud `relay.ply`.
use std::path::Path;

use periscope_recon::DepthAxis;
use periscope_recon::io::{write_albedo_png, write_depth_png, write_npy, write_volume};
use serde::Serialize;

use super::reconstruct::ReconResult;
use super::{PipelineError, ReconError};
use crate::events::{EventSink, RunEvent};
use crate::run_dir::file;

/// The relay point cloud's file name.
pub const RELAY_PLY: &str = crate::run_dir::file::RELAY;

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
    move |e| {
        PipelineError::Recon(ReconError::Output {
            path: path.to_path_buf(),
            source: e,
        })
    }
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
    /// What `depth.npy` and the images look along.
    depth: DepthJson,
    timings_s: &'a [(String, f64)],
    /// Where the synthesis and the solver ran: `device` ("cpu" or "gpu"), and for a
    /// GPU its adapter, backend and driver.
    compute: &'a periscope_recon::gpu::DeviceInfo,
    /// The fit's last epoch loss (method `gtr`): the run catalogue's score of the fit.
    #[serde(skip_serializing_if = "Option::is_none")]
    final_loss: Option<f64>,
    /// The fit's settings the data chose (method `gtr`): `batch`, `surface_spread_m`,
    /// whether the capture counted as `coarse`, and the `pair_gains` it estimated.
    #[serde(skip_serializing_if = "Option::is_none")]
    fit: Option<FitJson>,
}

/// [`VolumeJson::depth`]: the depth map's axis (the volume's axis nearest the relay's
/// normal: `z` for our instrument's walls, `y` for a Zaragoza wall), whether depth away
/// from the relay grows along it (`away`: `+` or `-`), and its image's axes
/// (`columns`, then `rows`; row 0 of `depth.npy` is the smallest coordinate).
#[derive(Serialize)]
struct DepthJson {
    axis: &'static str,
    away: &'static str,
    columns: &'static str,
    rows: &'static str,
}

impl DepthJson {
    fn of(axis: DepthAxis) -> Self {
        let name = |a: usize| {
            DepthAxis {
                axis: a,
                positive: true,
            }
            .name()
        };
        let [c, r] = axis.lateral();
        Self {
            axis: axis.name(),
            away: if axis.positive { "+" } else { "-" },
            columns: name(c),
            rows: name(r),
        }
    }
}

/// [`VolumeJson::fit`].
#[derive(Serialize)]
struct FitJson {
    batch: usize,
    /// Pairs a step in the averaged epochs.
    average_batch: usize,
    surface_spread_m: Option<f64>,
    coarse: bool,
    /// The per-transient gains the fit estimated: `illumination`, `detection` or
    /// `none`.
    pair_gains: periscope_recon::gtr::PairGains,
}

/// Writes every output of a reconstruction into `dir`.
pub fn write_outputs(dir: &Path, r: &ReconResult, events: &EventSink) -> Result<RunOutputs, PipelineError> {
    let mut files = Vec::new();
    let wrote = |name: &str, files: &mut Vec<String>| {
        events.emit(RunEvent::Output { name: name.into() });
        files.push(name.to_owned());
    };
    let g = &r.volume.grid;
    let p = dir.join(file::VOLUME);
    write_volume(&p, &r.volume).map_err(recon_io(&p))?;
    wrote(file::VOLUME, &mut files);
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
        depth: DepthJson::of(r.depth_axis),
        timings_s: &r.timings,
        compute: &r.device,
        final_loss: r.train.as_ref().map(|t| t.final_loss).filter(|l| l.is_finite()),
        fit: r.train.as_ref().map(|t| FitJson {
            batch: t.batch_size,
            average_batch: t.average_batch,
            surface_spread_m: t.surface_spread,
            coarse: t.coarse,
            pair_gains: t.pair_gains,
        }),
    };
    let p = dir.join(file::VOLUME_JSON);
    crate::store::write_atomic(
        &p,
        serde_json::to_string_pretty(&json)
            .expect("serialises")
            .as_bytes(),
    )
    .map_err(io(&p))?;
    wrote(file::VOLUME_JSON, &mut files);
    let depth = r
        .volume
        .depth_map_along(r.depth_axis, r.settings.depth_threshold as f32);
    let p = dir.join(file::DEPTH);
    write_npy(&p, &[depth.shape[1], depth.shape[0]], &depth.depth).map_err(recon_io(&p))?;
    wrote(file::DEPTH, &mut files);
    let p = dir.join(file::DEPTH_PNG);
    write_depth_png(&p, &depth).map_err(recon_io(&p))?;
    wrote(file::DEPTH_PNG, &mut files);
    let p = dir.join(file::ALBEDO_PNG);
    write_albedo_png(&p, &depth).map_err(recon_io(&p))?;
    wrote(file::ALBEDO_PNG, &mut files);
    let p = dir.join(file::GAUSSIANS);
    if let Some(cloud) = &r.cloud {
        // Written whole, then atomically like every other output (a temporary file of
        // its own, synced, renamed, the directory synced; a failed write leaves none).
        let mut bytes = Vec::new();
        periscope_recon::gtr::write_ply(cloud, &mut bytes).map_err(io(&p))?;
        crate::store::write_atomic(&p, &bytes).map_err(io(&p))?;
        wrote(file::GAUSSIANS, &mut files);
    } else if std::fs::symlink_metadata(&p).is_ok_and(|m| m.file_type().is_file()) {
        // A reconstruction without primitives into a directory an earlier 3D-GTR
        // wrote to: its `gaussians.ply` would stand beside a volume it did not make.
        std::fs::remove_file(&p).map_err(io(&p))?;
        tracing::info!(path = %p.display(), "removed the gaussians.ply of an earlier reconstruction: this one fits no primitives");
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

//! Reconstruction settings: the `[recon]` table of a capture plan and the whole of a
//! `RECON.toml` for `periscope recon` share this format.
use periscope_recon::VolumeGrid;
use periscope_recon::gpu::ComputeDevice;
use periscope_recon::gtr::{
    AverageBatch, CoarseFit, Convergence, DensifySettings, GROW_FROM, Init, LossChoice, PairGains,
    SurfacePrior, TrainConfig,
};
use periscope_recon::solver::{
    FbpSettings, FkSettings, LctSettings, RsdSettings, SolverError, SolverKind, SolverSettings,
};
use serde::de::{self, value::StrDeserializer};
use serde::{Deserialize, Deserializer, Serialize, Serializer};

use crate::adaptive::{AdaptiveSettings, RawAdaptive, adaptive_settings};
use crate::config::{ConfigError, TomlSource};

/// How the hidden scene is reconstructed: `method = "gtr"`, or the name of a solver
/// run on the measured pairs (`"fbp"`, `"lct"`, `"fk"`, `"rsd"`). The solvers' names
/// are [`SolverKind`]'s serde names, so a new solver needs no edit here.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// 3D-GTR fit, virtual confocal synthesis, then [`ReconSettings::solver`].
    Gtr,
    /// A solver run on the measured pairs: FBP on any pairs, LCT and f-k on confocal
    /// planar grids only, RSD/phasor field on a planar detection grid.
    Solver(SolverKind),
}

/// The one name of [`Method::Gtr`]; every other method is a solver's name.
const GTR: &str = "gtr";

impl Serialize for Method {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            Method::Gtr => s.serialize_str(GTR),
            Method::Solver(kind) => kind.serialize(s),
        }
    }
}

impl<'de> Deserialize<'de> for Method {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        if name == GTR {
            return Ok(Method::Gtr);
        }
        solver_named(&name).map(Method::Solver).ok_or_else(|| {
            de::Error::custom(format!(
                "`{name}` is not a method: use {}",
                one_of(std::iter::once(GTR).chain(variant_names::<SolverKind>().iter().copied()))
            ))
        })
    }
}

/// Reads the `solver` key, with the message the `method` key gives.
fn solver_key<'de, D: Deserializer<'de>>(d: D) -> Result<Option<SolverKind>, D::Error> {
    let name = String::deserialize(d)?;
    solver_named(&name).map(Some).ok_or_else(|| {
        de::Error::custom(format!(
            "`{name}` is not a solver: use {}",
            one_of(variant_names::<SolverKind>().iter().copied())
        ))
    })
}

/// The solver whose serde name is `name`.
fn solver_named(name: &str) -> Option<SolverKind> {
    SolverKind::deserialize(StrDeserializer::<de::value::Error>::new(name)).ok()
}

/// The names a unit-variant enum's serde derive reads, in declaration order. The derive
/// is the one place that spells them and hands its list to
/// [`de::Error::unknown_variant`] when a name is not among them, so asking for the
/// empty name reads the list back.
fn variant_names<'de, T: Deserialize<'de>>() -> &'static [&'static str] {
    #[derive(Debug)]
    struct Names(&'static [&'static str]);
    impl std::fmt::Display for Names {
        fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
            write!(f, "{:?}", self.0)
        }
    }
    impl std::error::Error for Names {}
    impl de::Error for Names {
        fn custom<M: std::fmt::Display>(_: M) -> Self {
            Names(&[])
        }
        fn unknown_variant(_: &str, expected: &'static [&'static str]) -> Self {
            Names(expected)
        }
    }
    T::deserialize(StrDeserializer::<Names>::new("")).map_or_else(|Names(names)| names, |_| &[])
}

/// `"a", "b" or "c"`.
fn one_of<'a>(names: impl Iterator<Item = &'a str>) -> String {
    let names: Vec<String> = names.map(|n| format!("\"{n}\"")).collect();
    match names.split_last() {
        Some((last, [])) => last.clone(),
        Some((last, rest)) => format!("{} or {last}", rest.join(", ")),
        None => String::new(),
    }
}

/// Validated reconstruction settings.
#[derive(Clone, Debug, PartialEq)]
pub struct ReconSettings {
    /// Method.
    pub method: Method,
    /// The reconstructed volume, also the 3D-GTR region of interest.
    pub volume: VolumeGrid,
    /// 3D-GTR fit settings.
    pub train: TrainConfig,
    /// Virtual confocal grid (points per axis) for `gtr`; `None` (FBP without a
    /// `virtual-grid`): points one lateral voxel pitch apart
    /// ([`periscope_recon::solver::lateral_voxel_pitch`]).
    pub virtual_resolution: Option<[usize; 2]>,
    /// Virtual relay size (metres); `None`: the measured relay's extent.
    pub virtual_size: Option<[f64; 2]>,
    /// Solver run on the virtual confocal scan for `gtr`.
    pub solver: SolverKind,
    /// How `solver = "lct"` turns the fitted primitives into a volume after `gtr`
    /// (`[gtr] virtual-scan`); the other solvers always render the scan.
    pub virtual_scan: VirtualScan,
    /// Depth-map threshold, as a fraction of the volume's maximum.
    pub depth_threshold: f64,
    /// Each solver's settings (`[lct]`, `[fk]`, `[rsd]`, `[fbp]`), for the method of the
    /// same name and for the solver after `gtr`.
    pub solvers: SolverSettings,
    /// Whether the counts are divided by the laser's `cos θ / d²` falloff first.
    pub laser_falloff: LaserFalloff,
    /// How an adaptive capture, or its replay, chooses its pairs (`[adaptive]`).
    pub adaptive: AdaptiveSettings,
    /// Where the synthesis and the solvers run (`[compute] device`).
    pub compute: ComputeDevice,
}

/// How the volume after 3D-GTR is made with `solver = "lct"` (`[gtr] virtual-scan`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum VirtualScan {
    /// The virtual confocal scan rendered point by point, then LCT. The default.
    Render,
    /// Each primitive splatted once onto the scan's grid and filtered once by what LCT
    /// makes of a light cone ([`periscope_recon::synth::splat_lct`]); no transient is
    /// rendered. About a quarter of the time; a different image (docs/recon.md,
    /// "LCT after 3D-GTR without the scan").
    Splat,
}

/// Whether a capture's histograms carry the falloff of a point-source laser, which
/// the reconstruction then divides out (`laser-falloff`; docs/ytal.md, "Laser
/// falloff").
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum LaserFalloff {
    /// Rendered y-tal captures whose laser visits more than one point: yes; a run's
    /// own captures (a collimated laser) and measured y-tal captures: no.
    Auto,
    /// Divide every histogram by `cos θ / d²` from the capture's laser origin.
    CosInverseSquare,
    /// Take the counts as they are.
    None,
}

#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub(crate) struct RawRecon {
    #[serde(default)]
    method: Option<Method>,
    volume: Option<RawVolume>,
    #[serde(default)]
    gtr: RawGtr,
    #[serde(default, deserialize_with = "solver_key")]
    solver: Option<SolverKind>,
    #[serde(default)]
    depth_threshold: Option<f64>,
    #[serde(default)]
    fbp: Option<FbpSettings>,
    #[serde(default)]
    lct: Option<LctSettings>,
    #[serde(default)]
    fk: Option<FkSettings>,
    #[serde(default)]
    rsd: Option<RsdSettings>,
    #[serde(default)]
    laser_falloff: Option<String>,
    #[serde(default)]
    adaptive: RawAdaptive,
    #[serde(default)]
    compute: RawCompute,
}

/// `[compute]`: where the reconstruction's heavy work runs.
#[derive(Deserialize, Default)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub(crate) struct RawCompute {
    #[serde(default)]
    device: ComputeDevice,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
pub(crate) struct RawVolume {
    #[serde(deserialize_with = "crate::config::exact::array")]
    x: [f64; 2],
    #[serde(deserialize_with = "crate::config::exact::array")]
    y: [f64; 2],
    #[serde(deserialize_with = "crate::config::exact::array")]
    z: [f64; 2],
    #[serde(deserialize_with = "crate::config::exact::array")]
    shape: [usize; 3],
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields, rename_all = "kebab-case")]
struct RawGtr {
    #[serde(default = "default_primitives")]
    primitives: usize,
    epochs: Option<usize>,
    batch: Option<usize>,
    #[serde(default = "default_lr_scale")]
    lr_scale: f64,
    #[serde(default)]
    seed: u64,
    #[serde(default = "default_init")]
    init: String,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    virtual_grid: Option<[usize; 2]>,
    #[serde(default, deserialize_with = "crate::config::exact::option")]
    virtual_size: Option<[f64; 2]>,
    initial_scale: Option<f64>,
    #[serde(default = "default_densify")]
    densify: bool,
    split_scale: Option<f64>,
    average_from: Option<f64>,
    #[serde(default = "default_loss")]
    loss: String,
    #[serde(default = "default_pair_gains")]
    pair_gains: String,
    tolerance: Option<f64>,
    epoch_pairs: Option<usize>,
    #[serde(default = "default_virtual_scan")]
    virtual_scan: String,
    surface_spread: Option<f64>,
    grow_from: Option<f64>,
    average_batch: Option<usize>,
}

fn default_virtual_scan() -> String {
    "render".into()
}

fn default_pair_gains() -> String {
    "auto".into()
}

impl Default for RawGtr {
    fn default() -> Self {
        RawGtr {
            primitives: default_primitives(),
            epochs: None,
            batch: None,
            lr_scale: default_lr_scale(),
            seed: 0,
            init: default_init(),
            virtual_grid: None,
            virtual_size: None,
            initial_scale: None,
            densify: default_densify(),
            split_scale: None,
            average_from: None,
            loss: default_loss(),
            pair_gains: default_pair_gains(),
            tolerance: None,
            epoch_pairs: None,
            virtual_scan: default_virtual_scan(),
            surface_spread: None,
            grow_from: None,
            average_batch: None,
        }
    }
}

/// The depth map's default mask, a fraction of the volume's maximum. The volume is the
/// box-filtered mean over each voxel, so a surface's peak follows its integrated
/// intensity; for a uniformly bright object 0.4 of the maximum is close to half its
/// level, which a blurred edge crosses at the true edge (docs/pipeline.md, "Depth maps").
const DEFAULT_DEPTH_THRESHOLD: f64 = 0.4;

/// The virtual scan's points per axis over the detection extent for `solver = "lct"`,
/// `"fk"` and `"rsd"` when `[gtr] virtual-grid` is not set (FBP's scan follows the
/// voxels instead).
const GRID_SOLVERS_VIRTUAL_GRID: [usize; 2] = [64, 64];

/// Farthest a volume may reach from the instrument, metres.
const MAX_EXTENT_M: f64 = 100.0;

/// The narrowest a volume axis may be, metres.
const MIN_EXTENT_M: f64 = 1e-3;

fn default_primitives() -> usize {
    2000
}
/// Counted epochs when the plan sets none: at least this many ...
const DEFAULT_EPOCHS: usize = 16;
/// ... and at least this many optimiser steps: 32 epochs of a 1,024-pair capture in
/// batches of 4. A smaller capture gets more epochs; the fit's cost, which follows the
/// steps, stays that of the larger one. The 4,096 steps this was before, with 8
/// rounds of densification, left 2 cm bars 2 cm apart one blob on an independent
/// 4 cm-pitch render and cost the oblique two-torso render 0.16 IoU
/// (docs/recon.md, "More steps and more rounds of densification").
const DEFAULT_MIN_STEPS: usize = 8192;
/// Pairs an epoch trains on at most, by default ([`TrainConfig::epoch_pairs`]; 0: all).
const DEFAULT_EPOCH_PAIRS: usize = 0;

/// The convergence test's windows (`[gtr] tolerance`, [`Convergence`]): two windows of
/// 256 steps compared, after at least 1,024 averaged steps.
const CONVERGE_WINDOW_STEPS: usize = 256;
const CONVERGE_MIN_STEPS: usize = 1024;

/// The convergence test of `[gtr] tolerance`; none unless a tolerance above 0 is given
/// (stopping when the loss levels off cost the validation captures up to 0.024 IoU:
/// docs/recon.md, "Stopping when the loss levels off").
fn converge(
    src: &TomlSource,
    key: &dyn Fn(&str) -> String,
    g: &RawGtr,
) -> Result<Option<Convergence>, ConfigError> {
    let tolerance = g.tolerance.unwrap_or(0.0);
    if !(tolerance.is_finite() && (0.0..1.0).contains(&tolerance)) {
        return Err(src.invalid(
            &key("gtr.tolerance"),
            format!("{tolerance} is out of range: give the relative fall of the loss, 0 to 1 (e.g. 0.02), below which the fit's last stage ends early; 0 (the default) runs every epoch"),
        ));
    }
    Ok((tolerance > 0.0).then_some(Convergence {
        min_steps: CONVERGE_MIN_STEPS,
        window: CONVERGE_WINDOW_STEPS,
        tolerance,
    }))
}

fn default_loss() -> String {
    "auto".into()
}
/// Pairs per mini-batch when the plan sets none (a coarse capture takes
/// [`CoarseFit::DEFAULT_BATCH`]).
const DEFAULT_BATCH: usize = 4;
fn default_lr_scale() -> f64 {
    1.0
}
fn default_init() -> String {
    "backprojection".into()
}
fn default_densify() -> bool {
    true
}

/// Validates a `[recon]` table (keys under `prefix`, e.g. `recon.`, or `` for a
/// RECON.toml). `default_volume` supplies the volume when the table has none.
pub(crate) fn recon_settings(
    src: &TomlSource,
    prefix: &str,
    raw: RawRecon,
    default_volume: Option<VolumeGrid>,
) -> Result<ReconSettings, ConfigError> {
    let key = |k: &str| format!("{prefix}{k}");
    let method = raw.method.unwrap_or(Method::Gtr);
    // FBP with the phasor filter on the virtual scan beat LCT on every validation
    // capture (docs/recon.md, "Which solver after 3D-GTR").
    let solver = raw.solver.unwrap_or(SolverKind::Fbp);
    let volume = match raw.volume {
        Some(v) => {
            for (name, r) in [("x", v.x), ("y", v.y), ("z", v.z)] {
                if !(r[0].is_finite() && r[1].is_finite() && r[1] > r[0]) {
                    return Err(src.invalid(
                        &key(&format!("volume.{name}")),
                        format!("must be [min, max] in metres with max > min, got {r:?}"),
                    ));
                }
                if r[0].abs().max(r[1].abs()) > MAX_EXTENT_M {
                    return Err(src.invalid(
                        &key(&format!("volume.{name}")),
                        format!("{r:?} reaches beyond {MAX_EXTENT_M} m of the instrument; NLOS volumes are metres across"),
                    ));
                }
                // A hair-thin axis (1e-300 m) made voxels no solver can step through
                // (RSD counted past usize; FBP's Laplacian overflowed).
                if r[1] - r[0] < MIN_EXTENT_M {
                    return Err(src.invalid(
                        &key(&format!("volume.{name}")),
                        format!("{r:?} is {:.3e} m wide; give each axis at least 1 mm (NLOS volumes are centimetres to metres across)", r[1] - r[0]),
                    ));
                }
            }
            if v.shape.iter().any(|&n| !(2..=1024).contains(&n)) {
                return Err(src.invalid(
                    &key("volume.shape"),
                    format!("must be [nx, ny, nz], each 2 to 1024 voxels, got {:?}", v.shape),
                ));
            }
            VolumeGrid::new(v.x, v.y, v.z, v.shape).map_err(|e| src.invalid(&key("volume"), e.to_string()))?
        }
        None => default_volume.ok_or_else(|| {
            src.invalid(
                &key("volume"),
                "is required: give x, y, z ranges in metres and shape = [nx, ny, nz]",
            )
        })?,
    };
    let g = raw.gtr;
    if !(1..=1_000_000).contains(&g.primitives) {
        return Err(src.invalid(&key("gtr.primitives"), "must be 1 to 1,000,000"));
    }
    if let Some(f) = g.grow_from
        && !(f > 0.0 && f <= 1.0)
    {
        return Err(src.invalid(
            &key("gtr.grow-from"),
            format!("{f} is out of range: give the fraction of `primitives` the fit starts with, above 0 and at most 1 (1: all of them from the start)"),
        ));
    }
    if let Some(epochs) = g.epochs
        && !(1..=10_000).contains(&epochs)
    {
        return Err(src.invalid(&key("gtr.epochs"), "must be 1 to 10,000"));
    }
    if let Some(b) = g.batch
        && !(1..=65_536).contains(&b)
    {
        return Err(src.invalid(&key("gtr.batch"), "must be 1 to 65,536 pairs"));
    }
    if let Some(n) = g.average_batch
        && !(1..=g.batch.unwrap_or(65_536)).contains(&n)
    {
        return Err(src.invalid(
            &key("gtr.average-batch"),
            match g.batch {
                Some(b) => format!("{n} is out of range: give the pairs a step takes in the averaged epochs, 1 to `gtr.batch` ({b})"),
                None => format!("{n} is out of range: give the pairs a step takes in the averaged epochs, 1 to 65,536 (a fit takes at most its batch)"),
            },
        ));
    }
    // The largest batch the fit may take: a coarse capture's, where the plan sets none.
    let batch_at_most = g.batch.unwrap_or(DEFAULT_BATCH.max(CoarseFit::DEFAULT_BATCH));
    if let Some(n) = g.epoch_pairs
        && n != 0
        && !(batch_at_most..=100_000_000).contains(&n)
    {
        return Err(src.invalid(
            &key("gtr.epoch-pairs"),
            format!("{n} is out of range: give the pairs an epoch trains on, from the batch ({batch_at_most}) up, or 0 for every pair of the capture"),
        ));
    }
    if !(g.lr_scale > 0.0 && g.lr_scale <= 100.0) {
        return Err(src.invalid(
            &key("gtr.lr-scale"),
            "must be in (0, 100]: it multiplies every learning rate",
        ));
    }
    if let Some(grid) = g.virtual_grid
        && grid.iter().any(|&n| !(2..=1024).contains(&n))
    {
        return Err(src.invalid(&key("gtr.virtual-grid"), "must be two counts, 2 to 1024"));
    }
    // Volumes are bounded at 100 m from the instrument; a virtual relay wider than
    // that, or narrower than a millimetre, is no scan (1e308 m made an infinite bin
    // width after the whole capture).
    if let Some(s) = g.virtual_size
        && !s.iter().all(|v| v.is_finite() && (1e-3..=200.0).contains(v))
    {
        return Err(src.invalid(
            &key("gtr.virtual-size"),
            format!(
                "{s:?} is out of range: give two lengths in metres, 1 mm to 200 m (the relay's extent, say)"
            ),
        ));
    }
    for (name, value) in [("initial-scale", g.initial_scale), ("split-scale", g.split_scale)] {
        if let Some(v) = value
            && !(v.is_finite() && v > 1e-3 && v < 1.0)
        {
            return Err(src.invalid(
                &key(&format!("gtr.{name}")),
                format!("{v} m is out of range: give a scale between 1 mm and 1 m, or leave it out for the default"),
            ));
        }
    }
    let spread = g.surface_spread.unwrap_or(0.0);
    if !(spread.is_finite() && (0.0..1.0).contains(&spread)) {
        return Err(src.invalid(
            &key("gtr.surface-spread"),
            format!("{spread} m is out of range: give the depth spread within a column that the surface prior weighs as much as the data, up to 1 m, or 0 to turn the prior off"),
        ));
    }
    if let Some(v) = g.average_from
        && !(0.0..=1.0).contains(&v)
    {
        return Err(src.invalid(
            &key("gtr.average-from"),
            format!("{v} is out of range: give the fraction of the epochs after which iterates are averaged, 0 to 1 (1: the last iterate, as the paper)"),
        ));
    }
    let init = match g.init.as_str() {
        "uniform" => Init::Uniform,
        "backprojection" => Init::Backprojection {
            grid: [32, 32, 16],
            uniform_fraction: 0.2,
        },
        other => {
            return Err(src.invalid(
                &key("gtr.init"),
                format!("`{other}` is not an initialisation: use \"backprojection\" or \"uniform\""),
            ));
        }
    };
    let loss = match g.loss.as_str() {
        "auto" => LossChoice::Auto,
        "l2" => LossChoice::L2,
        "poisson" => LossChoice::Poisson,
        other => {
            return Err(src.invalid(
                &key("gtr.loss"),
                format!("`{other}` is not a loss: use \"auto\" (Poisson unless a bin is negative, then L2), \"poisson\" or \"l2\""),
            ));
        }
    };
    let pair_gains = match g.pair_gains.as_str() {
        "auto" => PairGains::Auto,
        "illumination" => PairGains::Illumination,
        "detection" => PairGains::Detection,
        "none" => PairGains::None,
        other => {
            return Err(src.invalid(
                &key("gtr.pair-gains"),
                format!("`{other}` is not a choice: use \"auto\" (each illumination point's gain estimated where the capture states none; the default), \"none\" (every transient's gain 1, or as the capture states it), \"illumination\" (each illumination point's gain estimated from the data, jointly with the fit, starting from what the capture states) or \"detection\" (each detection point's, with a fixed laser)"),
            ));
        }
    };
    let virtual_scan = match g.virtual_scan.as_str() {
        "splat" => VirtualScan::Splat,
        "render" => VirtualScan::Render,
        other => {
            return Err(src.invalid(
                &key("gtr.virtual-scan"),
                format!("`{other}` is not a choice: use \"render\" (the scan rendered, then LCT; the default) or \"splat\" (LCT's volume from the primitives in one filter, without the scan); only solver = \"lct\" reads it"),
            ));
        }
    };
    // One surface per pixel of the volume's image: along z until the reconstruction
    // sees the relay (`ReconInput::depth_axis` turns it to face the relay's normal).
    let prior = |spread: f64| {
        (spread > 0.0).then(|| SurfacePrior {
            spread,
            cell: volume.voxel()[0].max(volume.voxel()[1]),
            axis: Default::default(),
        })
    };
    let mut train = TrainConfig {
        primitives: g.primitives,
        loss,
        pair_gains,
        init,
        // A plan's own `epochs` is exact; without one the steps decide.
        epochs: g.epochs.unwrap_or(DEFAULT_EPOCHS),
        min_steps: if g.epochs.is_some() { 0 } else { DEFAULT_MIN_STEPS },
        batch_size: g.batch.unwrap_or(DEFAULT_BATCH),
        seed: g.seed,
        initial_scale: g.initial_scale,
        densify: DensifySettings {
            until: if g.densify {
                DensifySettings::default().until
            } else {
                0.0
            },
            target_scale: g.split_scale,
            // Growing needs the rounds, and steps between them for what they add to
            // settle: a plan's own `epochs` (a short fit) starts with every primitive.
            grow_from: match (g.densify, g.grow_from, g.epochs) {
                (false, _, _) => 1.0,
                (true, Some(f), _) => f,
                (true, None, None) => GROW_FROM,
                (true, None, Some(_)) => 1.0,
            },
            ..DensifySettings::default()
        },
        average_from: g.average_from.unwrap_or(TrainConfig::default().average_from),
        // Half the pairs a step where the iterates are averaged, at the same steps; a
        // plan's own `epochs` keeps the fit it was measured with.
        average_batch: match (g.average_batch, g.epochs) {
            (Some(n), _) => AverageBatch::Pairs(n),
            (None, None) => AverageBatch::Half,
            (None, Some(_)) => AverageBatch::Same,
        },
        converge: converge(src, &key, &g)?,
        epoch_pairs: g.epoch_pairs.unwrap_or(DEFAULT_EPOCH_PAIRS),
        surface: prior(spread),
        // What the plan leaves unset, a coarse capture sets its own way.
        coarse: Some(CoarseFit {
            batch_size: g.batch.unwrap_or(CoarseFit::DEFAULT_BATCH),
            surface: prior(g.surface_spread.unwrap_or(SurfacePrior::DEFAULT_SPREAD)),
            grow_from: if g.densify {
                g.grow_from.unwrap_or(1.0)
            } else {
                1.0
            },
            average_batch: g.average_batch.map_or(AverageBatch::Same, AverageBatch::Pairs),
        }),
        ..TrainConfig::default()
    };
    for group in [
        &mut train.adam.centres,
        &mut train.adam.scales,
        &mut train.adam.rotations,
        &mut train.adam.albedo,
    ] {
        group.lr *= g.lr_scale;
    }
    let depth_threshold = raw.depth_threshold.unwrap_or(DEFAULT_DEPTH_THRESHOLD);
    if !(depth_threshold > 0.0 && depth_threshold < 1.0) {
        return Err(src.invalid(
            &key("depth-threshold"),
            "must be a fraction in (0, 1) of the volume's maximum",
        ));
    }
    let solver_err = |table: &str, e: SolverError| match e {
        SolverError::Setting {
            name,
            value,
            expected,
        } => src.invalid(
            &key(&format!("{table}.{name}")),
            format!("{value} is out of range: {expected}"),
        ),
        other => src.invalid(&key(table), other.to_string()),
    };
    let solvers = SolverSettings {
        lct: raw.lct.unwrap_or_default(),
        fk: raw.fk.unwrap_or_default(),
        rsd: raw.rsd.unwrap_or_default(),
        fbp: raw.fbp.unwrap_or_default(),
        compute: Default::default(),
    };
    solvers.validate().map_err(|(table, e)| solver_err(table, e))?;
    let laser_falloff = match raw.laser_falloff.as_deref().unwrap_or("auto") {
        "auto" => LaserFalloff::Auto,
        "cos-inverse-square" if prefix.is_empty() => LaserFalloff::CosInverseSquare,
        "cos-inverse-square" => {
            return Err(src.invalid(
                &key("laser-falloff"),
                "a run's laser is the instrument's collimated beam, whose spot gets the same power wherever \
                 it points: leave the key out, or compensate a point-source capture with `periscope recon \
                 --config` instead",
            ));
        }
        "none" => LaserFalloff::None,
        other => {
            return Err(src.invalid(
                &key("laser-falloff"),
                format!(
                    "`{other}` is not a laser falloff: use \"auto\" (rendered y-tal captures only), \
                     \"cos-inverse-square\" (a point-source laser) or \"none\" (a collimated laser)"
                ),
            ));
        }
    };
    Ok(ReconSettings {
        method,
        volume,
        train,
        // FBP's wave follows the voxels, so its scan does too (one point per lateral
        // voxel pitch); the other solvers keep a grid of 64 × 64 over the detection
        // extent, which scored better for them (docs/recon.md, "The phasor wavelength
        // after 3D-GTR").
        virtual_resolution: g
            .virtual_grid
            .or((solver != SolverKind::Fbp).then_some(GRID_SOLVERS_VIRTUAL_GRID)),
        virtual_size: g.virtual_size,
        solver,
        virtual_scan,
        depth_threshold,
        solvers,
        laser_falloff,
        adaptive: adaptive_settings(src, prefix, raw.adaptive)?,
        compute: raw.compute.device,
    })
}

/// Loads a `RECON.toml`.
pub fn load_recon(
    src: &TomlSource,
    default_volume: Option<VolumeGrid>,
) -> Result<ReconSettings, ConfigError> {
    let raw: RawRecon = src.parse()?;
    recon_settings(src, "", raw, default_volume)
}

/// Checks a `RECON.toml` as far as it can be without the capture it is for: its keys,
/// types and values, and the whole of it (against its own volume) when it gives one;
/// one without a volume takes the capture's, which is known only once the capture is
/// read. The settings come back (with a 32³ placeholder volume where none is given).
pub fn check_recon(src: &TomlSource) -> Result<ReconSettings, ConfigError> {
    let raw: RawRecon = src.parse()?;
    match raw.volume {
        Some(_) => recon_settings(src, "", raw, None),
        None => {
            let placeholder =
                VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.5, 1.5], [32, 32, 32]).expect("a valid grid");
            recon_settings(src, "", raw, Some(placeholder))
        }
    }
}

/// The default reconstruction settings for a capture with no `RECON.toml`.
pub fn default_recon(volume: VolumeGrid) -> ReconSettings {
    let src = TomlSource::from_text("<defaults>", "");
    recon_settings(&src, "", RawRecon::default(), Some(volume)).expect("the defaults are valid")
}

#[cfg(test)]
mod tests {
    use periscope_recon::solver::FbpFilter;

    use super::*;

    fn volume() -> VolumeGrid {
        VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.2, 1.0], [8, 8, 8]).unwrap()
    }

    /// A RECON.toml of `[gtr]` with `text` in it, read over [`volume`].
    fn read_gtr(text: &str) -> Result<ReconSettings, ConfigError> {
        load_recon(
            &TomlSource::from_text("recon.toml", format!("[gtr]\n{text}\n")),
            Some(volume()),
        )
    }

    #[test]
    fn solver_tables_are_read_and_checked() {
        let src = TomlSource::from_text(
            "recon.toml",
            "method = \"fbp\"\n[fbp]\nfilter = \"laplacian\"\nfalloff = 0.0\nrelay-weights = false\n\
             [lct]\nsnr = 4.0\n[rsd]\nrelay-weights = false\n",
        );
        let s = load_recon(&src, Some(volume())).unwrap();
        assert_eq!(
            (s.solvers.fbp.filter, s.solvers.fbp.falloff),
            (FbpFilter::Laplacian, 0.0)
        );
        assert_eq!(s.solvers.lct.snr, Some(4.0));
        assert!(!s.solvers.fbp.relay_weights && !s.solvers.rsd.relay_weights);
        assert!(s.solvers.lct.relay_weights && s.solvers.fk.relay_weights);
        // Out of range: the error names the file, the line and the key.
        let src = TomlSource::from_text("recon.toml", "method = \"fbp\"\n[fbp]\nfalloff = 9.0\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("fbp.falloff") && e.contains("between 0 and 4"), "{e}");
        // The hierarchical backprojection and its bound.
        let src = TomlSource::from_text(
            "recon.toml",
            "method = \"fbp\"\n[fbp]\nbackprojection = \"hierarchical\"\npath-error = 0.125\n",
        );
        let s = load_recon(&src, Some(volume())).unwrap();
        assert_eq!(
            (s.solvers.fbp.backprojection, s.solvers.fbp.path_error),
            (periscope_recon::solver::FbpBackprojection::Hierarchical, 0.125)
        );
        let src = TomlSource::from_text("recon.toml", "method = \"fbp\"\n[fbp]\npath-error = 0.9\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("path-error") && e.contains("0.5 wavelengths"), "{e}");
        // f-k migration, as a method and as the solver after 3D-GTR, with its table.
        let src = TomlSource::from_text(
            "recon.toml",
            "method = \"fk\"\nsolver = \"fk\"\n[fk]\nfalloff = 2.0\n",
        );
        let s = load_recon(&src, Some(volume())).unwrap();
        assert_eq!(
            (s.method, s.solver, s.solvers.fk.falloff),
            (Method::Solver(SolverKind::Fk), SolverKind::Fk, 2.0)
        );
        let src = TomlSource::from_text("recon.toml", "method = \"fk\"\n[fk]\ngrid-tolerance = -1.0\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("fk.grid-tolerance"), "{e}");
        // Unknown keys too.
        let src = TomlSource::from_text("recon.toml", "[rsd]\ncolour = 1\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("colour"), "{e}");
        // No table: the phasor filter, and FBP after 3D-GTR.
        let d = default_recon(volume());
        assert_eq!(
            (d.solvers.fbp.filter, d.solvers.fbp.backprojection, d.solver),
            (
                FbpFilter::Phasor,
                periscope_recon::solver::FbpBackprojection::Auto,
                SolverKind::Fbp
            )
        );
    }

    #[test]
    fn methods_and_solvers_are_the_solvers_serde_names() {
        // `gtr`, then every solver by its own name, as a method and after 3D-GTR; the
        // name a volume.json records is the name the plan gave.
        let src = TomlSource::from_text("recon.toml", "method = \"gtr\"\n");
        assert_eq!(load_recon(&src, Some(volume())).unwrap().method, Method::Gtr);
        assert_eq!(default_recon(volume()).method, Method::Gtr);
        assert_eq!(serde_json::to_string(&Method::Gtr).unwrap(), "\"gtr\"");
        let names = variant_names::<SolverKind>();
        assert_eq!(names, ["lct", "fk", "rsd", "fbp"]);
        for name in names {
            let src = TomlSource::from_text(
                "recon.toml",
                format!("method = \"{name}\"\nsolver = \"{name}\"\n"),
            );
            let s = load_recon(&src, Some(volume())).unwrap();
            let Method::Solver(kind) = s.method else {
                panic!("{name} read as {:?}", s.method)
            };
            assert_eq!((kind, s.solver), (s.solver, kind), "{name}");
            assert_eq!(
                kind.to_string(),
                *name,
                "SolverKind's Display and serde names differ"
            );
            assert_eq!(serde_json::to_string(&s.method).unwrap(), format!("\"{name}\""));
        }
        // An unknown name: the file, the line, the key and every name there is.
        let src = TomlSource::from_text("plan.toml", "name = \"x\"\n\n[recon]\nmethod = \"phasor\"\n");
        #[derive(Deserialize)]
        #[allow(dead_code)]
        struct Plan {
            name: String,
            recon: RawRecon,
        }
        let e = src.parse::<Plan>().err().expect("an unknown method").to_string();
        assert_eq!(
            e,
            "plan.toml:4: key `recon.method`: `phasor` is not a method: use \"gtr\", \"lct\", \"fk\", \"rsd\" or \"fbp\"",
        );
        let src = TomlSource::from_text("recon.toml", "solver = \"gtr\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert_eq!(
            e,
            "recon.toml:1: key `solver`: `gtr` is not a solver: use \"lct\", \"fk\", \"rsd\" or \"fbp\"",
        );
        let src = TomlSource::from_text("recon.toml", "method = 3\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.starts_with("recon.toml:1: key `method`: invalid type"), "{e}");
    }

    #[test]
    fn the_virtual_grid_follows_the_voxels_for_fbp_unless_set() {
        // FBP after 3D-GTR (the default): no grid, so the scan takes the voxel pitch.
        assert_eq!(default_recon(volume()).virtual_resolution, None);
        // The other solvers keep 64 × 64 over the detection extent.
        for solver in ["lct", "fk", "rsd"] {
            let src = TomlSource::from_text("recon.toml", format!("solver = \"{solver}\"\n"));
            assert_eq!(
                load_recon(&src, Some(volume())).unwrap().virtual_resolution,
                Some([64, 64]),
                "{solver}"
            );
        }
        // A grid that is set is kept, for any solver, and checked.
        let src = TomlSource::from_text("recon.toml", "[gtr]\nvirtual-grid = [48, 40]\n");
        assert_eq!(
            load_recon(&src, Some(volume())).unwrap().virtual_resolution,
            Some([48, 40])
        );
        let src = TomlSource::from_text("recon.toml", "[gtr]\nvirtual-grid = [1, 40]\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("gtr.virtual-grid") && e.contains("2 to 1024"), "{e}");
    }

    #[test]
    fn the_laser_falloff_is_read_and_checked() {
        assert_eq!(default_recon(volume()).laser_falloff, LaserFalloff::Auto);
        for (text, want) in [
            ("cos-inverse-square", LaserFalloff::CosInverseSquare),
            ("none", LaserFalloff::None),
            ("auto", LaserFalloff::Auto),
        ] {
            let src = TomlSource::from_text("recon.toml", format!("laser-falloff = \"{text}\"\n"));
            assert_eq!(load_recon(&src, Some(volume())).unwrap().laser_falloff, want);
        }
        let src = TomlSource::from_text("recon.toml", "laser-falloff = \"inverse-square\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(
            e.contains("laser-falloff") && e.contains("cos-inverse-square"),
            "{e}"
        );
        // A plan's own reconstruction: the instrument's laser is collimated.
        let src = TomlSource::from_text("plan.toml", "laser-falloff = \"cos-inverse-square\"\n");
        let raw: RawRecon = src.parse().unwrap();
        let e = recon_settings(&src, "recon.", raw, Some(volume()))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("recon.laser-falloff") && e.contains("collimated"),
            "{e}"
        );
    }

    #[test]
    fn gtr_scales_and_densification_are_read_and_checked() {
        let d = default_recon(volume());
        assert!(d.train.densify.until > 0.0 && d.train.initial_scale.is_none());
        let src = TomlSource::from_text(
            "recon.toml",
            "[gtr]\ninitial-scale = 0.02\ndensify = false\nsplit-scale = 0.005\n",
        );
        let s = load_recon(&src, Some(volume())).unwrap();
        assert_eq!(s.train.initial_scale, Some(0.02));
        assert_eq!(s.train.densify.until, 0.0);
        assert_eq!(s.train.densify.target_scale, Some(0.005));
        for bad in [
            "initial-scale = 0.0",
            "initial-scale = 2.0",
            "split-scale = -1.0",
            "split-scale = nan",
        ] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\n{bad}\n"));
            let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
            let key = bad.split(' ').next().unwrap();
            assert!(
                e.contains(&format!("gtr.{key}")) && e.contains("between 1 mm and 1 m"),
                "{e}"
            );
        }
    }

    #[test]
    fn gtr_averaging_is_read_and_checked() {
        let d = default_recon(volume());
        assert!(d.train.average_from > 0.0 && d.train.average_from < 1.0);
        let src = TomlSource::from_text("recon.toml", "[gtr]\naverage-from = 1.0\n");
        assert_eq!(load_recon(&src, Some(volume())).unwrap().train.average_from, 1.0);
        for bad in ["-0.1", "1.5", "nan"] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\naverage-from = {bad}\n"));
            let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
            assert!(e.contains("gtr.average-from") && e.contains("0 to 1"), "{e}");
        }
    }

    #[test]
    fn gtr_surface_spread_is_read_and_checked() {
        // Off by default; one column per lateral voxel (the test volume's are 0.125 m).
        assert_eq!(default_recon(volume()).train.surface, None);
        let read = |text: &str| {
            load_recon(
                &TomlSource::from_text("recon.toml", format!("[gtr]\nsurface-spread = {text}\n")),
                Some(volume()),
            )
        };
        assert_eq!(
            read("0.005").unwrap().train.surface.map(|p| p.spread),
            Some(0.005)
        );
        assert_eq!(read("0.0").unwrap().train.surface, None);
        let on = read("0.018").unwrap().train.surface.expect("the prior is on");
        assert_eq!((on.spread, on.cell), (SurfacePrior::DEFAULT_SPREAD, 0.125));
        for bad in ["-0.01", "1.5", "nan"] {
            let e = read(bad).unwrap_err().to_string();
            assert!(
                e.contains("gtr.surface-spread") && e.contains("0 to turn the prior off"),
                "{e}"
            );
        }
    }

    #[test]
    fn a_coarse_capture_takes_what_the_plan_leaves_unset() {
        let read = |text: &str| read_gtr(text).unwrap().train;
        let prior = |spread| {
            Some(SurfacePrior {
                spread,
                cell: 0.125,
                axis: Default::default(),
            })
        };
        // Unset: batches of 4 without the prior, or 8 with it on a coarse capture;
        // half the primitives at the start, or all of them on a coarse capture or in a
        // plan's own epochs.
        assert_eq!(read("epochs = 16").densify.grow_from, 1.0);
        let t = read("");
        assert_eq!((t.batch_size, t.surface), (4, None));
        assert_eq!(t.densify.grow_from, GROW_FROM);
        assert_eq!(
            t.coarse,
            Some(CoarseFit {
                batch_size: 8,
                surface: prior(SurfacePrior::DEFAULT_SPREAD),
                grow_from: 1.0,
                average_batch: AverageBatch::Same,
            })
        );
        // What the plan sets holds on every capture.
        let t = read("batch = 4\nsurface-spread = 0\ngrow-from = 0.75\naverage-batch = 3");
        assert_eq!(t.densify.grow_from, 0.75);
        assert_eq!(
            t.coarse,
            Some(CoarseFit {
                batch_size: 4,
                surface: None,
                grow_from: 0.75,
                average_batch: AverageBatch::Pairs(3),
            })
        );
        // Without densification there are no rounds to grow in.
        let t = read("densify = false\ngrow-from = 0.5");
        assert_eq!(t.densify.grow_from, 1.0);
        assert_eq!(t.coarse.map(|c| c.grow_from), Some(1.0));
        for bad in ["0", "-0.5", "1.5", "nan"] {
            let e = load_recon(
                &TomlSource::from_text("recon.toml", format!("[gtr]\ngrow-from = {bad}\n")),
                Some(volume()),
            )
            .unwrap_err()
            .to_string();
            assert!(e.contains("gtr.grow-from") && e.contains("at most 1"), "{e}");
        }
        let t = read("surface-spread = 0.03");
        assert_eq!((t.batch_size, t.surface), (4, prior(0.03)));
        assert_eq!(
            t.coarse.map(|c| (c.batch_size, c.surface)),
            Some((8, prior(0.03)))
        );
    }

    #[test]
    fn the_averaged_epochs_take_half_the_batch_unless_the_plan_sets_epochs() {
        let read = |text: &str| read_gtr(text).map(|r| r.train.average_batch);
        assert_eq!(read("").unwrap(), AverageBatch::Half);
        assert_eq!(read("batch = 8").unwrap(), AverageBatch::Half);
        assert_eq!(read("epochs = 16").unwrap(), AverageBatch::Same);
        assert_eq!(read("average-batch = 3").unwrap(), AverageBatch::Pairs(3));
        assert_eq!(
            read("epochs = 16\nbatch = 4\naverage-batch = 4").unwrap(),
            AverageBatch::Pairs(4)
        );
        for (bad, says) in [
            ("average-batch = 0", "1 to 65,536"),
            ("batch = 2\naverage-batch = 3", "1 to `gtr.batch` (2)"),
        ] {
            let e = read(bad).unwrap_err().to_string();
            assert!(e.contains("gtr.average-batch") && e.contains(says), "{e}");
        }
        let e = read("average-batch = -1").unwrap_err().to_string();
        assert!(e.contains("average-batch"), "{e}");
    }

    #[test]
    fn gtr_pair_gains_are_read_and_checked() {
        assert_eq!(default_recon(volume()).train.pair_gains, PairGains::Auto);
        for (text, want) in [
            ("illumination", PairGains::Illumination),
            ("detection", PairGains::Detection),
            ("none", PairGains::None),
            ("auto", PairGains::Auto),
        ] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\npair-gains = \"{text}\"\n"));
            assert_eq!(load_recon(&src, Some(volume())).unwrap().train.pair_gains, want);
        }
        let src = TomlSource::from_text("recon.toml", "[gtr]\npair-gains = \"estimate\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("gtr.pair-gains") && e.contains("illumination"), "{e}");
    }

    #[test]
    fn gtr_virtual_scan_is_read_and_checked() {
        assert_eq!(default_recon(volume()).virtual_scan, VirtualScan::Render);
        for (text, want) in [("splat", VirtualScan::Splat), ("render", VirtualScan::Render)] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\nvirtual-scan = \"{text}\"\n"));
            assert_eq!(load_recon(&src, Some(volume())).unwrap().virtual_scan, want);
        }
        let src = TomlSource::from_text("recon.toml", "[gtr]\nvirtual-scan = \"rendered\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("gtr.virtual-scan") && e.contains("\"render\""), "{e}");
        // The virtual relay's size within what a scan can be: 1e308 m passed and failed
        // the run after its capture, with an infinite bin width.
        for size in ["[1e308, 1e308]", "[1e6, 1.0]", "[1e-300, 1.0]", "[0.0, 1.0]"] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\nvirtual-size = {size}\n"));
            let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
            assert!(
                e.contains("gtr.virtual-size") && e.contains("200 m"),
                "{size}: {e}"
            );
        }
        let src = TomlSource::from_text("recon.toml", "[gtr]\nvirtual-size = [1.5, 1.5]\n");
        assert!(load_recon(&src, Some(volume())).is_ok());
    }

    #[test]
    fn the_compute_device_is_read_and_checked() {
        assert_eq!(default_recon(volume()).compute, ComputeDevice::Auto);
        for (text, want) in [
            ("auto", ComputeDevice::Auto),
            ("cpu", ComputeDevice::Cpu),
            ("gpu", ComputeDevice::Gpu),
        ] {
            let src = TomlSource::from_text("recon.toml", format!("[compute]\ndevice = \"{text}\"\n"));
            assert_eq!(load_recon(&src, Some(volume())).unwrap().compute, want);
        }
        let src = TomlSource::from_text("recon.toml", "[compute]\ndevice = \"tpu\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("compute.device") && e.contains("gpu"), "{e}");
        let src = TomlSource::from_text("recon.toml", "[compute]\nadapter = \"x\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("adapter"), "{e}");
    }

    #[test]
    fn gtr_tolerance_is_read_and_checked() {
        assert_eq!(default_recon(volume()).train.converge, None);
        let src = TomlSource::from_text("recon.toml", "[gtr]\ntolerance = 0.02\n");
        let c = load_recon(&src, Some(volume())).unwrap().train.converge.unwrap();
        assert_eq!(c.tolerance, 0.02);
        let src = TomlSource::from_text("recon.toml", "[gtr]\ntolerance = 0\n");
        assert_eq!(load_recon(&src, Some(volume())).unwrap().train.converge, None);
        for bad in ["1.5", "-0.1", "nan"] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\ntolerance = {bad}\n"));
            let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
            assert!(e.contains("gtr.tolerance") && e.contains("0 to 1"), "{bad}: {e}");
        }
    }

    #[test]
    fn gtr_epoch_pairs_are_read_and_checked() {
        let src = TomlSource::from_text("recon.toml", "[gtr]\nepoch-pairs = 4096\n");
        assert_eq!(load_recon(&src, Some(volume())).unwrap().train.epoch_pairs, 4096);
        let src = TomlSource::from_text("recon.toml", "[gtr]\nepoch-pairs = 0\n");
        assert_eq!(load_recon(&src, Some(volume())).unwrap().train.epoch_pairs, 0);
        // At least the largest batch the fit may take: a coarse capture's 8 when the
        // plan sets none.
        let src = TomlSource::from_text("recon.toml", "[gtr]\nepoch-pairs = 6\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(e.contains("gtr.epoch-pairs") && e.contains("batch (8)"), "{e}");
        let src = TomlSource::from_text("recon.toml", "[gtr]\nbatch = 2\nepoch-pairs = 3\n");
        assert_eq!(load_recon(&src, Some(volume())).unwrap().train.epoch_pairs, 3);
    }

    #[test]
    fn gtr_loss_is_read_and_checked() {
        assert_eq!(default_recon(volume()).train.loss, LossChoice::Auto);
        for (text, loss) in [
            ("auto", LossChoice::Auto),
            ("l2", LossChoice::L2),
            ("poisson", LossChoice::Poisson),
        ] {
            let src = TomlSource::from_text("recon.toml", format!("[gtr]\nloss = \"{text}\"\n"));
            assert_eq!(load_recon(&src, Some(volume())).unwrap().train.loss, loss);
        }
        let src = TomlSource::from_text("recon.toml", "[gtr]\nloss = \"l1\"\n");
        let e = load_recon(&src, Some(volume())).unwrap_err().to_string();
        assert!(
            e.contains("gtr.loss") && e.contains("`l1`") && e.contains("poisson"),
            "{e}"
        );
    }
}

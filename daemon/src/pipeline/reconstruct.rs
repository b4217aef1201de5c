//! Reconstruction: the 3D-GTR fit (already running during capture when streaming),
//! virtual confocal synthesis on a plane fitted to the detection points, and a
//! conventional solver; or a solver straight on the measured pairs.
use std::sync::mpsc::{Receiver, Sender};
use std::thread::JoinHandle;
use std::time::Instant;

use glam::DVec3;
use periscope_recon::gpu::{Compute, ComputeDevice, DeviceInfo, GpuError};
use periscope_recon::gtr::{
    CancelToken, GaussianCloud, Kernel, LiveModel, TrainError, TrainSummary, Trainer, resolvable_separation,
};
use periscope_recon::linalg::fit_plane;
use periscope_recon::relay::VirtualRelay;
use periscope_recon::solver::{SolverError, SolverKind, SolverSettings};
use periscope_recon::solver::{lateral_voxel_pitch, phasor_wavelength};
use periscope_recon::synth::{SynthError, default_axis, splat_lct, synthesise_on};
use periscope_recon::{DepthAxis, RoiBox, TimeAxis, TransientSet, Volume, VolumeGrid};

use super::{Control, PipelineError, ReconError};
use crate::events::{EventSink, RunEvent};
use crate::plan::{Method, ReconSettings, VirtualScan};

pub use crate::budget::MAX_VIRTUAL_RESOLUTION;
use crate::budget::VIRTUAL_SCAN_BINS;

/// What a reconstruction needs.
pub struct ReconInput {
    /// Settings.
    pub settings: ReconSettings,
    /// Transients in hidden path length.
    pub set: TransientSet,
    /// Detection points (the virtual relay is fitted to them).
    pub detection_points: Vec<DVec3>,
    /// A point on the instrument's side (orients the virtual relay).
    pub viewpoint: DVec3,
}

impl ReconInput {
    /// The volume's axis nearest the relay's normal, away from the relay: the normal of
    /// the plane through the detection points, turned to face the volume's centre (or,
    /// where no plane fits them, the direction from their centroid to that centre).
    /// Our instrument's relays face +z; a Zaragoza wall faces −y. The depth map and the
    /// surface prior look along it.
    pub fn depth_axis(&self) -> DepthAxis {
        let g = &self.settings.volume;
        let centre = 0.5 * (g.min() + g.max());
        let points = &self.detection_points;
        let direction = match fit_plane(points) {
            Some(plane) if plane.normal.dot(centre - plane.centre) < 0.0 => -plane.normal,
            Some(plane) => plane.normal,
            None if points.is_empty() => DVec3::Z,
            None => centre - points.iter().copied().sum::<DVec3>() / points.len() as f64,
        };
        DepthAxis::nearest(direction).unwrap_or(DepthAxis::Z)
    }

    /// This input with its surface prior (and the coarse fit's) looking along the
    /// relay's depth axis, its columns the volume's voxel pitch across the two others.
    fn oriented(mut self) -> Self {
        let axis = self.depth_axis();
        let voxel = self.settings.volume.voxel();
        let cell = axis.lateral().map(|a| voxel[a]).into_iter().fold(0.0, f64::max);
        let train = &mut self.settings.train;
        let coarse = train.coarse.as_mut().and_then(|c| c.surface.as_mut());
        for prior in train.surface.as_mut().into_iter().chain(coarse) {
            if prior.axis != axis {
                prior.axis = axis;
                prior.cell = cell;
            }
        }
        self
    }
}

/// A finished reconstruction.
pub struct ReconResult {
    /// The volume.
    pub volume: Volume,
    /// The fitted Gaussians (method `gtr`).
    pub cloud: Option<GaussianCloud>,
    /// Fit summary (method `gtr`).
    pub train: Option<TrainSummary>,
    /// Settings used.
    pub settings: ReconSettings,
    /// Pairs used.
    pub pairs: usize,
    /// Seconds per step (fit, synthesis, solver).
    pub timings: Vec<(String, f64)>,
    /// Where the synthesis and the solver ran (`[compute] device`).
    pub device: DeviceInfo,
    /// The axis the depth map looks along ([`ReconInput::depth_axis`]).
    pub depth_axis: DepthAxis,
}

/// Opens the device `[compute] device` asks for, and says which it is.
fn open_compute(device: ComputeDevice) -> Result<Compute, ReconError> {
    let compute = Compute::open(device)?;
    tracing::info!(device = %compute.info(), asked = %device, "reconstruction device ([compute] device sets it)");
    Ok(compute)
}

/// Puts `trainer`'s steps on the GPU `[compute] device` asks for, if any: with
/// `device = "gpu"` a failure of the GPU is the fit's, with `"auto"` the fit goes on
/// on the CPU ([`Trainer::use_gpu`]).
fn fit_on(trainer: &mut Trainer, device: ComputeDevice) -> Result<(), GpuError> {
    if let Compute::Gpu(gpu) = Compute::open(device)? {
        tracing::info!(device = %gpu.device_info(), "the 3D-GTR fit runs on the GPU ([compute] device sets it)");
        trainer.use_gpu(gpu, device == ComputeDevice::Gpu);
    }
    Ok(())
}

/// Runs `work` on `compute`; with `device = "auto"`, a GPU that fails is left for the
/// CPU, with a warning, and the work done again there (`[compute] device = "gpu"`
/// makes the failure the run's).
fn on_device<T, E>(
    device: ComputeDevice,
    compute: &mut Compute,
    gpu_error: fn(&E) -> Option<&GpuError>,
    mut work: impl FnMut(&Compute) -> Result<T, E>,
) -> Result<T, E> {
    match work(compute) {
        Err(e) if device == ComputeDevice::Auto && compute.gpu().is_some() => match gpu_error(&e) {
            Some(g) => {
                tracing::warn!(error = %g, "the GPU failed: the reconstruction continues on the CPU");
                *compute = Compute::Cpu;
                work(compute)
            }
            None => Err(e),
        },
        other => other,
    }
}

/// Runs `kind` on `set` with `settings` on `compute` ([`on_device`]).
fn solve_on(
    kind: SolverKind,
    set: &TransientSet,
    grid: &VolumeGrid,
    settings: &SolverSettings,
    device: ComputeDevice,
    compute: &mut Compute,
) -> Result<Volume, ReconError> {
    fn gpu_error(e: &SolverError) -> Option<&GpuError> {
        match e {
            SolverError::Gpu(g) => Some(g),
            _ => None,
        }
    }
    on_device(device, compute, gpu_error, |c| {
        let settings = SolverSettings {
            compute: c.clone(),
            ..settings.clone()
        };
        kind.solve(set, grid, &settings)
    })
    .map_err(ReconError::from)
}

type TrainerThread = JoinHandle<Result<(Trainer, TrainSummary, f64), TrainError>>;

/// A reconstruction in progress: data so far, and the optimiser thread if started.
pub(crate) struct Fit {
    input: ReconInput,
    trainer: Option<TrainerThread>,
    cancel: CancelToken,
}

fn roi(grid: &VolumeGrid) -> Result<RoiBox, PipelineError> {
    Ok(RoiBox::from_bounds(grid.min(), grid.max()).map_err(ReconError::from)?)
}

impl Fit {
    /// The fit of a capture about to start. For 3D-GTR the virtual relay the result
    /// is rendered on is built now from the planned detection points, so a layout no
    /// plane fits (fewer than three points, all in a line) is refused before the laser
    /// goes on, not after the capture and the fit.
    pub(crate) fn new(input: ReconInput) -> Result<Fit, PipelineError> {
        let input = input.oriented();
        if input.settings.method == Method::Gtr {
            virtual_relay(&input)?;
        }
        Ok(Fit {
            input,
            trainer: None,
            cancel: CancelToken::new(),
        })
    }

    pub(crate) fn is_training(&self) -> bool {
        self.trainer.is_some()
    }

    /// Adds transients that will not be streamed: stored pairs when not training, or
    /// an adaptive capture's last batch, which goes to [`Fit::refit`] directly.
    pub(crate) fn add(&mut self, more: &TransientSet) -> Result<(), PipelineError> {
        Ok(self.input.set.extend(more).map_err(ReconError::from)?)
    }

    /// Starts the optimiser on `first`, with `feed` bringing the rest; with `live`, the
    /// model goes to its sender after each batch's live training of at least its steps
    /// (an adaptive capture's choices, [`Trainer::report_live_model`]).
    pub(crate) fn start_training(
        &mut self,
        first: TransientSet,
        feed: Receiver<TransientSet>,
        events: EventSink,
        control: Control,
        live: Option<(Sender<LiveModel>, usize)>,
    ) -> Result<(), PipelineError> {
        let config = self.input.settings.train.clone();
        let device = self.input.settings.compute;
        let roi = roi(&self.input.settings.volume)?;
        let cancel = self.cancel.clone();
        control.watch(&cancel);
        let handle = std::thread::Builder::new()
            .name("gtr-trainer".into())
            .spawn(move || {
                let t = Instant::now();
                let mut trainer = Trainer::new(config, roi, first)?;
                fit_on(&mut trainer, device)?;
                if let Some((tx, steps)) = live {
                    trainer.report_live_model(tx, steps);
                }
                let summary = trainer.run(Some(feed), &cancel, &mut |e| {
                    if control.stop_requested() {
                        cancel.cancel();
                    }
                    events.emit(RunEvent::Train(e.clone()));
                })?;
                Ok((trainer, summary, t.elapsed().as_secs_f64()))
            })
            .map_err(|e| ReconError::Thread(format!("could not start: {e}")))?;
        self.trainer = Some(handle);
        Ok(())
    }

    /// Waits for the fit (or runs it, if it never started) and reconstructs.
    pub(crate) fn finish(
        mut self,
        events: &EventSink,
        control: &Control,
    ) -> Result<ReconResult, PipelineError> {
        match self.trainer.take() {
            Some(handle) => {
                let (trainer, summary, secs) = handle
                    .join()
                    .map_err(|_| ReconError::Thread("panicked".into()))?
                    .map_err(ReconError::from)?;
                if summary.cancelled {
                    return Err(stopped(control, trainer.data().len()));
                }
                let data = trainer.data().clone();
                let input = ReconInput {
                    set: data,
                    ..self.take_input()
                };
                let relay = virtual_relay(&input)?;
                finish_gtr(&input, relay, trainer, summary, secs).and_then(finite)
            }
            None => reconstruct(self.take_input(), events, control),
        }
    }

    /// Stops the fit that ran alongside the capture and fits its data afresh, with the
    /// full schedule from a new start: an adaptive capture's live fit exists to choose
    /// pairs, and continuing it costs the result (on the validation captures, all of
    /// their pairs streamed in the adaptive batches and continued scored 0.940 and
    /// 0.906 where a fit from the start scores 0.964 and 0.976; docs/adaptive.md).
    pub(crate) fn refit(
        mut self,
        events: &EventSink,
        control: &Control,
    ) -> Result<ReconResult, PipelineError> {
        let set = match self.trainer.take() {
            Some(handle) => {
                self.cancel.cancel();
                let (trainer, _, _) = handle
                    .join()
                    .map_err(|_| ReconError::Thread("panicked".into()))?
                    .map_err(ReconError::from)?;
                // What was streamed, and what was added without being streamed.
                let mut set = trainer.data().clone();
                set.extend(&self.input.set).map_err(ReconError::from)?;
                set
            }
            None => {
                let empty = TransientSet::new(*self.input.set.axis()).map_err(ReconError::from)?;
                std::mem::replace(&mut self.input.set, empty)
            }
        };
        control.check(crate::events::Stage::Reconstruction, set.len())?;
        reconstruct(
            ReconInput {
                set,
                ..self.take_input()
            },
            events,
            control,
        )
    }

    fn take_input(&mut self) -> ReconInput {
        let empty = TransientSet::new(*self.input.set.axis()).expect("an axis that already holds data");
        ReconInput {
            settings: self.input.settings.clone(),
            set: std::mem::replace(&mut self.input.set, empty),
            detection_points: std::mem::take(&mut self.input.detection_points),
            viewpoint: self.input.viewpoint,
        }
    }
}

impl Drop for Fit {
    /// A fit abandoned (the run paused, failed or was aborted during capture) stops its
    /// optimiser instead of training on to its last epoch.
    fn drop(&mut self) {
        self.cancel.cancel();
    }
}

/// The error for an optimiser that was cancelled: the run's pause or abort.
fn stopped(control: &Control, pairs: usize) -> PipelineError {
    match control.check(crate::events::Stage::Reconstruction, pairs) {
        Err(e) => e,
        Ok(()) => PipelineError::Aborted(pairs),
    }
}

/// The virtual confocal scan's relay after 3D-GTR: a plane fitted to the detection
/// points, with the settings' `virtual-size` and `virtual-grid`, or else one voxel
/// pitch between points over the points and the volume's footprint. Built before a
/// fit where it can be, so that points no plane fits (a line scan) are refused
/// before the fit's minutes instead of after them.
fn virtual_relay(input: &ReconInput) -> Result<VirtualRelay, ReconError> {
    let s = &input.settings;
    let fitted = VirtualRelay::fitted(
        &input.detection_points,
        input.viewpoint,
        s.virtual_size,
        s.virtual_resolution.unwrap_or([2, 2]),
    )?;
    // Without a `virtual-grid`, the scan's points lie one lateral voxel pitch apart:
    // the final FBP's wave is 2.5 voxel pitches long (`phasor_wavelength`), which that
    // pitch samples as y-tal's rule samples a measured relay, and a denser scan only
    // costs time (docs/recon.md, "The phasor wavelength after 3D-GTR").
    let mut relay = match s.virtual_resolution {
        Some(_) => fitted,
        None => fitted.with_pitch(
            lateral_voxel_pitch(&s.volume, fitted.normal),
            MAX_VIRTUAL_RESOLUTION,
        )?,
    };
    if s.virtual_size.is_none() {
        // The virtual scan spans the detection points and the volume's footprint on
        // the plane, so nothing fitted beyond the measured aperture is cut off.
        let g = &s.volume;
        let corners: Vec<DVec3> = (0..8)
            .map(|c| DVec3::new(g.x[c & 1], g.y[(c >> 1) & 1], g.z[(c >> 2) & 1]))
            .collect();
        // Its columns on a whole fraction of the voxel pitch where the relay is level,
        // so the final FBP shares each path length among all pairs at one offset.
        relay = relay
            .covering(&corners, MAX_VIRTUAL_RESOLUTION)?
            .columns_fitting(g.voxel().x, MAX_VIRTUAL_RESOLUTION);
    }
    Ok(relay)
}

/// The final FBP's wave after 3D-GTR is at least this many times the smallest
/// separation the capture resolves ([`resolvable_separation`]): a phasor field of
/// wavelength λ resolves about λ/2.
const WAVES_PER_SEPARATION: f64 = 2.0;

fn finish_gtr(
    input: &ReconInput,
    relay: VirtualRelay,
    trainer: Trainer,
    summary: TrainSummary,
    fit_secs: f64,
) -> Result<ReconResult, PipelineError> {
    let s = &input.settings;
    let t = Instant::now();
    let pitch = relay.spacing();
    tracing::info!(
        columns = relay.resolution[0],
        rows = relay.resolution[1],
        pitch_m = pitch[0].max(pitch[1]),
        "virtual confocal scan ([gtr] virtual-grid and virtual-size set it)"
    );
    let axis = default_axis(&relay, &s.volume, VIRTUAL_SCAN_BINS);
    let kernels = trainer.cloud().kernels();
    let (device, volume, timings) = if s.solver == SolverKind::Lct && s.virtual_scan == VirtualScan::Splat {
        // LCT's volume straight from the primitives: no scan is rendered.
        let solvers = s.solvers.for_virtual_scan();
        let volume = splat_lct(
            &kernels,
            &relay,
            &s.volume,
            axis,
            trainer.render_options(),
            &solvers.lct,
        )
        .map_err(ReconError::from)?
        .to_world(&s.volume);
        let timings = vec![
            ("fit".into(), fit_secs),
            ("splat and lct".into(), t.elapsed().as_secs_f64()),
        ];
        (Compute::Cpu.info(), volume, timings)
    } else {
        render_and_solve(input, &relay, &trainer, axis, &kernels, fit_secs)?
    };
    Ok(ReconResult {
        device,
        depth_axis: input.depth_axis(),
        volume,
        cloud: Some(trainer.cloud().clone()),
        train: Some(summary),
        settings: s.clone(),
        pairs: input.set.len(),
        timings,
    })
}

/// What made the volume after 3D-GTR: the device, the volume, and the steps' timings.
type Solved = (DeviceInfo, Volume, Vec<(String, f64)>);

/// The virtual confocal scan of `kernels` on `relay`, rendered where `[compute]` says,
/// and the solver's volume of it: the device it ran on, the volume and the timings.
fn render_and_solve(
    input: &ReconInput,
    relay: &VirtualRelay,
    trainer: &Trainer,
    axis: TimeAxis,
    kernels: &[Kernel],
    fit_secs: f64,
) -> Result<Solved, PipelineError> {
    let s = &input.settings;
    let t = Instant::now();
    let mut compute = open_compute(s.compute)?;
    fn gpu_error(e: &SynthError) -> Option<&GpuError> {
        match e {
            SynthError::Gpu(g) => Some(g),
            SynthError::Transient(_) => None,
        }
    }
    let scan = on_device(s.compute, &mut compute, gpu_error, |c| {
        synthesise_on(c, kernels, relay, axis, trainer.render_options())
    })
    .map_err(|e| match e {
        SynthError::Transient(e) => ReconError::from(e),
        SynthError::Gpu(e) => ReconError::from(e),
    })?;
    let synth_secs = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let mut solvers = s.solvers.for_virtual_scan();
    if solvers.fbp.wavelength.is_none() {
        // No finer a wave than the capture resolves: the virtual scan is dense and wide,
        // but what the fit put between the measured pairs' reach is its own lumps.
        let rule = phasor_wavelength(&scan.set, &s.volume, &solvers.fbp);
        let centre = 0.5 * (s.volume.min() + s.volume.max());
        if let Some(separation) =
            resolvable_separation(trainer.data(), centre, trainer.render_options().sigma_sys)
        {
            let floor = WAVES_PER_SEPARATION * separation;
            if floor > rule && floor.is_finite() {
                tracing::info!(
                    wavelength = floor,
                    separation_m = separation,
                    "FBP phasor wavelength after 3D-GTR: twice the smallest separation the capture resolves, \
                     longer than the voxels' rule here ([fbp] wavelength sets it)"
                );
                solvers.fbp.wavelength = Some(floor);
            }
        }
    }
    let volume = solve_on(s.solver, &scan.set, &s.volume, &solvers, s.compute, &mut compute)?;
    let timings = vec![
        ("fit".into(), fit_secs),
        ("synthesis".into(), synth_secs),
        (format!("solver ({})", s.solver), t.elapsed().as_secs_f64()),
    ];
    Ok((compute.info(), volume, timings))
}

/// Reconstructs a complete set of transients (offline, or a resumed run whose capture
/// was already complete).
pub fn reconstruct(
    input: ReconInput,
    events: &EventSink,
    control: &Control,
) -> Result<ReconResult, PipelineError> {
    if input.set.is_empty() {
        return Err(ReconError::Empty.into());
    }
    let input = input.oriented();
    let s = &input.settings;
    let result = match s.method {
        Method::Gtr => {
            let relay = virtual_relay(&input)?;
            let t = Instant::now();
            let mut trainer = Trainer::new(s.train.clone(), roi(&s.volume)?, input.set.clone())
                .map_err(ReconError::from)?;
            fit_on(&mut trainer, s.compute).map_err(ReconError::from)?;
            let cancel = CancelToken::new();
            control.watch(&cancel);
            let summary = trainer
                .run(None, &cancel, &mut |e| {
                    if control.stop_requested() {
                        cancel.cancel();
                    }
                    events.emit(RunEvent::Train(e.clone()));
                })
                .map_err(ReconError::from)?;
            if summary.cancelled {
                return Err(stopped(control, input.set.len()));
            }
            finish_gtr(&input, relay, trainer, summary, t.elapsed().as_secs_f64())
        }
        Method::Solver(kind) => {
            let t = Instant::now();
            let mut compute = open_compute(s.compute)?;
            let volume = solve_on(kind, &input.set, &s.volume, &s.solvers, s.compute, &mut compute)?;
            Ok(ReconResult {
                device: compute.info(),
                depth_axis: input.depth_axis(),
                volume,
                cloud: None,
                train: None,
                settings: s.clone(),
                pairs: input.set.len(),
                timings: vec![(format!("solver ({kind})"), t.elapsed().as_secs_f64())],
            })
        }
    }?;
    finite(result)
}

/// `result`, unless its volume holds a NaN or an infinity, which is never written as a
/// result (every way to a volume, offline, streamed or refitted, ends here).
/// A volume of zeros is kept (a fit that found nothing writes one), but not silently.
fn finite(result: ReconResult) -> Result<ReconResult, PipelineError> {
    if let Some(i) = result.volume.data.iter().position(|v| !v.is_finite()) {
        return Err(ReconError::NotFinite {
            index: i,
            value: result.volume.data[i],
        }
        .into());
    }
    if result.volume.data.iter().all(|&v| v == 0.0) {
        tracing::warn!(
            pairs = result.pairs,
            "the volume is zero everywhere: nothing was reconstructed. Check that the volume lies where the \
             capture's pairs see (its bounds, in metres) and, for 3D-GTR on values far from photon counts \
             (about 1e-10 or less a bin), scale the capture's values up: the fit's optimiser does not move \
             on gradients below about 1e-12"
        );
    }
    Ok(result)
}

#[cfg(test)]
mod tests {
    use periscope_recon::gtr::SurfacePrior;
    use periscope_recon::{DepthAxis, TimeAxis, TransientSet, VolumeGrid};

    use super::*;
    use crate::plan::default_recon;

    /// A 5 × 4 grid of detection points on the plane through `origin` spanned by `u`
    /// and `v`, and settings over `volume` with the surface prior on (and the coarse
    /// fit's).
    fn input(origin: DVec3, u: DVec3, v: DVec3, volume: VolumeGrid) -> ReconInput {
        let mut settings = default_recon(volume);
        let prior = SurfacePrior {
            spread: 0.02,
            cell: 0.5,
            axis: DepthAxis::Z,
        };
        settings.train.surface = Some(prior);
        if let Some(coarse) = settings.train.coarse.as_mut() {
            coarse.surface = Some(prior);
        }
        let points = (0..20)
            .map(|i| origin + u * (i % 5) as f64 * 0.1 + v * (i / 5) as f64 * 0.1)
            .collect();
        ReconInput {
            settings,
            set: TransientSet::new(TimeAxis {
                start: 0.0,
                width: 0.01,
                bins: 64,
            })
            .unwrap(),
            detection_points: points,
            viewpoint: origin,
        }
    }

    /// A Zaragoza wall (the x–z plane, its scene at −y) gives the depth axis −y, and
    /// the surface prior's columns run along y, a voxel of x and z across; a wall
    /// facing +z keeps z.
    #[test]
    fn the_depth_axis_and_the_prior_follow_the_relays_normal() {
        let volume = VolumeGrid::new([-0.4, 0.4], [-1.0, -0.1], [-0.3, 0.3], [16, 30, 20]).unwrap();
        let wall = input(DVec3::new(-0.2, 0.0, -0.15), DVec3::X, DVec3::Z, volume);
        let want = DepthAxis {
            axis: 1,
            positive: false,
        };
        assert_eq!(wall.depth_axis(), want);
        let oriented = wall.oriented();
        let t = &oriented.settings.train;
        let priors = [t.surface, t.coarse.and_then(|c| c.surface)];
        for prior in priors.into_iter().flatten() {
            assert_eq!(prior.axis, want);
            assert!(
                (prior.cell - 0.05).abs() < 1e-12,
                "x's voxel 0.05 m, z's 0.03 m: {}",
                prior.cell
            );
        }
        // The normal's sign comes from the volume, not from the order of the points.
        let flipped = input(DVec3::new(-0.2, 0.0, -0.15), DVec3::Z, DVec3::X, volume);
        assert_eq!(flipped.depth_axis(), want);
        // Our instrument's wall, facing +z.
        let ours = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.2, 1.2], [20, 20, 20]).unwrap();
        let wall = input(DVec3::new(-0.2, -0.15, 0.0), DVec3::X, DVec3::Y, ours);
        assert_eq!(wall.depth_axis(), DepthAxis::Z);
        // Points in a line fit no plane: the direction to the volume decides.
        let mut line = input(DVec3::new(-0.2, 0.0, 0.0), DVec3::X, DVec3::ZERO, volume);
        line.detection_points.truncate(5);
        assert_eq!(line.depth_axis(), want);
    }
}

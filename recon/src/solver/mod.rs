//! Conventional NLOS solvers: LCT and f-k migration for confocal grids, RSD / phasor-field propagation for
//! planar (also non-confocal) data, and filtered backprojection for any pairs on any
//! relay. Each takes a [`TransientSet`](crate::TransientSet) in hidden path length, measured or synthesised,
//! and returns a [`Volume`](crate::Volume) on the user's world-frame grid.
//!
//! LCT and RSD work in the relay plane's own frame (columns along u, rows along v, depth
//! along the normal) because their speed comes from shift invariance in that frame;
//! their result is box-filtered onto the world grid ([`FrameVolume`]).
mod confocal;
mod fbp;
mod fft;
mod fk;
mod frame;
mod lct;
mod quadrature;
mod rsd;
mod scan;

pub use fbp::{
    AUTO_MAX_COST, FbpBackprojection, FbpFilter, FbpSettings, PATH_ERROR_WAVELENGTHS, PHASOR_PITCHES,
    SIGMA_PER_WAVELENGTH, VIRTUAL_SCAN_SIGMA_PER_WAVELENGTH, fbp, fbp_on, lateral_voxel_pitch,
    phasor_wavelength, sampling_pitch,
};
pub use fk::{FkSettings, fk, fk_frame, fk_work_bytes};
pub use frame::FrameVolume;
pub use lct::{LctSettings, VIRTUAL_SCAN_SNR, default_snr, lct, lct_frame, lct_of_apexes, lct_work_bytes};
pub use quadrature::{REACH_PITCHES, pair_weights, relay_areas};
pub use rsd::{RSD_CONFOCAL_OFFSET, RsdSettings, rsd, rsd_frame};
pub use scan::{MAX_REACH_FACTOR, PlanarScan};

use crate::relay::GeometryError;
use crate::volume::VolumeError;

/// Whether `grid` lies wholly behind every detection point of `pairs`, against its
/// normal (each of the volume's corners checked): no pair sees any of it, and a
/// backprojection there images the hidden scene's mirror.
pub(crate) fn behind_every_detection_point(pairs: &[crate::Pair], grid: &crate::volume::VolumeGrid) -> bool {
    let corners: Vec<glam::DVec3> = (0..8)
        .map(|c: usize| glam::DVec3::new(grid.x[c & 1], grid.y[(c >> 1) & 1], grid.z[(c >> 2) & 1]))
        .collect();
    pairs
        .iter()
        .all(|p| corners.iter().all(|&c| p.nd.dot(c - p.xd) <= 0.0))
}

/// [`SolverError::Axis`] where the volume lies behind the relay
/// ([`behind_every_detection_point`]): no pair sees it, and an image there is the
/// hidden scene's mirror, or nothing.
pub(crate) fn refuse_a_volume_behind(
    pairs: &[crate::Pair],
    grid: &crate::volume::VolumeGrid,
) -> Result<(), SolverError> {
    if behind_every_detection_point(pairs, grid) {
        return Err(SolverError::Axis(
            "the volume lies behind the relay, against every detection point's normal: no pair sees it, and \
             a backprojection there images the hidden scene's mirror; move the [volume] in front of the relay"
                .into(),
        ));
    }
    Ok(())
}

/// The longest wavelet envelope (6 sigma) the phasor solvers (RSD, FBP's phasor
/// filter) take, in lengths of the time axis: their padding grows with it.
pub const MAX_ENVELOPE_SPANS: f64 = 8.0;

/// Which conventional solver turns transients into a volume.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SolverKind {
    /// Light-cone transform (confocal grids on a plane).
    Lct,
    /// f-k migration (confocal grids on a plane).
    Fk,
    /// Rayleigh–Sommerfeld diffraction / phasor field (planar detection grid).
    Rsd,
    /// Filtered backprojection (any pairs, any relay).
    Fbp,
}

impl std::fmt::Display for SolverKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            SolverKind::Lct => "lct",
            SolverKind::Fk => "fk",
            SolverKind::Rsd => "rsd",
            SolverKind::Fbp => "fbp",
        })
    }
}

impl SolverKind {
    /// Runs this solver on `set`, onto `grid`, with its table of `settings`.
    pub fn solve(
        self,
        set: &crate::TransientSet,
        grid: &crate::VolumeGrid,
        settings: &SolverSettings,
    ) -> Result<crate::Volume, SolverError> {
        match self {
            SolverKind::Lct => lct(set, grid, &settings.lct),
            SolverKind::Fk => fk(set, grid, &settings.fk),
            SolverKind::Rsd => rsd(set, grid, &settings.rsd),
            SolverKind::Fbp => fbp_on(set, grid, &settings.fbp, &settings.compute),
        }
    }

    /// Every check this solver makes before it reads a count, on the `pairs` a capture
    /// will measure, its time `axis` and the volume `grid`: the pairs' layout (confocal,
    /// on a plane, on a grid), the volume's side of the relay, the settings, and the
    /// working memory of LCT, f-k migration and RSD (which grows with the grid the
    /// pairs span and the bins from path length 0). A capture that would measure every
    /// pair and then fail here can be refused before the laser goes on. Passing it does
    /// not promise the solve: a reader may leave empty transients out.
    pub fn check_layout(
        self,
        pairs: &[crate::Pair],
        axis: &crate::TimeAxis,
        grid: &crate::VolumeGrid,
        settings: &SolverSettings,
    ) -> Result<(), SolverError> {
        match self {
            SolverKind::Lct | SolverKind::Fk => {
                let tolerance = if self == SolverKind::Lct {
                    settings.lct.validate()?;
                    settings.lct.grid_tolerance
                } else {
                    settings.fk.validate()?;
                    settings.fk.grid_tolerance
                };
                refuse_a_volume_behind(pairs, grid)?;
                let scan = lct::confocal_grid(pairs, 0, tolerance)?.reaching(grid);
                if self == SolverKind::Lct {
                    lct::lct_bins(&scan, axis)?;
                } else {
                    fk::fk_bins(&scan, axis)?;
                }
            }
            SolverKind::Rsd => rsd::rsd_layout(pairs, axis, grid, &settings.rsd)?,
            SolverKind::Fbp => {
                settings.fbp.validate()?;
                if pairs.is_empty() {
                    return Err(SolverError::Empty);
                }
                refuse_a_volume_behind(pairs, grid)?;
                if settings.fbp.filter == FbpFilter::Phasor {
                    fbp::phasor_envelope(pairs, axis, grid, &settings.fbp)?;
                }
            }
        }
        Ok(())
    }
}

/// Every solver's settings, as a plan's `[recon]` or a `RECON.toml` gives them in its
/// `[lct]`, `[fk]`, `[rsd]` and `[fbp]` tables.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SolverSettings {
    /// LCT.
    pub lct: LctSettings,
    /// f-k migration.
    pub fk: FkSettings,
    /// RSD / phasor field.
    pub rsd: RsdSettings,
    /// Filtered backprojection.
    pub fbp: FbpSettings,
    /// Where the solvers' heavy work runs (`[compute] device`): FBP's backprojection
    /// runs on a GPU when this holds one; LCT, f-k and RSD run on the CPU.
    pub compute: crate::gpu::Compute,
}

impl SolverSettings {
    /// These settings for the virtual confocal scan 3D-GTR synthesises: LCT's `snr`,
    /// when not set, is [`VIRTUAL_SCAN_SNR`] instead of [`default_snr`]'s, and FBP's
    /// `sigma-per-wavelength` is [`VIRTUAL_SCAN_SIGMA_PER_WAVELENGTH`] instead of
    /// [`SIGMA_PER_WAVELENGTH`].
    pub fn for_virtual_scan(&self) -> SolverSettings {
        let mut s = self.clone();
        s.lct.snr = s.lct.snr.or(Some(VIRTUAL_SCAN_SNR));
        s.fbp.sigma_per_wavelength = s
            .fbp
            .sigma_per_wavelength
            .or(Some(VIRTUAL_SCAN_SIGMA_PER_WAVELENGTH));
        s
    }

    /// Checks every table; on a bad value, the table's name (`lct`, ...) and why.
    pub fn validate(&self) -> Result<(), (&'static str, SolverError)> {
        self.lct.validate().map_err(|e| ("lct", e))?;
        self.fk.validate().map_err(|e| ("fk", e))?;
        self.rsd.validate().map_err(|e| ("rsd", e))?;
        self.fbp.validate().map_err(|e| ("fbp", e))
    }
}

/// Why a solver could not run on the given data.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SolverError {
    /// No transients.
    #[error("the capture has no transients to reconstruct")]
    Empty,
    /// Points that should lie on a plane do not.
    #[error(
        "the {what} points are not planar (rms distance from the fitted plane {rms_mm:.1} mm > {tolerance_mm:.1} mm): \
         use the fbp solver, or method = \"gtr\" to synthesise a planar virtual scan"
    )]
    NotPlanar {
        /// Which points.
        what: &'static str,
        /// Their rms distance from the plane, mm.
        rms_mm: f64,
        /// The tolerance, mm.
        tolerance_mm: f64,
    },
    /// Points on a plane that are not on a regular grid.
    #[error(
        "the {what} points are not on a regular grid ({detail}): use the fbp solver, or method = \"gtr\" \
         to synthesise a gridded virtual scan"
    )]
    NotGrid {
        /// Which points.
        what: &'static str,
        /// What went wrong.
        detail: String,
    },
    /// LCT got a non-confocal pair.
    #[error(
        "pair {pair} is not confocal (illumination and detection {distance_mm:.1} mm apart): LCT and f-k migration \
         need confocal data; use rsd or fbp"
    )]
    NotConfocal {
        /// Index of the pair.
        pair: usize,
        /// Distance between its points, mm.
        distance_mm: f64,
    },
    /// The time axis does not suit the solver.
    #[error("time axis: {0}")]
    Axis(String),
    /// A setting outside its valid range.
    #[error("solver setting `{name}` = {value} is out of range: {expected}")]
    Setting {
        /// The setting.
        name: &'static str,
        /// Its value.
        value: String,
        /// What would be valid.
        expected: &'static str,
    },
    /// The working arrays would exceed the memory cap.
    #[error(
        "the {solver} working arrays would need {needed_mib} MiB, above the {limit_mib} MiB cap: \
         use a coarser grid or fewer bins"
    )]
    TooLarge {
        /// Solver name.
        solver: &'static str,
        /// MiB needed.
        needed_mib: usize,
        /// MiB allowed.
        limit_mib: usize,
    },
    /// Geometry failure.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// Output grid failure.
    #[error(transparent)]
    Volume(#[from] VolumeError),
    /// The GPU failed.
    #[error(transparent)]
    Gpu(#[from] crate::gpu::GpuError),
}

/// Working memory a solver may allocate, MiB.
pub const MEMORY_CAP_MIB: usize = 8 * 1024;

pub(crate) fn check_memory(solver: &'static str, bytes: usize) -> Result<(), SolverError> {
    let needed_mib = bytes.div_ceil(1 << 20);
    if needed_mib > MEMORY_CAP_MIB {
        return Err(SolverError::TooLarge {
            solver,
            needed_mib,
            limit_mib: MEMORY_CAP_MIB,
        });
    }
    Ok(())
}

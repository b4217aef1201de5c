//! A run directory's layout: the name of every file a run writes, in one place, and the
//! reads every consumer of a stored run shares (the pipeline on resume, `periscope
//! recon` and `export`, the API's downloads and geometry). See `docs/pipeline.md` for
//! what each file holds.
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

use glam::DVec3;
use serde::{Deserialize, Serialize};

use crate::config::{ConfigError, InstrumentConfig, TomlSource};
use crate::plan::{Plan, PlannedPair};

/// The files of a run directory, by name.
pub mod file {
    /// The run's state, stage, counters and timings ([`super::RunInfo`]).
    pub const RUN: &str = "run.json";
    /// The capture plan as submitted.
    pub const PLAN: &str = "plan.toml";
    /// The instrument config the run used (its token cut out).
    pub const INSTRUMENT: &str = "instrument.toml";
    /// The planned pairs.
    pub const PAIRS: &str = "pairs.json";
    /// The typed progress events, one JSON object per line.
    pub const EVENTS: &str = "events.jsonl";
    /// The histogram log (append-only, checksummed records).
    pub const HISTOGRAMS: &str = crate::store::HISTOGRAM_LOG;
    /// Bytes of the histogram log set aside by recovery.
    pub const HISTOGRAMS_DAMAGED: &str = crate::store::DAMAGED_LOG;
    /// The relay point cloud with normals (binary PLY).
    pub const RELAY: &str = "relay.ply";
    /// The LOS scan's returns, row by row as measured ([`crate::pipeline`]'s LOS log).
    pub const LOS: &str = "los.jsonl";
    /// The reconstructed volume (`.npy`, C order `[nz, ny, nx]`).
    pub const VOLUME: &str = "volume.npy";
    /// The volume's grid, method and timings.
    pub const VOLUME_JSON: &str = "volume.json";
    /// The depth map (`.npy`, `[ny, nx]`, NaN where no surface).
    pub const DEPTH: &str = "depth.npy";
    /// The depth map as an image.
    pub const DEPTH_PNG: &str = "depth.png";
    /// The albedo (peak along z) as an image.
    pub const ALBEDO_PNG: &str = "albedo.png";
    /// The fitted Gaussians (PLY in the 3DGS layout; 3D-GTR only).
    pub const GAUSSIANS: &str = "gaussians.ply";
    /// The capture as a y-tal HDF5 file.
    pub const CAPTURE: &str = "capture.hdf5";
    /// The API's export of an unfinished run's capture, and its stamp.
    pub const EXPORT_CACHE: &str = ".capture-export.hdf5";
    /// The run's tags and note ([`super::Annotations`]), kept apart from `run.json` so
    /// an operator's edit never races the pipeline's own writes of it.
    pub const ANNOTATIONS: &str = "annotations.json";
    /// An imported capture's files, as uploaded ([`super::ImportSource`]).
    pub const IMPORT_DIR: &str = "import";
    /// The reconstruction settings an imported capture came with.
    pub const RECON: &str = "recon.toml";
    /// An imported capture's geometry for 3-D views (relay points, volume).
    pub const GEOMETRY: &str = "geometry.json";
}

/// Why a run directory could not be read or written.
#[derive(Debug, thiserror::Error)]
pub enum RunDirError {
    /// A file could not be read or written, or holds something else than it should.
    #[error("run directory {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// What failed.
        source: std::io::Error,
    },
    /// The stored plan or instrument config no longer loads.
    #[error(transparent)]
    Config(#[from] ConfigError),
}

impl RunDirError {
    fn io(path: &Path, source: std::io::Error) -> RunDirError {
        RunDirError::Io {
            path: path.to_owned(),
            source,
        }
    }
}

fn io(path: &Path) -> impl Fn(std::io::Error) -> RunDirError + '_ {
    move |e| RunDirError::io(path, e)
}

/// A relay point as the LOS scan measured it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RelayPoint {
    /// Position, metres.
    pub x: DVec3,
    /// Unit normal toward the instrument.
    pub n: DVec3,
    /// Photons of its LOS return (the counts within ±1.3 jitter FWHM of its peak, less
    /// the histogram's median a bin): the spot's albedo under the diffused laser.
    pub intensity: f64,
}

/// One process's hold on a run directory while it writes the run: an exclusive
/// advisory lock (`flock`) on the directory itself, released when the hold is dropped
/// or the process ends, however it ends. A second process (a `periscope resume` of a
/// run the daemon is capturing, a second daemon, a daemon that finds a `periscope run`
/// under way in its runs directory) is refused it, so two writers never append to, cut
/// or replace the same histogram log.
#[derive(Debug)]
pub struct RunHold {
    _dir: std::fs::File,
}

impl RunHold {
    /// Holds `dir`; `Ok(None)` where another holds it now.
    pub fn take(dir: &Path) -> io::Result<Option<RunHold>> {
        let f = std::fs::File::open(dir)?;
        match f.try_lock() {
            Ok(()) => Ok(Some(RunHold { _dir: f })),
            Err(std::fs::TryLockError::WouldBlock) => Ok(None),
            Err(std::fs::TryLockError::Error(e)) => Err(e),
        }
    }

    /// Whether another hold on `dir` is taken now (by any process, this one included).
    /// Unknown (the directory cannot be opened) counts as not held.
    pub fn held(dir: &Path) -> bool {
        matches!(RunHold::take(dir), Ok(None))
    }
}

/// A run directory.
#[derive(Clone, Debug)]
pub struct RunDir {
    path: PathBuf,
}

impl RunDir {
    /// The run directory at `path` (nothing is read yet).
    pub fn new(path: impl Into<PathBuf>) -> RunDir {
        RunDir { path: path.into() }
    }

    /// The first of a run's data files (its histogram log, the log set aside by
    /// recovery, its planned pairs, its relay, its LOS scan's rows) that `path` holds,
    /// if any.
    pub fn leftover_data(path: &Path) -> Option<&'static str> {
        [
            file::HISTOGRAMS,
            file::HISTOGRAMS_DAMAGED,
            file::PAIRS,
            file::RELAY,
            file::LOS,
        ]
        .into_iter()
        .find(|f| path.join(f).symlink_metadata().is_ok())
    }

    /// The first file `path` holds under a name a new run writes there (its copies of
    /// the plan and instrument config, its events, its outputs), if any: a new run in a
    /// directory without `run.json` would replace a user's own file of that name (an
    /// instrument config kept beside its plan lost its token to the redacted copy).
    pub fn file_a_run_would_replace(path: &Path) -> Option<&'static str> {
        [
            file::PLAN,
            file::INSTRUMENT,
            file::EVENTS,
            file::VOLUME,
            file::VOLUME_JSON,
            file::DEPTH,
            file::DEPTH_PNG,
            file::ALBEDO_PNG,
            file::GAUSSIANS,
            file::CAPTURE,
            file::ANNOTATIONS,
            file::RECON,
            file::GEOMETRY,
        ]
        .into_iter()
        .find(|f| path.join(f).symlink_metadata().is_ok())
    }

    /// Whether `path` holds a run (it has a `run.json`).
    pub fn holds_run(path: &Path) -> bool {
        path.join(file::RUN).is_file()
    }

    /// The directory.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// One of its files (a name from [`mod@file`]).
    pub fn file(&self, name: &str) -> PathBuf {
        self.path.join(name)
    }

    /// The run's state, plan and instrument as stored. The stored text is what ran;
    /// scene paths in the instrument config resolve against where it was. An imported
    /// capture's run has none, and is refused with what to do instead.
    pub fn load(&self) -> Result<(RunInfo, Plan, InstrumentConfig), RunDirError> {
        let info = RunInfo::load(&self.path).map_err(io(&self.file(file::RUN)))?;
        if let Some(source) = &info.import {
            return Err(RunDirError::io(
                &self.path,
                std::io::Error::other(format!(
                    "run {} is an imported capture ({}/{}), not a capture run: it has no plan, instrument or \
                     histogram log to resume or export; reconstruct it with `periscope recon {}`, and take its \
                     capture as y-tal from {} once it has been reconstructed",
                    info.id,
                    file::IMPORT_DIR,
                    source.capture,
                    self.path.display(),
                    file::CAPTURE
                )),
            ));
        }
        // Capped and regular files only, as any config is read: a FIFO or a link to
        // `/dev/zero` put in a run directory must not hang or exhaust a resume.
        let read = |name: &str| {
            let path = self.file(name);
            crate::store::read_text_capped(&path, crate::config::MAX_TOML_BYTES).map_err(io(&path))
        };
        let instrument = InstrumentConfig::from_source(&TomlSource::from_text(
            info.instrument_path.clone(),
            read(file::INSTRUMENT)?,
        ))?;
        let plan = Plan::stored(
            &TomlSource::from_text(self.file(file::PLAN), read(file::PLAN)?),
            &instrument,
        )?;
        Ok((info, plan, instrument))
    }

    /// The planned pairs, or `None` before planning.
    pub fn planned_pairs(&self) -> Result<Option<Vec<PlannedPair>>, RunDirError> {
        let path = self.file(file::PAIRS);
        if !path.exists() {
            return Ok(None);
        }
        let bytes =
            periscope_recon::io::read_regular_capped(&path, MAX_PAIRS_JSON_BYTES).map_err(io(&path))?;
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| RunDirError::io(&path, std::io::Error::new(std::io::ErrorKind::InvalidData, e)))
    }

    /// The planned pairs of a run that got past planning.
    pub fn pairs(&self) -> Result<Vec<PlannedPair>, RunDirError> {
        self.planned_pairs()?.ok_or_else(|| {
            RunDirError::io(
                &self.file(file::PAIRS),
                std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    "the run never got past pair planning",
                ),
            )
        })
    }

    /// The relay the LOS scan measured, or `None` before the relay stage.
    pub fn relay(&self) -> Result<Option<Vec<RelayPoint>>, RunDirError> {
        read_relay_ply(&self.path)
    }
}

/// Writes the relay as a binary PLY: x y z nx ny nz intensity (float32), atomically
/// ([`crate::store::write_atomic`]: its own temporary file, synced, renamed, the
/// directory synced).
pub fn write_relay_ply(dir: &Path, relay: &[RelayPoint]) -> Result<(), RunDirError> {
    let path = dir.join(file::RELAY);
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment Periscope relay: LOS first-bounce points, normals toward the instrument, return photons\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty float intensity\nend_header\n",
        relay.len()
    );
    let mut bytes = Vec::with_capacity(header.len() + relay.len() * 28);
    bytes.extend_from_slice(header.as_bytes());
    for p in relay {
        for v in [p.x.x, p.x.y, p.x.z, p.n.x, p.n.y, p.n.z, p.intensity] {
            bytes.extend_from_slice(&(v as f32).to_le_bytes());
        }
    }
    crate::store::write_atomic(&path, &bytes).map_err(io(&path))
}

/// The most `pairs.json` may hold: 4 Mi pairs (a 2,048² confocal grid) at about 250
/// bytes each. A larger file is no plan this daemon wrote.
const MAX_PAIRS_JSON_BYTES: u64 = 1 << 30;

/// The most `relay.ply` may hold: 16 Mi relay points at 24 bytes each, with room.
const MAX_RELAY_PLY_BYTES: u64 = 1 << 30;

/// The most `run.json` may hold (its adaptive batches and errors included).
const MAX_RUN_JSON_BYTES: u64 = 64 << 20;

/// Reads `relay.ply` back (resume, the dashboard's 3-D view), or `None` if the run has
/// none yet.
pub fn read_relay_ply(dir: &Path) -> Result<Option<Vec<RelayPoint>>, RunDirError> {
    let path = dir.join(file::RELAY);
    if !path.exists() {
        return Ok(None);
    }
    let bytes = periscope_recon::io::read_regular_capped(&path, MAX_RELAY_PLY_BYTES).map_err(io(&path))?;
    parse_relay_ply(&bytes).map(Some).map_err(|m| {
        RunDirError::io(
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

/// Files a run offers for download, with their media types.
pub const DOWNLOADS: &[(&str, &str)] = &[
    (file::VOLUME, "application/octet-stream"),
    (file::VOLUME_JSON, "application/json"),
    (file::DEPTH, "application/octet-stream"),
    (file::DEPTH_PNG, "image/png"),
    (file::ALBEDO_PNG, "image/png"),
    (file::RELAY, "application/octet-stream"),
    (file::GAUSSIANS, "application/octet-stream"),
    (file::CAPTURE, "application/x-hdf5"),
    (file::PAIRS, "application/json"),
    (file::EVENTS, "application/x-ndjson"),
    (file::PLAN, "application/toml"),
    (file::RECON, "application/toml"),
    (file::INSTRUMENT, "application/toml"),
    (file::RUN, "application/json"),
];

/// Where a run is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "kebab-case")]
pub enum RunState {
    /// Waiting for the instrument.
    Queued,
    /// Capturing or reconstructing.
    Running,
    /// Stopped at a checkpoint, resumable.
    Paused,
    /// Finished with outputs.
    Completed,
    /// Stopped by the operator; what was captured is kept.
    Aborted,
    /// Stopped by an error; resumable.
    Failed,
}

/// A run state's name as the API, the catalogue and the CLI spell it.
pub fn state_name(s: RunState) -> &'static str {
    match s {
        RunState::Queued => "queued",
        RunState::Running => "running",
        RunState::Paused => "paused",
        RunState::Completed => "completed",
        RunState::Aborted => "aborted",
        RunState::Failed => "failed",
    }
}

/// The names [`parse_state`] takes.
pub const STATE_NAMES: &str = "queued, running, paused, completed, aborted, failed";

/// A run state from its name ([`state_name`]).
pub fn parse_state(s: &str) -> Result<RunState, String> {
    Ok(match s {
        "queued" => RunState::Queued,
        "running" => RunState::Running,
        "paused" => RunState::Paused,
        "completed" => RunState::Completed,
        "aborted" => RunState::Aborted,
        "failed" => RunState::Failed,
        other => return Err(format!("state `{other}`: expected one of {STATE_NAMES}")),
    })
}

/// `run.json`: the run's state and provenance.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct RunInfo {
    /// Run id (the directory name).
    pub id: String,
    /// Plan name.
    pub plan: String,
    /// State.
    pub state: RunState,
    /// Current or last stage.
    pub stage: String,
    /// Where the instrument config was loaded from (scene paths resolve against it).
    pub instrument_path: PathBuf,
    /// Pairs planned (0 until planned).
    pub pairs_total: usize,
    /// Pairs stored.
    pub pairs_done: usize,
    /// Last error, if failed.
    pub error: Option<String>,
    /// Seconds per stage, for the summary.
    pub timings: Vec<(String, f64)>,
    /// When the run was made (Unix seconds); `None` in runs stored before it was kept
    /// (the run catalogue then reads the time from the run id).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub created_unix_s: Option<f64>,
    /// Who submitted it: the name of the API key, or `cli` for `periscope run`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub submitted_by: Option<String>,
    /// The run whose stored plan this one runs again (`POST /runs/{id}/again`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub again_of: Option<String>,
    /// What an imported capture's run reconstructs (`POST /api/v1/imports`); `None`
    /// for a capture run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub import: Option<ImportSource>,
    /// Every change of `state`, oldest first; [`RunInfo::save`] appends one whenever
    /// the state it writes differs from the last one recorded.
    #[serde(default)]
    pub history: Vec<StateChange>,
    /// Seconds an adaptive capture has spent choosing and measuring, over every session
    /// (a resumed capture's time budget, `adaptive.seconds`, counts them all).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub adaptive_seconds: f64,
    /// Why an adaptive capture ended before its pair budget (its stopping rule or its
    /// time budget), once it has: a resumed run does not choose again.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub adaptive_stopped: Option<String>,
    /// Batches an adaptive capture has chosen, over every session (a batch stopped in
    /// its middle included): a resumed capture numbers its next batch on from them
    /// (and seeds its sampling with the number), as one session would.
    #[serde(default, skip_serializing_if = "is_zero_count")]
    pub adaptive_batches: usize,
    /// Who makes the next state change ([`RunInfo::save`] records it and clears it).
    #[serde(skip)]
    pub acting: Option<String>,
}

fn is_zero_count(v: &usize) -> bool {
    *v == 0
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

/// An imported capture: the files uploaded into the run's `import/` directory.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ImportSource {
    /// The capture file's name under `import/`.
    pub capture: String,
    /// Files stored beside it for its reader (an f-k measurement's `tof.mat`).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sidecars: Vec<String>,
    /// Bytes uploaded, all files together.
    pub bytes: u64,
    /// Whether reconstruction settings came with it (`recon.toml`); without, the
    /// defaults derived for the capture are used.
    pub recon: bool,
}

/// Whether `name` is one plain path component (no separator, not `.` or `..`, not
/// hidden, not empty): a file directly inside the folder it is joined to.
fn is_plain_file_name(name: &str) -> bool {
    !name.is_empty()
        && !name.starts_with('.')
        && !name.contains(['/', '\\', '\0'])
        && matches!(
            Path::new(name).components().collect::<Vec<_>>().as_slice(),
            [std::path::Component::Normal(_)]
        )
}

/// One change of a run's state.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StateChange {
    /// When (Unix seconds).
    pub at_unix_s: f64,
    /// The state entered.
    pub state: RunState,
    /// Who caused it (a key's name, `cli`, `worker`), where known.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub by: Option<String>,
}

/// The time now as Unix seconds.
pub fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// A run's tags and free-text note (`annotations.json`), set by operators through the
/// API or `periscope runs tag` / `note`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Annotations {
    /// Tags, sorted, without duplicates.
    #[serde(default)]
    pub tags: Vec<String>,
    /// A free-text note.
    #[serde(default)]
    pub note: String,
}

/// The most tags one run keeps, and the longest tag and note: an annotation is a label,
/// not a place to store data.
pub const MAX_TAGS: usize = 32;
/// See [`MAX_TAGS`].
pub const MAX_TAG_LEN: usize = 64;
/// See [`MAX_TAGS`].
pub const MAX_NOTE_LEN: usize = 4096;

impl Annotations {
    /// Reads a run's annotations (none when the file is missing).
    pub fn load(dir: &Path) -> io::Result<Annotations> {
        let path = dir.join(file::ANNOTATIONS);
        match crate::store::read_text_capped(&path, 1 << 20) {
            Ok(text) => {
                serde_json::from_str(&text).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
            }
            Err(e) if e.kind() == io::ErrorKind::NotFound => Ok(Annotations::default()),
            Err(e) => Err(e),
        }
    }

    /// Loads a run's annotations, changes them with `f`, and writes them back, under
    /// an exclusive lock (`annotations.json.lock`): the daemon and the CLI editing at
    /// once never lose each other's tags.
    pub fn update<E: From<io::Error>>(
        dir: &Path,
        f: impl FnOnce(&mut Annotations) -> Result<(), E>,
    ) -> Result<Annotations, E> {
        let lock = fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(dir.join(format!("{}.lock", file::ANNOTATIONS)))?;
        lock.lock()?;
        let mut a = Annotations::load(dir)?;
        f(&mut a)?;
        a.save(dir)?;
        Ok(a)
    }

    /// Writes them atomically.
    pub fn save(&self, dir: &Path) -> io::Result<()> {
        let text = serde_json::to_string_pretty(self).expect("annotations serialise");
        crate::store::write_atomic(&dir.join(file::ANNOTATIONS), text.as_bytes())
    }

    /// Checks a tag: 1 to [`MAX_TAG_LEN`] characters of letters, digits, `-`, `_`,
    /// `.`, `:` or `/`.
    pub fn check_tag(tag: &str) -> Result<(), String> {
        let ok = !tag.is_empty()
            && tag.chars().count() <= MAX_TAG_LEN
            && tag
                .chars()
                .all(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | '.' | ':' | '/'));
        if ok {
            Ok(())
        } else {
            Err(format!(
                "tag `{tag}`: a tag is 1 to {MAX_TAG_LEN} letters, digits, `-`, `_`, `.`, `:` or `/`"
            ))
        }
    }

    /// Adds and removes tags and replaces the note (when given), refusing what breaks
    /// the limits; the result is sorted and without duplicates.
    pub fn edit(&mut self, add: &[String], remove: &[String], note: Option<&str>) -> Result<(), String> {
        for t in add {
            Annotations::check_tag(t)?;
        }
        let mut tags: std::collections::BTreeSet<String> = self.tags.iter().cloned().collect();
        tags.extend(add.iter().cloned());
        for t in remove {
            tags.remove(t);
        }
        if tags.len() > MAX_TAGS {
            return Err(format!("a run keeps at most {MAX_TAGS} tags; remove some first"));
        }
        if let Some(n) = note {
            if n.chars().count() > MAX_NOTE_LEN {
                return Err(format!("the note is longer than {MAX_NOTE_LEN} characters"));
            }
            self.note = n.to_owned();
        }
        self.tags = tags.into_iter().collect();
        Ok(())
    }
}

impl RunInfo {
    /// Reads `run.json` from a run directory.
    pub fn load(dir: &Path) -> io::Result<RunInfo> {
        let text = crate::store::read_text_capped(&dir.join(file::RUN), MAX_RUN_JSON_BYTES)?;
        let info: RunInfo =
            serde_json::from_str(&text).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))?;
        // An imported capture's files are read from `import/` by these names: each must
        // name a file there (the daemon stores plain names), not a path out of the run
        // (`..`, an absolute path) in a run.json edited or copied in from elsewhere.
        if let Some(source) = &info.import
            && let Some(bad) = std::iter::once(&source.capture)
                .chain(&source.sidecars)
                .find(|n| !is_plain_file_name(n))
        {
            return Err(io::Error::new(
                io::ErrorKind::InvalidData,
                format!(
                    "{}: `import` names `{bad}`, not a plain file name under {}/: the file was edited or \
                     damaged; give the name of the capture file stored there",
                    dir.join(file::RUN).display(),
                    file::IMPORT_DIR
                ),
            ));
        }
        Ok(info)
    }

    /// Writes `run.json` atomically, first recording a state change in `history`
    /// when the state differs from the last one recorded (with [`RunInfo::acting`] as
    /// its cause).
    pub fn save(&mut self, dir: &Path) -> io::Result<()> {
        if self.history.last().map(|c| c.state) != Some(self.state) {
            self.history.push(StateChange {
                at_unix_s: unix_now(),
                state: self.state,
                by: self.acting.take(),
            });
        }
        let text = serde_json::to_string_pretty(self).expect("run info serialises");
        crate::store::write_atomic(&dir.join(file::RUN), text.as_bytes())
    }
}

/// A fresh run id: plan name and UTC time, made unique within `root`.
pub fn new_run_dir(root: &Path, plan: &str) -> io::Result<PathBuf> {
    // The root made durable too: the first run on a fresh machine made `runs/` as
    // well, and a power cut that forgot that entry lost the run with it.
    crate::store::create_dir_durably(root)?;
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let (d, s) = (secs / 86_400, secs % 86_400);
    let (y, m, day) = civil_from_days(d as i64);
    let stamp = format!(
        "{y:04}{m:02}{day:02}-{:02}{:02}{:02}",
        s / 3600,
        s % 3600 / 60,
        s % 60
    );
    let safe: String = plan
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    for n in 0.. {
        let id = if n == 0 {
            format!("{stamp}-{safe}")
        } else {
            format!("{stamp}-{safe}-{n}")
        };
        let dir = root.join(id);
        match fs::create_dir(&dir) {
            Ok(()) => {
                // The new directory's entry is made durable before anything in it
                // is: a log synced inside a directory a power cut forgot is lost.
                periscope_recon::io::sync_directory(root)?;
                return Ok(dir);
            }
            Err(e) if e.kind() == io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(e),
        }
    }
    unreachable!("some suffix is free")
}

/// Days since 1970-01-01 to (year, month, day), proleptic Gregorian (H. Hinnant).
fn civil_from_days(z: i64) -> (i64, u32, u32) {
    let z = z + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = (doy - (153 * mp + 2) / 5 + 1) as u32;
    let m = if mp < 10 { mp + 3 } else { mp - 9 } as u32;
    (yoe + era * 400 + i64::from(m <= 2), m, d)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dates_are_civil() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(20_778), (2026, 11, 21));
    }
}

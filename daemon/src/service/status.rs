//! What the service reports without touching the hardware: the worker's last reading
//! of the devices, a run's relay and pair geometry for the 3-D view, run files for
//! download, and event-stream subscriptions.
use super::*;

impl Service {
    /// How old the worker's idle reading may be before it is unknown.
    fn idle_stale_s(&self) -> f64 {
        2.0 * self.instrument.api.status_interval.as_secs_f64() + 1.0
    }

    /// The instrument's status, without touching the hardware: the worker's last
    /// reading of the devices with its age (it reads them when it starts, after every
    /// run and e-stop, and every `[api] status-interval-s` while idle), and the running
    /// run's stage while one holds the instrument.
    pub fn instrument_status(&self) -> InstrumentStatus {
        let s = self.lock();
        let (reading, devices, error) = match &s.reading {
            Some(r) => {
                let age = ReadingAge {
                    taken_unix_s: r.unix_s,
                    age_s: r.at.elapsed().as_secs_f64(),
                    stale_after_s: self.idle_stale_s(),
                };
                match &r.devices {
                    Ok(d) => (Some(age), Some(d.clone()), None),
                    Err(e) => (Some(age), None, Some(e.clone())),
                }
            }
            None => (None, None, None),
        };
        let run = s.current.as_ref().map(|(id, _)| RunStage {
            id: id.clone(),
            stage: s.live.stage.clone(),
        });
        let import = s.live.import;
        InstrumentStatus {
            name: self.instrument.name.clone(),
            summary: self.instrument.summary(),
            busy: run.is_some() && !import,
            note: run.as_ref().map(|_| {
                if import {
                    "the running run reconstructs an imported capture and holds no device; the devices are read as when idle"
                } else {
                    "the running run holds the devices; their live state is in its event stream"
                }
            }),
            run,
            devices,
            reading,
            error,
            last_safe: s.last_safe.clone(),
        }
    }

    /// The live safety state, from the running run's readings or the idle reading.
    pub fn safety(&self) -> Safety {
        let s = self.lock();
        let idle_stale = self.idle_stale_s();
        let reading = s.reading.as_ref();
        let idle_devices = reading.and_then(|r| r.devices.as_ref().ok());
        let pointer = |p: &str| idle_devices.and_then(|d| d.pointer(p));
        let flag = |p: &str| pointer(p).and_then(serde_json::Value::as_bool);
        let angles = |p: &str| {
            let x = pointer(&format!("{p}/x")).and_then(serde_json::Value::as_f64)?;
            let y = pointer(&format!("{p}/y")).and_then(serde_json::Value::as_f64)?;
            Some([x.to_degrees(), y.to_degrees()])
        };
        let mut out = Safety {
            emission: flag("/laser/emission"),
            interlock_closed: flag("/laser/interlock_closed"),
            diffuser_in: flag("/laser/diffuser_in"),
            laser_deg: angles("/laser_position"),
            spad_deg: angles("/spad_position"),
            signal_rate_hz: None,
            detector_rate_hz: pointer("/tdc_status/rates/detector").and_then(serde_json::Value::as_f64),
            counts_per_pulse: None,
            pair_rate_hz: None,
            source: "idle",
            run: None,
            pair: None,
            age_s: idle_devices.and(reading).map(|r| r.at.elapsed().as_secs_f64()),
            stale_after_s: idle_stale,
            note: None,
            unix_ms: crate::run_dir::unix_now() * 1e3,
        };
        if let Some((id, _)) = &s.current
            && s.live.import
        {
            out.run = Some(id.clone());
            out.note = Some(format!(
                "run {id} reconstructs an imported capture and holds no device; the devices are read as when idle"
            ));
        } else if let Some((id, _)) = &s.current {
            let live = &s.live;
            out.source = "run";
            out.run = Some(id.clone());
            out.stale_after_s = RUN_STALE_S;
            // Until the run reads the laser, nothing is known of it now; nor of the
            // arms and the detector from the idle reading taken before the run.
            out.emission = None;
            out.interlock_closed = None;
            out.diffuser_in = None;
            out.age_s = None;
            out.laser_deg = None;
            out.spad_deg = None;
            out.detector_rate_hz = None;
            if let Some((state, at, unix_s)) = live.laser {
                out.emission = Some(state.emission);
                out.interlock_closed = Some(state.interlock_closed);
                out.diffuser_in = Some(state.diffuser_in);
                // Aged from when the run read it, not from when the event reached the
                // service (its forwarder waits for the service's lock): the older of
                // the two clocks' ages, so a late event is never taken for a fresh one.
                let wall = (crate::run_dir::unix_now() - unix_s).max(0.0);
                out.age_s = Some(at.elapsed().as_secs_f64().max(wall));
            }
            if let Some(h) = live.histogram {
                out.pair = Some(h.pair);
                if h.at.elapsed().as_secs_f64() < RUN_STALE_S {
                    out.laser_deg = Some(h.laser_deg);
                    out.spad_deg = Some(h.spad_deg);
                    out.signal_rate_hz = Some(h.signal_rate);
                    out.counts_per_pulse =
                        Some(h.signal_rate / self.instrument.laser.repetition_rate.max(1.0));
                }
            }
            if live.stage == "capture"
                && let Some((t0, done0)) = live.capture_started
            {
                out.pair_rate_hz =
                    Some(live.pairs_done.saturating_sub(done0) as f64 / t0.elapsed().as_secs_f64().max(1e-3));
            }
            if !matches!(live.stage.as_str(), "los-scan" | "capture") {
                out.note = Some(format!(
                    "run {id} holds the devices during {} and reads the laser only while it measures",
                    live.stage
                ));
            }
        }
        out
    }

    /// Reads the devices (worker thread only: it owns the instrument between runs).
    pub(super) fn take_reading(&self) {
        let held = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let devices = crate::devices::Devices::open(self.backend.as_ref(), &|| false)
            .and_then(|mut d| d.report())
            .map(|r| serde_json::to_value(r).unwrap_or_default())
            .map_err(|e| e.to_string());
        // The devices are closed: let them go before the service's lock is waited for,
        // which a request writing files may hold (an idle e-stop, which takes them
        // first, waited for those writes).
        drop(held);
        let unix_s = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64());
        self.lock().reading = Some(Reading {
            at: Instant::now(),
            unix_s,
            devices,
        });
    }

    /// A run file for download. `instrument.toml` is served with its secrets cut out
    /// (runs stored before they were cut out at the source included); `capture.hdf5`
    /// of a run that has not finished is exported from what is stored so far, once per
    /// stored pair count, into a cache file beside the run; the rest stream from disk.
    pub fn download(&self, id: &str, name: &str) -> Result<Download, ServiceError> {
        let dir = self.dir(id)?;
        let missing = |_| {
            ServiceError::Conflict(format!(
                "run {id} has no {name} (yet): outputs appear when the run completes"
            ))
        };
        let path = dir.join(name);
        if name == file::INSTRUMENT {
            let text = crate::store::read_text_capped(&path, 1 << 20).map_err(missing)?;
            return Ok(Download::Bytes(crate::config::redact_secrets(&text).into_bytes()));
        }
        if !path.is_file() && name == crate::ytal::CAPTURE_FILE {
            if self.info(id)?.import.is_some() {
                return Err(ServiceError::Conflict(format!(
                    "run {id} has no {name} yet: an imported capture is written as y-tal HDF5 when it has been reconstructed"
                )));
            }
            return self.export_capture(id, &dir);
        }
        // A regular file only (a FIFO or device planted there would hang or never end).
        match std::fs::metadata(&path) {
            Ok(m) if m.is_file() => Ok(Download::Path(path)),
            Ok(_) => Err(ServiceError::Conflict(format!(
                "run {id}'s {name} is not a regular file"
            ))),
            Err(e) => Err(missing(e)),
        }
    }

    pub(super) fn export_capture(&self, id: &str, dir: &Path) -> Result<Download, ServiceError> {
        // One export at a time, and a request that finds one under way is answered at
        // once: waiting for it would hold a thread of the blocking pool past the
        // request's own timeout, and enough of them would starve every other request.
        let _one = match self.exporting.try_lock() {
            Ok(guard) => guard,
            Err(std::sync::TryLockError::Poisoned(p)) => p.into_inner(),
            Err(std::sync::TryLockError::WouldBlock) => {
                return Err(ServiceError::Busy(format!(
                    "run {id}: a capture export is being written; retry in a few seconds"
                )));
            }
        };
        let info = RunInfo::load(dir).ok();
        let done = info.as_ref().map_or(0, |i| i.pairs_done);
        let records = std::fs::metadata(dir.join(crate::store::HISTOGRAM_LOG)).map_or(0, |m| m.len());
        let cache = dir.join(file::EXPORT_CACHE);
        let stamp = dir.join(format!("{}.stamp", file::EXPORT_CACHE));
        let key = format!("{done} {records}");
        let fresh = std::fs::read_to_string(&stamp).is_ok_and(|k| k == key) && cache.is_file();
        // A running capture changes with every pair: an export made in the last
        // EXPORT_REFRESH is served as it is, so no client can keep the disk and a core
        // busy re-exporting while the instrument measures.
        let recent = info.as_ref().is_some_and(|i| i.state == RunState::Running)
            && std::fs::metadata(&cache)
                .and_then(|m| m.modified())
                .is_ok_and(|t| t.elapsed().is_ok_and(|age| age < EXPORT_REFRESH));
        if !fresh && !recent {
            if let Some(available) = periscope_recon::io::memory_available()
                && let Err(why) = export_fits(records, available)
            {
                return Err(ServiceError::Busy(format!(
                    "run {id}: {why}; take it with `periscope export {}` (a process of its own), after the run \
                     if it is capturing",
                    dir.display()
                )));
            }
            let not_yet = |e: &dyn std::fmt::Display| {
                ServiceError::Conflict(format!("run {id} has no capture to export yet: {e}"))
            };
            let capture = crate::capture::RunCapture::load(dir)
                .map_err(|e| not_yet(&e))?
                .to_ytal()
                .map_err(|e| not_yet(&e))?;
            capture.write(&cache).map_err(|source| ServiceError::Export {
                id: id.to_owned(),
                source,
            })?;
            write_atomic(&stamp, key.as_bytes()).map_err(ServiceError::storage(&stamp))?;
        }
        Ok(Download::Path(cache))
    }

    /// A run's geometry for 3-D views: the relay points the LOS scan kept, the planned
    /// illumination and detection points (each thinned to at most [`GEOMETRY_POINTS`]),
    /// the reconstruction volume and the instrument's viewpoint, in metres. Parts the
    /// run has not made yet are empty.
    pub fn geometry(&self, id: &str) -> Result<Geometry, ServiceError> {
        let dir = self.dir(id)?;
        if self.info(id)?.import.is_some() {
            return import_geometry(&dir);
        }
        // The pair list and the relay are written once each, when the run plans and
        // scans: while their stamps hold, the geometry made from them holds too.
        let stamp =
            [file::PAIRS, file::RELAY, file::PLAN, file::INSTRUMENT].map(|f| file_stamp(&dir.join(f)));
        if let Some(g) = self
            .geometries
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(id, &stamp)
        {
            return Ok(g);
        }
        let g = run_geometry(&dir)?;
        self.geometries
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .put(id, stamp, g.clone());
        Ok(g)
    }

    /// Subscribes to a run's events: a running run's, or a queued or paused one's from
    /// when it (re)starts. `None` when the run has finished (its past events are in
    /// `events.jsonl`). The stream ends when the run stops.
    pub fn subscribe(&self, id: &str) -> Result<Option<broadcast::Receiver<StreamEvent>>, ServiceError> {
        self.dir(id)?;
        let mut s = self.lock();
        let waiting = s.current.as_ref().is_some_and(|(c, _)| c == id) || s.queue.iter().any(|q| q == id);
        if !waiting || s.shutdown {
            return Ok(None);
        }
        Ok(Some(
            s.channels
                .entry(id.to_owned())
                .or_insert_with(|| broadcast::channel(EVENT_BUFFER).0)
                .subscribe(),
        ))
    }
}

/// A planned run's geometry, made from its files (see [`Service::geometry`]).
fn run_geometry(dir: &Path) -> Result<Geometry, ServiceError> {
    let storage = ServiceError::RunFiles;
    let run = RunDir::new(dir);
    let (_, plan, inst) = run.load().map_err(storage)?;
    let relay: Vec<[f64; 3]> = run
        .relay()
        .map_err(storage)?
        .unwrap_or_default()
        .iter()
        .map(|p| p.x.to_array())
        .collect();
    let pairs = run.planned_pairs().map_err(storage)?.unwrap_or_default();
    let unique = |pick: fn(&crate::plan::PlannedPair) -> glam::DVec3| {
        let mut seen = std::collections::HashSet::new();
        let points: Vec<[f64; 3]> = pairs
            .iter()
            .map(pick)
            .filter(|p| seen.insert(p.to_array().map(f64::to_bits)))
            .map(|p| p.to_array())
            .collect();
        thin(points)
    };
    let v = &plan.recon.volume;
    let viewpoint = 0.5 * (inst.laser_arm.pose.origin + inst.spad_arm.pose.origin);
    Ok(Geometry {
        relay: thin(relay),
        illumination: unique(|p| p.xi),
        detection: unique(|p| p.xd),
        pairs: pairs.len(),
        volume: VolumeBox {
            x: v.x,
            y: v.y,
            z: v.z,
        },
        viewpoint: viewpoint.to_array(),
    })
}

/// The geometries [`Service::geometry`] made last, at most [`GEOMETRY_CACHE`] runs'.
#[derive(Default)]
pub(super) struct GeometryCache(std::collections::VecDeque<(String, GeometryStamp, Geometry)>);

/// The modification time and length of each file a run's geometry is made from
/// (`None` for one not written yet).
type GeometryStamp = [Option<(std::time::SystemTime, u64)>; 4];

/// How many runs' geometries are kept: a few runs open in a few browsers.
pub(super) const GEOMETRY_CACHE: usize = 8;

impl GeometryCache {
    fn get(&mut self, id: &str, stamp: &GeometryStamp) -> Option<Geometry> {
        let at = self.0.iter().position(|(i, s, _)| i == id && s == stamp)?;
        let hit = self.0.remove(at)?;
        let g = hit.2.clone();
        self.0.push_front(hit);
        Some(g)
    }

    fn put(&mut self, id: &str, stamp: GeometryStamp, g: Geometry) {
        self.0.retain(|(i, _, _)| i != id);
        self.0.push_front((id.to_owned(), stamp, g));
        self.0.truncate(GEOMETRY_CACHE);
    }
}

fn file_stamp(path: &Path) -> Option<(std::time::SystemTime, u64)> {
    let m = std::fs::metadata(path).ok()?;
    Some((m.modified().ok()?, m.len()))
}

/// An imported capture's geometry, from the `geometry.json` its run wrote when it read
/// the file; empty (no points, a zero volume) until then.
fn import_geometry(dir: &Path) -> Result<Geometry, ServiceError> {
    let path = dir.join(file::GEOMETRY);
    let g = match crate::store::read_text_capped(&path, 64 << 20) {
        Ok(text) => serde_json::from_str::<pipeline::ImportGeometry>(&text).map_err(|e| {
            ServiceError::storage(&path)(std::io::Error::new(std::io::ErrorKind::InvalidData, e))
        })?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => pipeline::ImportGeometry {
            relay: Vec::new(),
            illumination: Vec::new(),
            detection: Vec::new(),
            pairs: 0,
            volume: [[0.0; 2]; 3],
            viewpoint: [0.0; 3],
        },
        Err(e) => return Err(ServiceError::storage(&path)(e)),
    };
    Ok(Geometry {
        relay: thin(g.relay),
        illumination: thin(g.illumination),
        detection: thin(g.detection),
        pairs: g.pairs,
        volume: VolumeBox {
            x: g.volume[0],
            y: g.volume[1],
            z: g.volume[2],
        },
        viewpoint: g.viewpoint,
    })
}

/// How long a running capture's export is served before a download makes it again.
const EXPORT_REFRESH: Duration = Duration::from_secs(10);

/// Bytes an export holds at once for a byte of the histogram log: the records read
/// whole (counts as `u32`), the capture's `f32` transients, and the HDF5 writer's copy
/// of them, with room for its headers.
const EXPORT_BYTES_PER_LOG_BYTE: u64 = 4;

/// Whether the daemon can make an export of a log of `log_bytes` with `available`
/// bytes free, leaving half of them to the capture and the requests: the export is
/// made in the daemon's own memory, and one past it would have the process killed
/// (the capture with it) for a download an observer asked for.
fn export_fits(log_bytes: u64, available: u64) -> Result<(), String> {
    let need = log_bytes.saturating_mul(EXPORT_BYTES_PER_LOG_BYTE);
    if need <= available / 2 {
        return Ok(());
    }
    let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
    Err(format!(
        "the export would need about {:.1} GiB, more than half the {:.1} GiB this daemon has free",
        gib(need),
        gib(available)
    ))
}

/// The most points of each kind [`Service::geometry`] returns.
pub const GEOMETRY_POINTS: usize = 20_000;

/// Every k-th point, so at most [`GEOMETRY_POINTS`] remain, rounded to 0.1 mm.
pub(super) fn thin(points: Vec<[f64; 3]>) -> Vec<[f64; 3]> {
    let step = points.len().div_ceil(GEOMETRY_POINTS).max(1);
    points
        .into_iter()
        .step_by(step)
        .map(|p| p.map(|c| (c * 1e4).round() / 1e4))
        .collect()
}

/// The live safety state (`GET /api/v1/instrument/events`, event `safety`): the
/// laser, interlock and diffuser, the arms and the count rates, from the freshest
/// source there is: the running run's own readings (it reads the laser at every pair
/// and after each switch), else the worker's idle reading. `stale_after_s` is the age
/// past which a client must show the state as UNKNOWN.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct Safety {
    /// Laser emitting; `None` when never read.
    pub emission: Option<bool>,
    /// Interlock loop closed.
    pub interlock_closed: Option<bool>,
    /// LOS diffuser in the beam.
    pub diffuser_in: Option<bool>,
    /// Laser arm's optical angles, degrees.
    pub laser_deg: Option<[f64; 2]>,
    /// SPAD arm's optical angles, degrees.
    pub spad_deg: Option<[f64; 2]>,
    /// Signal counts per second of the run's latest histogram (while capturing).
    pub signal_rate_hz: Option<f64>,
    /// Detector input rate of the idle reading (dark counts and ambient light while the
    /// laser is off).
    pub detector_rate_hz: Option<f64>,
    /// Signal counts per laser pulse (pile-up stays negligible below about 0.05).
    pub counts_per_pulse: Option<f64>,
    /// Pairs per second of the running capture.
    pub pair_rate_hz: Option<f64>,
    /// `run` (the running run's readings) or `idle` (the worker's reading).
    pub source: &'static str,
    /// The running run, if any.
    pub run: Option<String>,
    /// The run's latest histogram's pair index.
    pub pair: Option<usize>,
    /// Age of the laser reading, seconds (`None`: never read).
    pub age_s: Option<f64>,
    /// Past this age the reading says nothing about now: clients show UNKNOWN.
    pub stale_after_s: f64,
    /// Why the reading may be old (a run reconstructing holds the devices).
    pub note: Option<String>,
    /// When this snapshot was taken, milliseconds since the Unix epoch.
    pub unix_ms: f64,
}

/// While a run holds the devices, a laser reading older than this is stale: the run
/// reads the laser at every pair, many times a second.
pub const RUN_STALE_S: f64 = 3.0;

/// What `GET /api/v1/instrument` reports: the worker's last reading of the devices,
/// never a fresh one.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct InstrumentStatus {
    /// The instrument config's name.
    pub name: String,
    /// One line on the instrument config.
    pub summary: String,
    /// Whether a run holds the instrument.
    pub busy: bool,
    /// The run holding the instrument, and its stage.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub run: Option<RunStage>,
    /// Where to look for the devices' live state while a run holds them.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<&'static str>,
    /// The last reading of the devices, as `periscope devices --json` prints it
    /// (`null` until one succeeded).
    #[schema(value_type = Option<Object>)]
    pub devices: Option<serde_json::Value>,
    /// When that reading was taken (`null`: none yet).
    pub reading: Option<ReadingAge>,
    /// Why the last reading failed, if it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// The last time the instrument was made safe, and by what.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_safe: Option<String>,
}

/// A run and its stage.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct RunStage {
    /// Run id.
    pub id: String,
    /// Its current stage.
    pub stage: String,
}

/// When a device reading was taken.
#[derive(Clone, Copy, Debug, Serialize, ToSchema)]
pub struct ReadingAge {
    /// Unix time of the reading, seconds.
    pub taken_unix_s: f64,
    /// Its age, seconds.
    pub age_s: f64,
    /// The age past which a client must show what it read as unknown (two of the
    /// worker's reading intervals and a second).
    pub stale_after_s: f64,
}

/// A run's geometry for 3-D views, metres, world frame.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct Geometry {
    /// Relay points of the LOS scan (thinned).
    pub relay: Vec<[f64; 3]>,
    /// Planned illumination points, each once (thinned).
    pub illumination: Vec<[f64; 3]>,
    /// Planned detection points, each once (thinned).
    pub detection: Vec<[f64; 3]>,
    /// Planned pairs.
    pub pairs: usize,
    /// The reconstruction volume.
    pub volume: VolumeBox,
    /// Midway between the two galvo pairs.
    pub viewpoint: [f64; 3],
}

/// An axis-aligned box, metres.
#[derive(Clone, Copy, Debug, Serialize, ToSchema)]
pub struct VolumeBox {
    /// x range.
    pub x: [f64; 2],
    /// y range.
    pub y: [f64; 2],
    /// z range.
    pub z: [f64; 2],
}

#[cfg(test)]
mod tests {
    /// An export needs about four times its log and may take half of what is free: a
    /// 1 GiB log with 16 GiB free is made, with 6 GiB free it is refused, naming both
    /// sizes. Until 2026-12-06 any export was made, whatever it needed.
    #[test]
    fn an_export_is_made_only_where_half_the_free_memory_holds_it() {
        const GIB: u64 = 1 << 30;
        assert!(super::export_fits(GIB, 16 * GIB).is_ok());
        let why = super::export_fits(GIB, 6 * GIB).unwrap_err();
        assert!(why.contains("4.0 GiB") && why.contains("6.0 GiB"), "{why}");
        assert!(super::export_fits(u64::MAX, u64::MAX).is_err());
        assert!(super::export_fits(0, 0).is_ok());
    }
}

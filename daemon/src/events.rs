//! The run's typed progress events: written to `events.jsonl` in the run directory,
//! shown by the CLI's progress bars, and (with the HTTP API) streamed to clients. One
//! enum for all of them, so they cannot drift apart.
use std::fs::{File, OpenOptions};
use std::io::Write;
use std::path::Path;
use std::sync::{Arc, Mutex};

use periscope_recon::gtr::TrainEvent;
use serde::Serialize;

/// A pipeline stage.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Stage {
    /// Opening and identifying the devices.
    Opening,
    /// Reading an imported capture file (`POST /api/v1/imports`) into transients.
    Reading,
    /// LOS first-bounce scan of the relay.
    LosScan,
    /// Relay point cloud, thresholds and normals.
    Relay,
    /// Pair planning.
    Planning,
    /// NLOS acquisition (the optimiser runs alongside).
    Capture,
    /// Fit completion, synthesis and solver.
    Reconstruction,
    /// Writing volumes and images.
    Outputs,
}

impl Stage {
    /// The stage's name as written in `run.json` and events.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Opening => "opening",
            Stage::Reading => "reading",
            Stage::LosScan => "los-scan",
            Stage::Relay => "relay",
            Stage::Planning => "planning",
            Stage::Capture => "capture",
            Stage::Reconstruction => "reconstruction",
            Stage::Outputs => "outputs",
        }
    }
}

/// Something that happened in a run.
#[derive(Clone, Debug, Serialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum RunEvent {
    /// A stage started.
    StageStarted {
        /// Which.
        stage: Stage,
    },
    /// A stage finished.
    StageFinished {
        /// Which.
        stage: Stage,
        /// Seconds it took.
        seconds: f64,
    },
    /// A suspender tripped: the laser is off and the run waits (or pauses) until the
    /// condition clears.
    Suspended {
        /// What tripped and what was measured.
        reason: String,
        /// `auto` (the run goes on by itself once the condition has cleared) or
        /// `operator` (the run pauses; resume it).
        resume: String,
    },
    /// A suspender's condition cleared and the run goes on.
    SuspendCleared {
        /// What had tripped.
        reason: String,
    },
    /// LOS scan progress.
    LosPoint {
        /// Points scanned.
        done: usize,
        /// Points in the scan.
        total: usize,
    },
    /// The relay was extracted.
    Relay {
        /// LOS points with a return.
        returns: usize,
        /// Points kept after thresholds and outlier removal, with normals.
        kept: usize,
    },
    /// Pairs were planned.
    Planned {
        /// Pairs to measure.
        pairs: usize,
        /// Pairs left out (outside the galvo limits).
        unreachable: usize,
        /// Pairs the plan's layout asks for at most (its grid's cells, its count): more
        /// than `pairs` plus `unreachable` where the relay the LOS scan found has no
        /// point in some of the grid's cells.
        requested: usize,
    },
    /// A pair was measured and stored.
    Pair {
        /// Pairs stored.
        done: usize,
        /// Pairs planned.
        total: usize,
        /// Photon counts in its histogram.
        counts: u64,
        /// Peak bin of its histogram.
        peak_bin: usize,
        /// Whether a flag (overflow, saturation) was set.
        flagged: bool,
    },
    /// A pair's histogram, for live displays (streamed to clients, not written to
    /// `events.jsonl`: the data itself is in `histograms.bin`).
    Histogram {
        /// Index of the pair in `pairs.json`.
        pair: usize,
        /// Illumination point on the relay, metres.
        illumination: [f64; 3],
        /// Detection point on the relay, metres.
        detection: [f64; 3],
        /// Laser arm's optical angles for the pair, degrees (x, y).
        laser_deg: [f64; 2],
        /// SPAD arm's optical angles for the pair, degrees (x, y).
        spad_deg: [f64; 2],
        /// Acquisition time summed into the histogram, microseconds.
        dwell_us: u64,
        /// The histogram, summed down to at most [`HISTOGRAM_DISPLAY_BINS`] bins: bin `i` sums the
        /// measured bins `i·group ..(i+1)·group`.
        bins: Vec<u32>,
        /// Measured bins per bin of `bins`.
        group: usize,
        /// Width of a measured bin, picoseconds.
        bin_width_ps: f64,
        /// Time of the first bin after the laser pulse, picoseconds.
        offset_ps: f64,
        /// When the histogram was stored, milliseconds since the Unix epoch (for
        /// event-to-screen latency).
        unix_ms: f64,
    },
    /// The laser's state as the run last read it from the controller (at every pair's
    /// interlock check, and after each switch on or off), for the live safety bar;
    /// streamed, not written to `events.jsonl`.
    Safety {
        /// Emission on.
        emission: bool,
        /// Interlock loop closed.
        interlock_closed: bool,
        /// LOS diffuser in the beam.
        diffuser_in: bool,
        /// When it was read, milliseconds since the Unix epoch.
        unix_ms: f64,
    },
    /// Optimiser progress.
    Train(TrainEvent),
    /// An adaptive capture (or its replay) chose its next batch of pairs.
    PairsChosen(crate::adaptive::BatchChoice),
    /// An output was written.
    Output {
        /// File name in the run directory.
        name: String,
    },
    /// A device error stopped the run (it can be resumed).
    Failed {
        /// The error.
        message: String,
    },
    /// The run finished.
    Completed,
}

/// At most this many bins of a histogram go into a [`RunEvent::Histogram`].
pub const HISTOGRAM_DISPLAY_BINS: usize = 512;

impl RunEvent {
    /// Events for live displays only: streamed, never written to `events.jsonl`.
    pub fn display_only(&self) -> bool {
        matches!(
            self,
            RunEvent::Histogram { .. }
                | RunEvent::Safety { .. }
                | RunEvent::Train(TrainEvent::Snapshot { .. })
        )
    }

    /// A pair's histogram as a [`RunEvent::Histogram`], summed down to at most
    /// [`HISTOGRAM_DISPLAY_BINS`] bins.
    pub fn histogram(
        index: usize,
        pair: &crate::plan::PlannedPair,
        counts: &[u32],
        dwell_us: u64,
        bin_width_s: f64,
        offset_s: f64,
    ) -> RunEvent {
        let group = counts.len().div_ceil(HISTOGRAM_DISPLAY_BINS).max(1);
        let bins = counts
            .chunks(group)
            .map(|c| c.iter().fold(0u32, |a, &v| a.saturating_add(v)))
            .collect();
        let unix_ms = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0.0, |d| d.as_secs_f64() * 1e3);
        let deg = |a: periscope_drivers::OpticalAngles| [a.x.to_degrees(), a.y.to_degrees()];
        RunEvent::Histogram {
            pair: index,
            illumination: pair.xi.to_array(),
            detection: pair.xd.to_array(),
            laser_deg: deg(pair.laser),
            spad_deg: deg(pair.spad),
            dwell_us,
            bins,
            group,
            bin_width_ps: bin_width_s * 1e12,
            offset_ps: offset_s * 1e12,
            unix_ms,
        }
    }
}

/// Where events go: the run's `events.jsonl` and any number of listeners.
#[derive(Clone)]
pub struct EventSink {
    inner: Arc<Mutex<Inner>>,
}

type Listener = Box<dyn FnMut(&RunEvent) + Send>;

struct Inner {
    file: Option<File>,
    /// The file may end in a partial line (a process killed, or a disk that filled,
    /// mid-write): the next line starts on a line of its own, so the log stays one
    /// JSON object a line.
    torn: bool,
    listeners: Vec<Listener>,
}

/// Whether `file` is not empty and its last byte is not a newline.
fn ends_mid_line(file: &File) -> std::io::Result<bool> {
    use std::io::{Read, Seek, SeekFrom};
    let len = file.metadata()?.len();
    if len == 0 {
        return Ok(false);
    }
    let mut f = file;
    f.seek(SeekFrom::Start(len - 1))?;
    let mut last = [0u8];
    f.read_exact(&mut last)?;
    Ok(last[0] != b'\n')
}

impl EventSink {
    /// Appends to `dir/events.jsonl`.
    pub fn open(dir: &Path) -> std::io::Result<EventSink> {
        // Read as well, for its last byte (writes still go to its end).
        let file = OpenOptions::new()
            .create(true)
            .read(true)
            .append(true)
            .open(dir.join(crate::run_dir::file::EVENTS))?;
        let torn = ends_mid_line(&file)?;
        Ok(EventSink {
            inner: Arc::new(Mutex::new(Inner {
                file: Some(file),
                torn,
                listeners: Vec::new(),
            })),
        })
    }

    /// Adds a listener (the CLI progress display, the HTTP event stream).
    pub fn listen(&self, f: impl FnMut(&RunEvent) + Send + 'static) {
        self.lock().listeners.push(Box::new(f));
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Records an event.
    pub fn emit(&self, event: RunEvent) {
        let mut guard = self.lock();
        let Inner {
            file,
            torn,
            listeners,
        } = &mut *guard;
        if let Some(f) = file.as_mut().filter(|_| !event.display_only()) {
            let t = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            let mut line = serde_json::json!({ "time": t });
            if let (Some(obj), Ok(serde_json::Value::Object(ev))) =
                (line.as_object_mut(), serde_json::to_value(&event))
            {
                obj.extend(ev);
            }
            // One write a line, so a line is whole on the disk or cut at its end, never
            // interleaved; after a cut one, a newline first.
            let text = format!("{}{line}\n", if *torn { "\n" } else { "" });
            // Events are a log, not data: a full disk must not stop the capture.
            *torn = f.write_all(text.as_bytes()).is_err();
        }
        for l in listeners.iter_mut() {
            l(&event);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A log whose last line was cut (a process killed mid-write) gets its next event
    /// on a line of its own: until 2026-12-06 the two ran together into one line that
    /// no JSON-lines reader takes.
    #[test]
    fn an_event_after_a_cut_line_starts_a_line_of_its_own() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(crate::run_dir::file::EVENTS);
        std::fs::write(
            &path,
            "{\"time\":1.0,\"event\":\"stage-started\"}\n{\"time\":2.0,\"ev",
        )
        .unwrap();
        let sink = EventSink::open(dir.path()).unwrap();
        sink.emit(RunEvent::StageStarted {
            stage: Stage::Opening,
        });
        sink.emit(RunEvent::StageStarted {
            stage: Stage::Reading,
        });
        let text = std::fs::read_to_string(&path).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), 4, "{text}");
        assert_eq!(lines[1], "{\"time\":2.0,\"ev");
        for l in [lines[0], lines[2], lines[3]] {
            serde_json::from_str::<serde_json::Value>(l).unwrap_or_else(|e| panic!("{l}: {e}"));
        }
        assert!(text.ends_with('\n'));
        // A whole log gains no empty line.
        drop(sink);
        let sink = EventSink::open(dir.path()).unwrap();
        sink.emit(RunEvent::StageStarted {
            stage: Stage::Opening,
        });
        let again = std::fs::read_to_string(&path).unwrap();
        assert_eq!(again.lines().count(), 5);
        assert!(!again.contains("\n\n"), "{again}");
    }

    #[test]
    fn histograms_are_summed_for_the_wire_and_kept_out_of_the_log() {
        let counts: Vec<u32> = (0..1300).map(|i| i % 7).collect();
        let pair = crate::plan::PlannedPair {
            xi: glam::DVec3::X,
            ni: glam::DVec3::Z,
            xd: glam::DVec3::Y,
            nd: glam::DVec3::Z,
            laser: periscope_drivers::OpticalAngles { x: 0.1, y: -0.2 },
            spad: periscope_drivers::OpticalAngles { x: 0.0, y: 0.05 },
        };
        let e = RunEvent::histogram(3, &pair, &counts, 20_000, 16e-12, 2e-9);
        let RunEvent::Histogram {
            bins,
            group,
            bin_width_ps,
            offset_ps,
            laser_deg,
            dwell_us,
            ..
        } = &e
        else {
            panic!("{e:?}")
        };
        // 1300 bins → groups of 3 → 434 bins, the last holding the one left over.
        assert_eq!((*group, bins.len()), (3, 434));
        assert_eq!(
            bins.iter().map(|&b| u64::from(b)).sum::<u64>(),
            counts.iter().map(|&c| u64::from(c)).sum::<u64>()
        );
        assert_eq!(bins[0], 1 + 2);
        assert_eq!(bins[433], counts[1299]);
        assert!((bin_width_ps - 16.0).abs() < 1e-9 && (offset_ps - 2000.0).abs() < 1e-9);
        assert!((laser_deg[0] - 0.1f64.to_degrees()).abs() < 1e-12 && *dwell_us == 20_000);
        // Short histograms go as they are.
        let RunEvent::Histogram { bins, group, .. } = RunEvent::histogram(0, &pair, &[5, 6], 1, 1e-12, 0.0)
        else {
            unreachable!()
        };
        assert_eq!((group, bins), (1, vec![5, 6]));

        let dir = tempfile::tempdir().unwrap();
        let sink = EventSink::open(dir.path()).unwrap();
        let seen = Arc::new(Mutex::new(Vec::new()));
        let s = Arc::clone(&seen);
        sink.listen(move |e| s.lock().unwrap().push(e.display_only()));
        sink.emit(e);
        sink.emit(RunEvent::Train(TrainEvent::Snapshot {
            centres: vec![[0.0; 3]],
            weights: vec![1.0],
        }));
        sink.emit(RunEvent::Completed);
        // Listeners (the event stream) get all three; the log only the last.
        assert_eq!(*seen.lock().unwrap(), vec![true, true, false]);
        let log = std::fs::read_to_string(dir.path().join("events.jsonl")).unwrap();
        assert_eq!(log.lines().count(), 1, "{log}");
        assert!(log.contains("\"completed\""), "{log}");
    }
}

//! Imports: a capture file of any public format (`POST /api/v1/imports`) becomes a run
//! that reads and reconstructs it as a queue item, after the runs before it, so it
//! never competes with a capture; its results are a run's like any other.
//!
//! The upload is written to `RUNS_DIR/.imports/<n>/` while it arrives and moved into
//! its run directory only once it is whole and checked, so a dropped connection, a
//! refused file or a crash leaves no run and no half a file behind (the daemon clears
//! what a crash left there when it starts).
use std::sync::atomic::{AtomicU64, Ordering};

use super::*;
use crate::run_dir::ImportSource;

/// Where uploads are written until they are whole, under the runs directory.
pub const STAGING_DIR: &str = ".imports";

/// Longest name kept for an uploaded file.
pub const MAX_FILE_NAME: usize = 128;

/// A place in the queue held for an import while its files upload, and the directory
/// they are written to. Dropping it (a refused or broken upload) gives the place back
/// and deletes what was written.
pub struct ImportTicket {
    service: Arc<Service>,
    staging: PathBuf,
    admitted: bool,
    /// The e-stops' count when the place was reserved ([`Service::queue_admitted`]).
    seen: u64,
}

impl ImportTicket {
    /// The directory the upload's files are written to (its `import/`).
    pub fn files_dir(&self) -> PathBuf {
        self.staging.join(file::IMPORT_DIR)
    }

    /// Gives the place back and deletes what was written, before returning (blocking:
    /// call it off the async runtime). A ticket merely dropped does the same in the
    /// background.
    pub fn discard(mut self) {
        if !self.admitted {
            self.service.lock().admitting -= 1;
            self.admitted = true;
        }
        remove_staging(&std::mem::take(&mut self.staging));
    }
}

fn remove_staging(staging: &Path) {
    if staging.as_os_str().is_empty() {
        return;
    }
    if let Err(e) = std::fs::remove_dir_all(staging)
        && e.kind() != std::io::ErrorKind::NotFound
    {
        tracing::warn!("could not remove the upload directory {}: {e}", staging.display());
    }
}

impl Drop for ImportTicket {
    fn drop(&mut self) {
        let staging = std::mem::take(&mut self.staging);
        if self.admitted && staging.as_os_str().is_empty() {
            return;
        }
        // The place in the queue is given back under the service's lock, which resume,
        // abort and the e-stop hold across file syncs: with the removal, off the async
        // runtime when the ticket is dropped on it (a broken or cancelled upload).
        let service = (!self.admitted).then(|| Arc::clone(&self.service));
        let remove = move || {
            if let Some(service) = service {
                service.lock().admitting -= 1;
            }
            remove_staging(&staging);
        };
        match tokio::runtime::Handle::try_current() {
            Ok(rt) => {
                rt.spawn_blocking(remove);
            }
            Err(_) => remove(),
        }
    }
}

/// What an upload delivered: its files (under the ticket's `files_dir`) and fields.
#[derive(Clone, Debug, Default)]
pub struct Upload {
    /// The run's name (`name` field), else the capture file's stem.
    pub name: Option<String>,
    /// The capture file's name.
    pub capture: Option<String>,
    /// Files for the reader beside it.
    pub sidecars: Vec<String>,
    /// Bytes of all the files.
    pub bytes: u64,
    /// Reconstruction settings (`recon` field: a RECON.toml).
    pub recon: Option<String>,
}

/// Checks an uploaded file's name and returns it as stored: a plain file name of
/// letters, digits, `.`, `_` and `-` (other characters become `_`), not hidden, at
/// most [`MAX_FILE_NAME`] characters. Paths are cut to their last component, so no
/// name reaches outside the upload's directory.
pub fn stored_name(given: &str) -> Result<String, String> {
    let base = given.rsplit(['/', '\\']).next().unwrap_or_default();
    let name: String = base
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-') {
                c
            } else {
                '_'
            }
        })
        .collect();
    if name.is_empty() || name.starts_with('.') || name.chars().count() > MAX_FILE_NAME {
        return Err(format!(
            "file name `{given}`: give a plain file name of 1 to {MAX_FILE_NAME} characters, not starting with `.`"
        ));
    }
    Ok(name)
}

impl Service {
    /// Holds a place in the queue for an import about to upload, as a submission
    /// does (429 when the queue is full, 423 when it is locked without `lock_key`),
    /// and makes the directory its files are written to.
    pub fn begin_import(self: &Arc<Self>, lock_key: Option<&str>) -> Result<ImportTicket, ServiceError> {
        static NEXT: AtomicU64 = AtomicU64::new(0);
        self.check_lock(lock_key)?;
        let seen = self.reserve_place()?;
        let staging = self.runs_dir.join(STAGING_DIR).join(format!(
            "{}-{}",
            std::process::id(),
            NEXT.fetch_add(1, Ordering::Relaxed)
        ));
        let ticket = ImportTicket {
            seen,
            service: Arc::clone(self),
            staging,
            admitted: false,
        };
        let files = ticket.files_dir();
        std::fs::create_dir_all(&files).map_err(ServiceError::storage(&files))?;
        Ok(ticket)
    }

    /// Checks a finished upload and queues it as a run submitted by `by`: the capture
    /// file must be there with a capture's extension and container (HDF5 or MATLAB:
    /// read whole by the run), the settings must parse. Returns the new run's status.
    pub fn admit_import(
        &self,
        ticket: ImportTicket,
        upload: Upload,
        by: &str,
    ) -> Result<RunStatus, ServiceError> {
        let capture = match self.check_import(&ticket, &upload) {
            Ok(c) => c,
            Err(e) => {
                ticket.discard();
                return Err(e);
            }
        };
        self.queue_import(ticket, upload, capture, by)
    }

    /// The upload's capture file name, once its name, container and settings pass.
    fn check_import(&self, ticket: &ImportTicket, upload: &Upload) -> Result<String, ServiceError> {
        let invalid = ServiceError::InvalidImport;
        let capture = upload.capture.clone().ok_or_else(|| {
            invalid(
                "the upload has no `capture` part: send the capture file as the form field `capture`".into(),
            )
        })?;
        let path = ticket.files_dir().join(&capture);
        let is_mat = periscope_recon::io::lct::is_mat_path(&path);
        if !periscope_recon::io::ytal::is_hdf5_path(&path) && !is_mat {
            return Err(invalid(format!(
                "{capture}: not a capture file name: captures are .hdf5 or .h5 (y-tal, ZNLOS) or .mat (Stanford LCT \
                 and f-k, phasor field); see docs/formats.md"
            )));
        }
        let mut head = Vec::with_capacity(4096);
        {
            use std::io::Read as _;
            std::fs::File::open(&path)
                .and_then(|f| f.take(4096).read_to_end(&mut head))
                .map_err(ServiceError::storage(&path))?;
        }
        if !periscope_recon::io::formats::is_capture_container(&head) {
            return Err(invalid(format!(
                "{capture}: neither HDF5 nor a MATLAB file ({} bytes): upload the capture file itself \
                 (docs/formats.md lists the formats read)",
                upload.bytes
            )));
        }
        if let Some(text) = &upload.recon {
            let recon = crate::plan::check_recon(&TomlSource::from_text("the `recon` part", text.clone()))
                .map_err(|e| invalid(e.to_string()))?;
            // Its volume and fit are held in the daemon's memory as a run's are.
            crate::budget::Budget::of_import(&recon)
                .check(&self.instrument.budget)
                .map_err(|over| ServiceError::OverBudget(over.message))?;
        }
        Ok(capture)
    }

    /// Moves a checked upload into a new run directory and queues it.
    fn queue_import(
        &self,
        mut ticket: ImportTicket,
        upload: Upload,
        capture: String,
        by: &str,
    ) -> Result<RunStatus, ServiceError> {
        let name = match &upload.name {
            Some(n) if !n.trim().is_empty() => n.trim().to_owned(),
            _ => Path::new(&capture)
                .file_stem()
                .map_or_else(|| "import".into(), |s| s.to_string_lossy().into_owned()),
        };
        let name: String = name.chars().take(64).collect();
        let dir = crate::run_dir::new_run_dir(&self.runs_dir, &name)
            .map_err(ServiceError::storage(&self.runs_dir))?;
        let made = (|| {
            let to = dir.join(file::IMPORT_DIR);
            std::fs::rename(ticket.files_dir(), &to).map_err(ServiceError::storage(&to))?;
            if let Some(text) = &upload.recon {
                let p = dir.join(file::RECON);
                write_atomic(&p, text.as_bytes()).map_err(ServiceError::storage(&p))?;
            }
            let mut info = RunInfo {
                id: dir
                    .file_name()
                    .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
                plan: name.clone(),
                state: RunState::Queued,
                stage: "queued".into(),
                instrument_path: self.instrument_src.path().to_owned(),
                pairs_total: 0,
                pairs_done: 0,
                error: None,
                timings: Vec::new(),
                created_unix_s: Some(crate::run_dir::unix_now()),
                submitted_by: Some(by.to_owned()),
                again_of: None,
                import: Some(ImportSource {
                    capture: capture.clone(),
                    sidecars: upload.sidecars.clone(),
                    bytes: upload.bytes,
                    recon: upload.recon.is_some(),
                }),
                history: Vec::new(),
                adaptive_seconds: 0.0,
                adaptive_stopped: None,
                adaptive_batches: 0,
                acting: Some(by.to_owned()),
            };
            info.save(&dir)
                .map_err(ServiceError::storage(dir.join(file::RUN)))?;
            Ok::<String, ServiceError>(info.id)
        })();
        let id = match made {
            Ok(id) => id,
            Err(e) => {
                if let Err(rm) = std::fs::remove_dir_all(&dir) {
                    tracing::warn!("could not remove the unfinished import {}: {rm}", dir.display());
                }
                ticket.discard();
                return Err(e);
            }
        };
        let mut s = self.lock();
        s.admitting -= 1;
        ticket.admitted = true;
        // The upload's directory is empty now (its files moved into the run).
        remove_staging(&std::mem::take(&mut ticket.staging));
        self.queue_admitted(&mut s, &id, ticket.seen);
        self.persist_after_change(&s);
        self.wake.notify_all();
        drop(s);
        tracing::info!(run = %id, capture = %capture, bytes = upload.bytes, by, "capture imported and queued");
        self.index_now(&id);
        self.status(&id)
    }

    /// Removes what uploads left in [`STAGING_DIR`] when the daemon stopped during
    /// them (a crash, a kill): none of it was ever a run.
    pub(super) fn clear_staging(runs_dir: &Path) {
        let staging = runs_dir.join(STAGING_DIR);
        match std::fs::remove_dir_all(&staging) {
            Ok(()) => tracing::info!("removed unfinished uploads in {}", staging.display()),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
            Err(e) => tracing::warn!(
                "could not remove unfinished uploads in {}: {e}",
                staging.display()
            ),
        }
    }

    /// Reads and reconstructs an imported capture's run on its own thread while the
    /// calling worker thread keeps reading the devices every `[api]
    /// status-interval-s` (no run holds them, so the safety bar stays live), and
    /// returns once it has stopped.
    pub(super) fn execute_import(
        &self,
        dir: &Path,
        control: Control,
        events: EventSink,
    ) -> Result<(), PipelineError> {
        let (tx, rx) = std::sync::mpsc::channel();
        let (d, c) = (dir.to_owned(), control.clone());
        let thread = std::thread::Builder::new().name("import".into()).spawn(move || {
            let _ = tx.send(pipeline::execute_import(&d, c, events));
        });
        let handle = match thread {
            Ok(h) => h,
            Err(e) => {
                return Err(PipelineError::storage(
                    dir,
                    std::io::Error::other(format!("no thread for the import: {e}")),
                ));
            }
        };
        let interval = self.instrument.api.status_interval;
        let result = loop {
            // At once, then every interval: a run before the import left no reading
            // (what it left the instrument in is unknown until read).
            self.take_reading();
            match rx.recv_timeout(interval) {
                Ok(r) => break r,
                Err(std::sync::mpsc::RecvTimeoutError::Timeout) => continue,
                Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => {
                    break Err(PipelineError::Panicked {
                        stage: "import",
                        message: "the import thread ended without a result".into(),
                    });
                }
            }
        };
        let _ = handle.join();
        result
    }
}

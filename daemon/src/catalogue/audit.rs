//! The audit trail: who did what and when. Each entry is appended to
//! `RUNS_DIR/audit.jsonl` first (one `write` of one line on an `O_APPEND` file, flushed
//! to disk: the record that survives a lost or damaged catalogue, and that the daemon
//! and the CLI append to at once without interleaving), then inserted in the
//! catalogue's `audit` table by its id, so an entry is never there twice.
use std::io::Write as _;
use std::path::Path;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// The audit log's file name in the runs directory.
pub const AUDIT_FILE: &str = "audit.jsonl";

/// The longest detail an entry keeps (a refused plan's reason, say), in bytes.
const MAX_DETAIL: usize = 2048;

/// The longest target an entry keeps, in bytes.
const MAX_TARGET: usize = 256;

/// `s` cut to at most `max` bytes at a character boundary, marked with `…` where cut.
pub(crate) fn cut(mut s: String, max: usize) -> String {
    if s.len() > max {
        let mut at = max;
        while !s.is_char_boundary(at) {
            at -= 1;
        }
        s.truncate(at);
        s.push('…');
    }
    s
}

/// One audited action.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct AuditEntry {
    /// A unique id (random, 128 bits, hex).
    pub id: String,
    /// When (Unix seconds).
    pub at_unix_s: f64,
    /// Who: an API key's name, `loopback` for a request without a key from this
    /// machine, `cli` for the command line, or `unknown` for a failed authentication.
    pub actor: String,
    /// The actor's role (`observer`, `operator`, `admin`, `estop`, or `none`).
    pub role: String,
    /// What: `submit`, `pause`, `resume`, `abort`, `estop`, `again`, `annotate`,
    /// `queue-order`, `queue-move`, `queue-lock`, `queue-unlock`, `key-create`,
    /// `key-revoke`, `authenticate` (a missing, unknown, expired or revoked key).
    pub action: String,
    /// On what: a run id, a key's name.
    pub target: Option<String>,
    /// `ok`, `refused` (the request was not allowed or not valid) or `failed`.
    pub outcome: String,
    /// Why it was refused or failed, or what it changed.
    pub detail: Option<String>,
    /// The client's address, for API requests.
    pub peer: Option<String>,
}

impl AuditEntry {
    /// A new entry stamped now with a fresh id; the target is cut to 256 bytes (a
    /// refused request's route may be any path a client sends).
    pub fn new(actor: &str, role: &str, action: &str, target: Option<&str>, outcome: &str) -> AuditEntry {
        use rand::RngCore;
        let mut id = [0u8; 16];
        rand::rng().fill_bytes(&mut id);
        AuditEntry {
            id: id.iter().map(|b| format!("{b:02x}")).collect(),
            at_unix_s: crate::run_dir::unix_now(),
            actor: actor.to_owned(),
            role: role.to_owned(),
            action: action.to_owned(),
            target: target.map(|t| cut(t.to_owned(), MAX_TARGET)),
            outcome: outcome.to_owned(),
            detail: None,
            peer: None,
        }
    }

    /// With a detail (cut to 2,048 bytes at a character boundary).
    pub fn detail(mut self, detail: impl Into<String>) -> AuditEntry {
        self.detail = Some(cut(detail.into(), MAX_DETAIL));
        self
    }

    /// With the client's address.
    pub fn peer(mut self, peer: Option<std::net::SocketAddr>) -> AuditEntry {
        self.peer = peer.map(|p| p.to_string());
        self
    }
}

/// Appends `entry` to the audit log in `runs_dir` as one line, written whole with one
/// call on a file opened for appending, and flushed to disk. A log that ends inside a
/// line (a write cut short by a crash) gets a line break first, so the fragment does
/// not take this entry with it.
pub fn append(runs_dir: &Path, entry: &AuditEntry) -> std::io::Result<()> {
    use std::os::unix::fs::FileExt as _;
    let mut line = serde_json::to_string(entry).expect("audit entries serialise");
    line.push('\n');
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .read(true)
        .append(true)
        .open(runs_dir.join(AUDIT_FILE))?;
    let len = f.metadata()?.len();
    let mut last = [b'\n'];
    if len > 0 {
        f.read_exact_at(&mut last, len - 1)?;
    }
    if last[0] != b'\n' {
        line.insert(0, '\n');
    }
    f.write_all(line.as_bytes())?;
    f.sync_data()
}

/// Every entry of the audit log in `runs_dir`, oldest first ([`read_from`] 0).
pub fn read_all(runs_dir: &Path) -> std::io::Result<Vec<AuditEntry>> {
    read_from(runs_dir, 0)
}

/// The entries of the audit log in `runs_dir` from byte `from` on (from the start of
/// the line `from` falls in), oldest first, read a line at a time. Lines that do not
/// parse (a line cut short by a crash, bytes that are not UTF-8) are skipped with a
/// warning.
pub fn read_from(runs_dir: &Path, from: u64) -> std::io::Result<Vec<AuditEntry>> {
    use std::io::{BufRead as _, Seek as _};
    let path = runs_dir.join(AUDIT_FILE);
    let mut file = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(e),
    };
    let len = file.metadata()?.len();
    // Back to the start of the line `from` falls in (entries are a few KiB at most).
    let mut start = 0;
    if from > 0 && from <= len {
        let back = from.min(LINE_SEARCH);
        let mut before = vec![0; back as usize];
        file.seek(std::io::SeekFrom::Start(from - back))?;
        std::io::Read::read_exact(&mut file, &mut before)?;
        start = match before.iter().rposition(|&b| b == b'\n') {
            Some(i) => from - back + i as u64 + 1,
            None if back == from => 0,
            None => from,
        };
    }
    file.seek(std::io::SeekFrom::Start(start))?;
    let mut out = Vec::new();
    for (n, line) in std::io::BufReader::new(file).split(b'\n').enumerate() {
        let line = line?;
        if line.iter().all(u8::is_ascii_whitespace) {
            continue;
        }
        match serde_json::from_slice(&line) {
            Ok(e) => out.push(e),
            Err(e) => tracing::warn!(
                "{}: line {} after byte {start} skipped: {e}",
                path.display(),
                n + 1
            ),
        }
    }
    Ok(out)
}

/// How far back from an offset [`read_from`] looks for the start of its line.
const LINE_SEARCH: u64 = 16 << 10;

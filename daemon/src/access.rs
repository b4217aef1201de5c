//! Who may do what: roles, and the API keys that carry them.
//!
//! | role | may |
//! |---|---|
//! | `estop` | e-stop (a key for a wall panel or a phone) |
//! | `observer` | e-stop, and read everything: runs, files, events, the catalogue, the audit trail, metrics, plan checks |
//! | `operator` | and submit, pause, resume, abort, run again, tag and annotate runs |
//! | `admin` | and reorder and lock the queue, create, list and revoke keys |
//!
//! A request from this machine (loopback) needs no key to read or to e-stop; every
//! change needs a key, from any host. Keys live in `RUNS_DIR/keys.json` (mode 0600) as
//! SHA-256 digests of 256-bit random secrets: the secret is shown once, when the key is
//! made (`periscope keys create`), and never stored. A digest of a random 256-bit
//! secret needs no slow password hash: nothing short of the secret matches it. Keys may
//! expire and may be revoked; the daemon reads the file again whenever it changes, so
//! a revocation holds from the next request. The daemon's single token
//! (`PERISCOPE_TOKEN`, `[api] token`) keeps working as an admin key named `token`.
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use utoipa::ToSchema;

/// The keys file's name in the runs directory.
pub const KEYS_FILE: &str = "keys.json";

/// The name the daemon's single token answers to.
pub const TOKEN_KEY_NAME: &str = "token";

/// What a key may do; each role may do everything the ones before it may.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "kebab-case")]
pub enum Role {
    /// E-stop only.
    Estop,
    /// Read, check plans, e-stop.
    Observer,
    /// And submit, pause, resume, abort, run again, annotate.
    Operator,
    /// And the queue's order and lock, and keys.
    Admin,
}

impl Role {
    /// The names [`Role::parse`] takes.
    pub const NAMES: &'static str = "estop, observer, operator, admin";

    /// A role from its name.
    pub fn parse(s: &str) -> Result<Role, String> {
        Ok(match s {
            "estop" => Role::Estop,
            "observer" => Role::Observer,
            "operator" => Role::Operator,
            "admin" => Role::Admin,
            other => return Err(format!("role `{other}`: expected one of {}", Role::NAMES)),
        })
    }

    /// Its name.
    pub fn name(self) -> &'static str {
        match self {
            Role::Estop => "estop",
            Role::Observer => "observer",
            Role::Operator => "operator",
            Role::Admin => "admin",
        }
    }
}

/// A key as stored: its digest, never its secret.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct KeyRecord {
    /// The key's name, recorded with every action it takes.
    pub name: String,
    /// Its role.
    pub role: Role,
    /// SHA-256 of the secret, hex.
    pub sha256: String,
    /// When it was made (Unix seconds).
    pub created_unix_s: f64,
    /// Who made it.
    pub created_by: String,
    /// When it stops working (Unix seconds), if ever.
    pub expires_unix_s: Option<f64>,
    /// When it was revoked (Unix seconds).
    pub revoked_unix_s: Option<f64>,
}

/// Who a request is from.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Identity {
    /// The key's name (or `loopback` for a request without a key from this machine).
    pub name: String,
    /// What it may do.
    pub role: Role,
}

/// Why a secret was not accepted.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AuthError {
    /// No key has this secret.
    #[error("the key is not known to this daemon")]
    Unknown,
    /// The key has expired.
    #[error("key `{0}` has expired; ask an admin for a new one (periscope keys create)")]
    Expired(String),
    /// The key was revoked.
    #[error("key `{0}` was revoked")]
    Revoked(String),
}

/// Why the keys file could not be changed.
#[derive(Debug, thiserror::Error)]
pub enum KeysError {
    /// Reading, locking or writing it failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// What failed.
        #[source]
        source: std::io::Error,
    },
    /// The request does not fit the keys there (a name taken, no such key, a bad name).
    #[error("{0}")]
    Invalid(String),
}

/// The keys of a runs directory, read again when the file changes.
pub struct KeyStore {
    path: PathBuf,
    token: Option<String>,
    cache: Mutex<(Option<FileStamp>, Vec<KeyRecord>)>,
    /// The read failure last logged (each is logged once, until the file reads).
    reported: Mutex<Option<String>>,
}

/// A file's modification time and length: when either changes, it is read again.
type FileStamp = (std::time::SystemTime, u64);

/// The SHA-256 of `secret`, hex.
pub fn digest(secret: &str) -> String {
    Sha256::digest(secret.as_bytes())
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

fn constant_time_eq(a: &[u8], b: &[u8]) -> bool {
    a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

impl KeyStore {
    /// The keys of `runs_dir`, and the daemon's single token (an admin key named
    /// `token`) if it has one.
    pub fn open(runs_dir: &Path, token: Option<String>) -> KeyStore {
        KeyStore {
            path: runs_dir.join(KEYS_FILE),
            token,
            cache: Mutex::new((None, Vec::new())),
            reported: Mutex::new(None),
        }
    }

    /// Whether any key or token can be accepted at all.
    pub fn any(&self) -> bool {
        self.token.is_some() || !self.keys().is_empty()
    }

    /// The keys as the file holds them, or why they cannot be read (a listing must
    /// not show a damaged file as no keys; [`KeyStore::keys`] accepts none then).
    pub fn read(&self) -> std::io::Result<Vec<KeyRecord>> {
        match read_keys(&self.path) {
            Err(e) if e.kind() != std::io::ErrorKind::NotFound => Err(std::io::Error::new(
                e.kind(),
                format!(
                    "{e}: no API key is accepted while it cannot be read; restore it from a backup, or move \
                     it aside and create the keys again"
                ),
            )),
            other => other,
        }
    }

    /// The keys as the file holds them now (read again if it changed).
    pub fn keys(&self) -> Vec<KeyRecord> {
        let stamp = std::fs::metadata(&self.path)
            .ok()
            .and_then(|m| Some((m.modified().ok()?, m.len())));
        let mut cache = self.cache.lock().unwrap_or_else(|p| p.into_inner());
        if cache.0 != stamp || stamp.is_none() {
            let mut reported = self.reported.lock().unwrap_or_else(|p| p.into_inner());
            match read_keys(&self.path) {
                Ok(keys) => {
                    *cache = (stamp, keys);
                    *reported = None;
                }
                Err(e) => {
                    // A file that cannot be read accepts no key (never the old set,
                    // which may hold a revoked one). A damaged file's failure is kept
                    // for this version of it, so it is read once, not on every
                    // request, until it changes; any other failure (a file the daemon
                    // may not read, no file descriptor left, a slow disk) is tried
                    // again at the next request. Each failure is logged once, the
                    // first included, until the file reads again.
                    let damaged = e.kind() == std::io::ErrorKind::InvalidData;
                    let message = e.to_string();
                    if reported.as_deref() != Some(message.as_str()) {
                        tracing::error!(
                            "{}: {e}; no API key is accepted until it is fixed",
                            self.path.display()
                        );
                        *reported = Some(message);
                    }
                    *cache = (if damaged { stamp } else { None }, Vec::new());
                }
            }
        }
        cache.1.clone()
    }

    /// Whether the daemon has its single token (known without reading any file).
    pub fn has_token(&self) -> bool {
        self.token.is_some()
    }

    /// The token's identity if `secret` is the daemon's token. Reads no file, so the
    /// API answers it on its own threads, never queued behind the blocking pool.
    pub fn token_identity(&self, secret: &str) -> Option<Identity> {
        // Digests against digests: equal lengths, so the comparison's time says
        // nothing of the token's length either.
        let t = self.token.as_ref()?;
        constant_time_eq(digest(secret).as_bytes(), digest(t).as_bytes()).then(|| Identity {
            name: TOKEN_KEY_NAME.into(),
            role: Role::Admin,
        })
    }

    /// Who holds `secret`.
    pub fn authenticate(&self, secret: &str, now_unix_s: f64) -> Result<Identity, AuthError> {
        if let Some(id) = self.token_identity(secret) {
            return Ok(id);
        }
        let d = digest(secret);
        let keys = self.keys();
        let Some(k) = keys
            .iter()
            .find(|k| constant_time_eq(k.sha256.as_bytes(), d.as_bytes()))
        else {
            return Err(AuthError::Unknown);
        };
        if k.revoked_unix_s.is_some() {
            return Err(AuthError::Revoked(k.name.clone()));
        }
        if k.expires_unix_s.is_some_and(|e| now_unix_s >= e) {
            return Err(AuthError::Expired(k.name.clone()));
        }
        Ok(Identity {
            name: k.name.clone(),
            role: k.role,
        })
    }

    /// Makes a key; returns it and its secret (shown once, never stored).
    pub fn create(
        &self,
        name: &str,
        role: Role,
        expires_unix_s: Option<f64>,
        created_by: &str,
    ) -> Result<(KeyRecord, String), KeysError> {
        check_name(name)?;
        let secret = new_secret();
        let now = crate::run_dir::unix_now();
        if expires_unix_s.is_some_and(|e| e <= now) {
            return Err(KeysError::Invalid("the expiry is in the past".into()));
        }
        let record = KeyRecord {
            name: name.to_owned(),
            role,
            sha256: digest(&secret),
            created_unix_s: now,
            created_by: created_by.to_owned(),
            expires_unix_s,
            revoked_unix_s: None,
        };
        self.change(|keys| {
            if keys.iter().any(|k| k.name == name) {
                return Err(KeysError::Invalid(format!(
                    "a key named `{name}` exists (revoked keys keep their names, so the audit trail stays unambiguous); choose another name"
                )));
            }
            keys.push(record.clone());
            Ok(())
        })?;
        Ok((record, secret))
    }

    /// Revokes key `name`.
    pub fn revoke(&self, name: &str) -> Result<KeyRecord, KeysError> {
        let mut out = None;
        self.change(|keys| {
            let Some(k) = keys.iter_mut().find(|k| k.name == name) else {
                return Err(KeysError::Invalid(format!(
                    "no key named `{name}`; list them with `periscope keys list`"
                )));
            };
            if k.revoked_unix_s.is_none() {
                k.revoked_unix_s = Some(crate::run_dir::unix_now());
            }
            out = Some(k.clone());
            Ok(())
        })?;
        Ok(out.expect("set when Ok"))
    }

    /// Changes the keys file under an exclusive lock (the daemon and the CLI may both
    /// change it), writing it whole to a temporary file with mode 0600 and renaming it.
    fn change(&self, f: impl FnOnce(&mut Vec<KeyRecord>) -> Result<(), KeysError>) -> Result<(), KeysError> {
        let io = |path: &Path| {
            let path = path.to_owned();
            move |source| KeysError::Io { path, source }
        };
        let lock_path = self.path.with_extension("lock");
        let lock = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&lock_path)
            .map_err(io(&lock_path))?;
        lock.lock().map_err(io(&lock_path))?;
        let mut keys = read_keys(&self.path).map_err(io(&self.path))?;
        f(&mut keys)?;
        let text = serde_json::to_string_pretty(&keys).expect("keys serialise");
        let tmp = self.path.with_extension("json.tmp");
        let written = (|| {
            use std::io::Write as _;
            use std::os::unix::fs::OpenOptionsExt as _;
            // A temporary left by a failed write keeps its mode: made afresh, 0600.
            let _ = std::fs::remove_file(&tmp);
            let mut file = std::fs::OpenOptions::new()
                .create_new(true)
                .write(true)
                .mode(0o600)
                .open(&tmp)?;
            file.write_all(text.as_bytes())?;
            file.sync_all()?;
            std::fs::rename(&tmp, &self.path)
        })();
        if let Err(e) = written {
            let _ = std::fs::remove_file(&tmp);
            return Err(io(&self.path)(e));
        }
        // The rename is durable once the directory is: a revoked key must not come
        // back after a power cut.
        if let Some(dir) = self.path.parent()
            && let Ok(d) = std::fs::File::open(dir)
        {
            let _ = d.sync_all();
        }
        // The cache is read again at the next request.
        self.cache.lock().unwrap_or_else(|p| p.into_inner()).0 = None;
        Ok(())
    }
}

fn read_keys(path: &Path) -> std::io::Result<Vec<KeyRecord>> {
    match crate::store::read_text_capped(path, 16 << 20) {
        Ok(text) => {
            serde_json::from_str(&text).map_err(|e| std::io::Error::new(std::io::ErrorKind::InvalidData, e))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Vec::new()),
        Err(e) => Err(e),
    }
}

/// A key name: 1 to 64 letters, digits, `-`, `_`, `.` or `@`, not one of the names the
/// daemon gives callers and causes itself (`token`, `loopback`, `open-reads`, `cli`,
/// `local`, `unknown`, `worker`, `estop`, `test`).
fn check_name(name: &str) -> Result<(), KeysError> {
    let ok = !name.is_empty()
        && name.len() <= 64
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.' | '@'));
    if !ok {
        return Err(KeysError::Invalid(format!(
            "key name `{name}`: 1 to 64 letters, digits, `-`, `_`, `.` or `@`"
        )));
    }
    if [
        TOKEN_KEY_NAME,
        "loopback",
        "open-reads",
        "cli",
        "local",
        "unknown",
        "worker",
        "estop",
        "test",
    ]
    .contains(&name)
    {
        return Err(KeysError::Invalid(format!(
            "`{name}` is a name the daemon gives callers itself; choose another"
        )));
    }
    Ok(())
}

/// A new secret: `psk_` and 256 random bits, hex.
fn new_secret() -> String {
    use rand::RngCore;
    let mut bytes = [0u8; 32];
    rand::rng().fill_bytes(&mut bytes);
    let hex: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
    format!("psk_{hex}")
}

/// When a key given `--expires` stops working: a duration from `now` (`90d`, `12h`,
/// `30m`) or an RFC 3339 time or a date (`2027-01-31`, midnight UTC).
pub fn parse_expiry(s: &str, now_unix_s: f64) -> Result<f64, String> {
    let s = s.trim();
    let unit = s.chars().last().unwrap_or(' ');
    let scale = match unit {
        'd' => Some(86_400.0),
        'h' => Some(3600.0),
        'm' => Some(60.0),
        _ => None,
    };
    let at = if let Some(scale) = scale
        && let Ok(n) = s[..s.len() - 1].parse::<f64>()
        && n.is_finite()
        && n > 0.0
    {
        now_unix_s + n * scale
    } else {
        parse_time(s).map_err(|_| {
            format!("`{s}`: give a duration (90d, 12h, 30m) or a time (2027-01-31 or 2027-01-31T12:00:00Z)")
        })?
    };
    // A time the keys file and `keys list` can hold and show: an overflowing duration
    // must not become a key that never expires.
    if at.is_nan() || at > LATEST_EXPIRY_UNIX_S {
        return Err(format!(
            "`{s}` ends after 9999-12-31: leave the expiry out for a key that never expires"
        ));
    }
    if at <= now_unix_s {
        return Err(format!(
            "`{s}` is already past ({}): give a time to come",
            format_time(at)
        ));
    }
    Ok(at)
}

/// 9999-12-31T23:59:59Z: the latest expiry a key may have.
const LATEST_EXPIRY_UNIX_S: f64 = 253_402_300_799.0;

/// Unix seconds of an RFC 3339 time or a date (midnight UTC).
pub fn parse_time(s: &str) -> Result<f64, String> {
    use time::format_description::well_known::Rfc3339;
    if let Ok(t) = time::OffsetDateTime::parse(s, &Rfc3339) {
        return Ok(t.unix_timestamp_nanos() as f64 / 1e9);
    }
    let fmt = time::macros::format_description!("[year]-[month]-[day]");
    time::Date::parse(s, fmt)
        .map(|d| d.midnight().assume_utc().unix_timestamp() as f64)
        .map_err(|_| {
            format!("`{s}`: expected a date (2027-01-31) or an RFC 3339 time (2027-01-31T12:00:00Z)")
        })
}

/// Unix seconds as an RFC 3339 time (UTC, whole seconds).
pub fn format_time(unix_s: f64) -> String {
    use time::format_description::well_known::Rfc3339;
    time::OffsetDateTime::from_unix_timestamp(unix_s.floor() as i64)
        .ok()
        .and_then(|t| t.format(&Rfc3339).ok())
        .unwrap_or_else(|| format!("{unix_s}"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn keys_are_stored_hashed_expire_and_revoke() {
        let dir = tempfile::tempdir().unwrap();
        let store = KeyStore::open(dir.path(), Some("old-token".into()));
        let now = crate::run_dir::unix_now();
        let (rec, secret) = store
            .create("alice", Role::Operator, Some(now + 60.0), "cli")
            .unwrap();
        let text = std::fs::read_to_string(dir.path().join(KEYS_FILE)).unwrap();
        assert!(!text.contains(&secret), "the secret is never stored");
        assert!(text.contains(&rec.sha256));
        use std::os::unix::fs::PermissionsExt as _;
        let mode = std::fs::metadata(dir.path().join(KEYS_FILE))
            .unwrap()
            .permissions()
            .mode();
        assert_eq!(mode & 0o777, 0o600);
        assert_eq!(
            store.authenticate(&secret, now).unwrap(),
            Identity {
                name: "alice".into(),
                role: Role::Operator
            }
        );
        assert_eq!(
            store.authenticate(&secret, now + 61.0),
            Err(AuthError::Expired("alice".into()))
        );
        assert_eq!(store.authenticate("psk_nope", now), Err(AuthError::Unknown));
        assert_eq!(store.authenticate("old-token", now).unwrap().role, Role::Admin);
        // Another process (the CLI) revokes it: the daemon's store sees it at once.
        KeyStore::open(dir.path(), None).revoke("alice").unwrap();
        assert_eq!(
            store.authenticate(&secret, now),
            Err(AuthError::Revoked("alice".into()))
        );
        assert!(matches!(
            store.create("alice", Role::Admin, None, "cli"),
            Err(KeysError::Invalid(_))
        ));
        assert!(matches!(
            store.create("token", Role::Admin, None, "cli"),
            Err(KeysError::Invalid(_))
        ));
        assert!(matches!(
            store.create("a b", Role::Admin, None, "cli"),
            Err(KeysError::Invalid(_))
        ));
        assert!(matches!(store.revoke("bob"), Err(KeysError::Invalid(_))));
    }

    #[test]
    fn a_damaged_keys_file_accepts_no_key() {
        let dir = tempfile::tempdir().unwrap();
        let store = KeyStore::open(dir.path(), None);
        let (_, secret) = store.create("alice", Role::Admin, None, "cli").unwrap();
        assert!(store.authenticate(&secret, 0.0).is_ok());
        let good = std::fs::read(dir.path().join(KEYS_FILE)).unwrap();
        std::fs::write(dir.path().join(KEYS_FILE), "[{\"name\": ").unwrap();
        assert_eq!(store.authenticate(&secret, 0.0), Err(AuthError::Unknown));
        // The failure is remembered for this version of the file, not the key set.
        assert_eq!(store.authenticate(&secret, 0.0), Err(AuthError::Unknown));
        assert!(store.keys().is_empty());
        // Mended, it is read again.
        std::fs::write(dir.path().join(KEYS_FILE), good).unwrap();
        assert!(store.authenticate(&secret, 0.0).is_ok());
    }

    #[test]
    fn expiries_parse_as_durations_dates_and_times() {
        assert_eq!(parse_expiry("90d", 100.0).unwrap(), 100.0 + 90.0 * 86_400.0);
        assert_eq!(parse_expiry("12h", 0.0).unwrap(), 43_200.0);
        assert_eq!(parse_expiry("1970-01-02", 0.0).unwrap(), 86_400.0);
        assert_eq!(parse_expiry("1970-01-01T01:00:00Z", 0.0).unwrap(), 3600.0);
        assert!(parse_expiry("soon", 0.0).is_err());
        assert!(parse_expiry("-3d", 0.0).is_err());
        // Overflowing durations were `inf`, written to keys.json as null: never.
        for huge in ["1e308d", "1e300h", "4000000d"] {
            let e = parse_expiry(huge, 1.8e9).unwrap_err();
            assert!(
                e.contains("9999-12-31") && e.contains("leave the expiry out"),
                "{e}"
            );
        }
        assert!(parse_expiry("9999-12-31", 1.8e9).is_ok());
        let e = parse_expiry("2020-01-01", 1.8e9).unwrap_err();
        assert!(
            e.contains("already past") && e.contains("2020-01-01T00:00:00Z"),
            "{e}"
        );
        assert_eq!(format_time(86_400.0), "1970-01-02T00:00:00Z");
    }
}

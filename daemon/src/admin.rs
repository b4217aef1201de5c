//! The command line's catalogue and access commands: `periscope runs` (query the run
//! catalogue, tag and annotate runs), `periscope catalogue rebuild|check`,
//! `periscope keys create|list|revoke` and `periscope audit`. They work on the runs
//! directory of the instrument config (`[api] runs-dir`), beside a running daemon or
//! without one: SQLite and the keys file's lock keep the two consistent.
use std::path::{Path, PathBuf};

use clap::{Args, Subcommand};

use crate::access::{KeyStore, Role, format_time, parse_expiry, parse_time};
use crate::catalogue::{AuditEntry, AuditQuery, Catalogue, CatalogueError, RunQuery, SortKey};
use crate::run_dir::{Annotations, RunDir, parse_state, state_name, unix_now};

/// `periscope runs`: list runs from the catalogue, or tag and annotate one.
#[derive(Debug, Args)]
#[command(args_conflicts_with_subcommands = true)]
pub struct RunsArgs {
    /// Tag or annotate a run instead of listing.
    #[command(subcommand)]
    pub command: Option<RunsCommand>,
    /// The filters and output of the listing.
    #[command(flatten)]
    pub list: RunsList,
}

/// The listing's filters.
#[derive(Debug, Args)]
pub struct RunsList {
    /// The instrument whose runs directory to read.
    #[command(flatten)]
    pub instrument: crate::config::InstrumentArg,
    /// Only runs in these states (comma-separated: queued, running, paused,
    /// completed, aborted, failed).
    #[arg(long, value_name = "STATES")]
    pub state: Option<String>,
    /// Only runs made at or after this date or RFC 3339 time.
    #[arg(long, value_name = "DATE")]
    pub since: Option<String>,
    /// Only runs made before this date or RFC 3339 time.
    #[arg(long, value_name = "DATE")]
    pub until: Option<String>,
    /// Only runs of this plan name.
    #[arg(long, value_name = "NAME")]
    pub plan: Option<String>,
    /// Only runs with this tag.
    #[arg(long, value_name = "TAG")]
    pub tag: Option<String>,
    /// Only runs containing this text in their id, plan, note, error, submitter or tags.
    #[arg(long, value_name = "TEXT")]
    pub text: Option<String>,
    /// Sort by: created, id, plan, state, updated, pairs.
    #[arg(long, default_value = "created")]
    pub sort: String,
    /// Newest (largest) first.
    #[arg(long)]
    pub desc: bool,
    /// At most this many runs.
    #[arg(long, default_value_t = 50)]
    pub limit: usize,
    /// Skip this many first.
    #[arg(long, default_value_t = 0)]
    pub offset: usize,
    /// Print JSON (the API's catalogue page) instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// Changing one run's annotations.
#[derive(Debug, Subcommand)]
pub enum RunsCommand {
    /// Add (or with --remove, remove) tags on a run.
    Tag {
        /// The instrument whose runs directory holds the run.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
        /// Run id.
        id: String,
        /// Tags.
        #[arg(required = true)]
        tags: Vec<String>,
        /// Remove the tags instead.
        #[arg(long)]
        remove: bool,
    },
    /// Set a run's free-text note.
    Note {
        /// The instrument whose runs directory holds the run.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
        /// Run id.
        id: String,
        /// The note (replaces the old one; "" clears it).
        text: String,
    },
}

/// `periscope catalogue`.
#[derive(Debug, Subcommand)]
pub enum CatalogueCommand {
    /// Delete the run catalogue and build it anew from the run directories and
    /// audit.jsonl.
    Rebuild {
        /// The instrument whose runs directory to rebuild.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
    },
    /// Bring the catalogue in line with the run directories (what the daemon does at
    /// start) and print what changed.
    Sync {
        /// The instrument whose runs directory to sync.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
    },
}

/// `periscope keys`.
#[derive(Debug, Subcommand)]
pub enum KeysCommand {
    /// Make an API key and print its secret (shown once, never stored).
    Create {
        /// The instrument whose daemon will accept it.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
        /// The key's name, recorded with every action it takes.
        name: String,
        /// Its role: estop, observer, operator, admin.
        #[arg(long)]
        role: String,
        /// When it stops working: a duration (90d, 12h, 30m) or a date or RFC 3339 time.
        #[arg(long, value_name = "WHEN")]
        expires: Option<String>,
    },
    /// List the keys (names, roles, expiry, revocation; never secrets).
    List {
        /// The instrument whose keys to list.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
    },
    /// Revoke a key: it stops working at the daemon's next request.
    Revoke {
        /// The instrument whose key to revoke.
        #[command(flatten)]
        instrument: crate::config::InstrumentArg,
        /// The key's name.
        name: String,
    },
}

/// `periscope audit`: the audit trail, newest first.
#[derive(Debug, Args)]
pub struct AuditArgs {
    /// The instrument whose audit trail to read.
    #[command(flatten)]
    pub instrument: crate::config::InstrumentArg,
    /// Only entries at or after this date or RFC 3339 time.
    #[arg(long, value_name = "DATE")]
    pub since: Option<String>,
    /// Only entries before this date or RFC 3339 time.
    #[arg(long, value_name = "DATE")]
    pub until: Option<String>,
    /// Only entries on this run id or key name.
    #[arg(long)]
    pub target: Option<String>,
    /// Only entries by this key name.
    #[arg(long)]
    pub actor: Option<String>,
    /// Only this action (submit, abort, estop, key-create, authenticate, ...).
    #[arg(long)]
    pub action: Option<String>,
    /// At most this many entries.
    #[arg(long, default_value_t = 50)]
    pub limit: usize,
}

/// Why a catalogue or key command failed.
#[derive(Debug, thiserror::Error)]
pub enum AdminError {
    /// The instrument config is invalid.
    #[error(transparent)]
    Config(#[from] crate::config::ConfigError),
    /// The catalogue failed.
    #[error(transparent)]
    Catalogue(#[from] CatalogueError),
    /// The keys file failed.
    #[error(transparent)]
    Keys(#[from] crate::access::KeysError),
    /// A value on the command line is not acceptable.
    #[error("{0}")]
    Usage(String),
    /// The runs directory a command reads is not there.
    #[error(
        "the runs directory {} {why}: check `[api] runs-dir` in the instrument config \
         (--instrument); `periscope serve` makes it when it first starts",
        path.display()
    )]
    NoRunsDir {
        /// The directory the config names.
        path: PathBuf,
        /// "does not exist", "is not a directory".
        why: &'static str,
    },
    /// A run's files could not be changed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
}

impl From<std::io::Error> for AdminError {
    /// An I/O error of a run's annotations (the caller names the file).
    fn from(source: std::io::Error) -> AdminError {
        AdminError::Io {
            path: PathBuf::new(),
            source,
        }
    }
}

fn runs_dir(instrument: &crate::config::InstrumentArg) -> Result<PathBuf, AdminError> {
    Ok(instrument.load()?.api.runs_dir)
}

/// The runs directory of a command that reads it or changes what is in it: it must be
/// there already. A mistyped `runs-dir` must not leave a new empty directory behind
/// and report no runs, no keys and no audit entries as if that were the instrument's.
fn existing_runs_dir(instrument: &crate::config::InstrumentArg) -> Result<PathBuf, AdminError> {
    let path = runs_dir(instrument)?;
    match std::fs::metadata(&path) {
        Ok(m) if m.is_dir() => Ok(path),
        Ok(_) => Err(AdminError::NoRunsDir {
            path,
            why: "is not a directory",
        }),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Err(AdminError::NoRunsDir {
            path,
            why: "does not exist",
        }),
        Err(source) => Err(AdminError::Io { path, source }),
    }
}

fn time_arg(v: &Option<String>, flag: &str) -> Result<Option<f64>, AdminError> {
    v.as_deref()
        .map(|t| parse_time(t).map_err(|m| AdminError::Usage(format!("--{flag}: {m}"))))
        .transpose()
}

/// `periscope runs`.
pub fn runs(args: RunsArgs) -> Result<(), AdminError> {
    match args.command {
        Some(RunsCommand::Tag {
            instrument,
            id,
            tags,
            remove,
        }) => {
            let (add, rm) = if remove { (vec![], tags) } else { (tags, vec![]) };
            annotate(&existing_runs_dir(&instrument)?, &id, &add, &rm, None)
        }
        Some(RunsCommand::Note { instrument, id, text }) => {
            annotate(&existing_runs_dir(&instrument)?, &id, &[], &[], Some(&text))
        }
        None => list(&args.list),
    }
}

fn list(a: &RunsList) -> Result<(), AdminError> {
    let dir = existing_runs_dir(&a.instrument)?;
    let states = match &a.state {
        Some(s) => s
            .split(',')
            .map(|s| parse_state(s.trim()).map_err(|m| AdminError::Usage(format!("--state: {m}"))))
            .collect::<Result<Vec<_>, _>>()?,
        None => Vec::new(),
    };
    let q = RunQuery {
        states,
        since: time_arg(&a.since, "since")?,
        until: time_arg(&a.until, "until")?,
        plan: a.plan.clone(),
        tag: a.tag.clone(),
        submitted_by: None,
        text: a.text.clone(),
        sort: SortKey::parse(&a.sort).map_err(|m| AdminError::Usage(format!("--sort: {m}")))?,
        descending: a.desc,
        limit: a.limit,
        offset: a.offset,
    };
    q.check().map_err(|(field, m)| {
        let flag = if field == "q" { "text" } else { field };
        AdminError::Usage(format!("--{flag} {m}"))
    })?;
    let cat = Catalogue::open(&dir)?;
    let page = cat.query(&q)?;
    if a.json {
        println!("{}", serde_json::to_string_pretty(&page).expect("serialises"));
        return Ok(());
    }
    println!(
        "{:<44} {:<10} {:<20} {:>11} {:<12} tags",
        "id", "state", "created (UTC)", "pairs", "by"
    );
    for r in &page.runs {
        println!(
            "{:<44} {:<10} {:<20} {:>11} {:<12} {}",
            r.id,
            state_name(r.state),
            r.created_unix_s
                .map(|t| format_time(t).trim_end_matches('Z').replace('T', " "))
                .unwrap_or_default(),
            format!("{}/{}", r.pairs_done, r.pairs_total),
            r.submitted_by.as_deref().unwrap_or("-"),
            r.tags.join(",")
        );
    }
    println!(
        "{} of {} matching (from {})",
        page.runs.len(),
        page.total,
        cat.path().display()
    );
    Ok(())
}

fn annotate(
    dir: &Path,
    id: &str,
    add: &[String],
    remove: &[String],
    note: Option<&str>,
) -> Result<(), AdminError> {
    let run = dir.join(id);
    if id.contains('/') || !RunDir::holds_run(&run) {
        return Err(AdminError::Usage(format!(
            "no run `{id}` in {}; list them with `periscope runs`",
            dir.display()
        )));
    }
    let path = run.join(crate::run_dir::file::ANNOTATIONS);
    let a =
        Annotations::update(&run, |a| a.edit(add, remove, note).map_err(AdminError::Usage)).map_err(|e| {
            match e {
                AdminError::Io { source, .. } => AdminError::Io {
                    path: path.clone(),
                    source,
                },
                other => other,
            }
        })?;
    let cat = Catalogue::open_unsynced(dir)?;
    cat.index(id)?;
    cat.record(
        &AuditEntry::new("cli", "admin", "annotate", Some(id), "ok").detail(format!(
            "tags: {}; note: {} characters",
            a.tags.join(","),
            a.note.chars().count()
        )),
    )?;
    println!("{id}: tags [{}], note {:?}", a.tags.join(", "), a.note);
    Ok(())
}

/// `periscope catalogue`.
pub fn catalogue(cmd: CatalogueCommand) -> Result<(), AdminError> {
    let (dir, rebuild) = match &cmd {
        CatalogueCommand::Rebuild { instrument } => (existing_runs_dir(instrument)?, true),
        CatalogueCommand::Sync { instrument } => (existing_runs_dir(instrument)?, false),
    };
    let t = std::time::Instant::now();
    let (cat, report) = if rebuild {
        Catalogue::rebuild(&dir)?
    } else {
        let cat = Catalogue::open_unsynced(&dir)?;
        let r = cat.sync()?;
        (cat, r)
    };
    println!(
        "{}: {} runs ({} read, {} dropped, {} unreadable), {} audit entries imported, {:.2} s, {} bytes",
        cat.path().display(),
        report.runs,
        report.indexed,
        report.removed,
        report.unreadable,
        report.audit_imported,
        t.elapsed().as_secs_f64(),
        cat.size_bytes()
    );
    Ok(())
}

/// `periscope keys`.
pub fn keys(cmd: KeysCommand) -> Result<(), AdminError> {
    match cmd {
        KeysCommand::Create {
            instrument,
            name,
            role,
            expires,
        } => {
            let dir = runs_dir(&instrument)?;
            std::fs::create_dir_all(&dir).map_err(|source| AdminError::Io {
                path: dir.clone(),
                source,
            })?;
            let role = Role::parse(&role).map_err(|m| AdminError::Usage(format!("--role: {m}")))?;
            let expires = expires
                .map(|e| {
                    parse_expiry(&e, unix_now()).map_err(|m| AdminError::Usage(format!("--expires: {m}")))
                })
                .transpose()?;
            let (rec, secret) = KeyStore::open(&dir, None).create(&name, role, expires, "cli")?;
            // The key exists now: its secret is printed whatever the audit trail says.
            let audited = audit_change(
                &dir,
                &AuditEntry::new("cli", "admin", "key-create", Some(&rec.name), "ok")
                    .detail(format!("role {}", rec.role.name())),
            );
            if let Err(e) = audited {
                eprintln!(
                    "warning: the key was made but its creation could not be recorded in the audit trail: {e}"
                );
            }
            // The secret alone on stdout, so `KEY=$(periscope keys create …)` works; the
            // rest on stderr.
            // Where it is kept, whole: a relative `runs-dir` is taken from the directory
            // the command runs in, and a daemon started elsewhere would not know it.
            let kept = dir.canonicalize().unwrap_or_else(|_| dir.clone());
            eprintln!(
                "key `{}` ({}){} kept in {}: send it as `Authorization: Bearer <secret>`; it is shown only now",
                rec.name,
                rec.role.name(),
                rec.expires_unix_s
                    .map(|e| format!(", expires {}", format_time(e)))
                    .unwrap_or_default(),
                kept.join(crate::access::KEYS_FILE).display()
            );
            println!("{secret}");
            Ok(())
        }
        KeysCommand::List { instrument } => {
            let dir = existing_runs_dir(&instrument)?;
            let keys = KeyStore::open(&dir, None)
                .read()
                .map_err(|source| AdminError::Io {
                    path: dir.join(crate::access::KEYS_FILE),
                    source,
                })?;
            println!(
                "{:<24} {:<9} {:<21} {:<21} status",
                "name", "role", "created", "expires"
            );
            let now = unix_now();
            for k in keys {
                let status = if let Some(r) = k.revoked_unix_s {
                    format!("revoked {}", format_time(r))
                } else if k.expires_unix_s.is_some_and(|e| e <= now) {
                    "expired".into()
                } else {
                    "active".into()
                };
                println!(
                    "{:<24} {:<9} {:<21} {:<21} {status}",
                    k.name,
                    k.role.name(),
                    format_time(k.created_unix_s),
                    k.expires_unix_s
                        .map(format_time)
                        .unwrap_or_else(|| "never".into()),
                );
            }
            Ok(())
        }
        KeysCommand::Revoke { instrument, name } => {
            let dir = existing_runs_dir(&instrument)?;
            let rec = KeyStore::open(&dir, None).revoke(&name)?;
            // Revoked now, whatever the audit trail says.
            println!("key `{}` revoked", rec.name);
            audit_change(
                &dir,
                &AuditEntry::new("cli", "admin", "key-revoke", Some(&rec.name), "ok"),
            )?;
            Ok(())
        }
    }
}

/// Records a change made from the command line: in the audit trail's log first (the
/// change is done; its record must not depend on the catalogue opening), then in the
/// catalogue, which, where it cannot be opened now, takes the entry from the log at its
/// next sync (a warning says so).
fn audit_change(dir: &Path, entry: &AuditEntry) -> Result<(), AdminError> {
    crate::catalogue::append_audit(dir, entry)?;
    if let Err(e) = Catalogue::open_unsynced(dir).and_then(|c| c.catalogue_audit(entry)) {
        eprintln!(
            "warning: recorded in the audit trail's log, not yet in the catalogue ({e}); \
             `periscope catalogue sync` adds it once the catalogue opens"
        );
    }
    Ok(())
}

/// `periscope audit`.
pub fn audit(a: AuditArgs) -> Result<(), AdminError> {
    // As `runs --limit` is (0 was taken as 1).
    let most = crate::catalogue::query::MAX_PAGE;
    if !(1..=most).contains(&a.limit) {
        return Err(AdminError::Usage(format!(
            "--limit {}: expected 1 to {most}",
            a.limit
        )));
    }
    let q = AuditQuery {
        since: time_arg(&a.since, "since")?,
        until: time_arg(&a.until, "until")?,
        actor: a.actor,
        action: a.action,
        target: a.target,
        limit: a.limit,
        ..AuditQuery::default()
    };
    q.check()
        .map_err(|(field, m)| AdminError::Usage(format!("--{field} {m}")))?;
    let dir = existing_runs_dir(&a.instrument)?;
    let cat = Catalogue::open(&dir)?;
    let page = cat.audit(&q)?;
    for e in &page.entries {
        // Entries quote what clients sent (a refused plan's key, a run's name): their
        // control characters are shown escaped, never sent to the terminal, and an
        // entry is one line.
        println!(
            "{}  {:<12} {:<9} {:<14} {:<8} {}{}",
            format_time(e.at_unix_s),
            printable(&e.actor),
            printable(&e.role),
            printable(&e.action),
            printable(&e.outcome),
            printable(e.target.as_deref().unwrap_or("-")),
            e.detail
                .as_deref()
                .map(|d| format!("  ({})", printable(d)))
                .unwrap_or_default()
        );
    }
    println!("{} of {} entries", page.entries.len(), page.total);
    // An action the trail has never recorded is most often a misspelling: say which
    // ones it holds (an action not taken yet is a fair filter, so not refused).
    if let Some(action) = &q.action {
        let known = cat.audit_actions()?;
        if !known.contains(action) {
            eprintln!(
                "no entry has action `{}`; the trail holds: {}",
                printable(action),
                if known.is_empty() {
                    "nothing yet".to_owned()
                } else {
                    known.iter().map(|k| printable(k)).collect::<Vec<_>>().join(", ")
                }
            );
        }
    }
    Ok(())
}

/// `text` with its control characters escaped (`\u{1b}`, `\n`), for a terminal.
fn printable(text: &str) -> String {
    text.chars()
        .flat_map(|c| {
            if c.is_control() {
                c.escape_debug().collect::<Vec<_>>()
            } else {
                vec![c]
            }
        })
        .collect()
}

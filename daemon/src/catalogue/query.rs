//! Reading the catalogue: runs filtered by state, date range, plan, tag, submitter and
//! free text, sorted and paged; one run with its plan; the audit trail. Every filter is
//! a bound parameter (never text pasted into SQL), and the sort column comes from a
//! closed list.
use rusqlite::{OptionalExtension, ToSql, params_from_iter};
use serde::Serialize;
use utoipa::ToSchema;

use super::{AuditEntry, Catalogue, CatalogueError};
use crate::run_dir::{RunState, StateChange};

/// The most rows one page holds.
pub const MAX_PAGE: usize = 1000;

/// A run as the catalogue holds it.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct RunRecord {
    /// Run id.
    pub id: String,
    /// Plan name.
    pub plan: String,
    /// State.
    pub state: RunState,
    /// Current or last stage.
    pub stage: String,
    /// The instrument config's name.
    pub instrument: Option<String>,
    /// Who submitted it (an API key's name, or `cli`).
    pub submitted_by: Option<String>,
    /// The run whose plan this one ran again.
    pub again_of: Option<String>,
    /// The capture file an imported capture's run reconstructs.
    pub imported: Option<String>,
    /// When it was made (Unix seconds).
    pub created_unix_s: Option<f64>,
    /// Its last state change (Unix seconds).
    pub updated_unix_s: Option<f64>,
    /// Pairs planned.
    pub pairs_total: u64,
    /// Pairs stored.
    pub pairs_done: u64,
    /// Last error.
    pub error: Option<String>,
    /// The reconstruction method, once reconstructed.
    pub method: Option<String>,
    /// Seconds the reconstruction took.
    pub recon_s: Option<f64>,
    /// The fit's final loss (method `gtr`).
    pub final_loss: Option<f64>,
    /// Tags.
    pub tags: Vec<String>,
    /// The operator's note.
    pub note: String,
    /// Seconds per stage.
    #[schema(value_type = Vec<Vec<Object>>)]
    pub timings: Vec<(String, f64)>,
    /// State changes, oldest first.
    #[schema(value_type = Vec<Object>)]
    pub history: Vec<StateChange>,
    /// Output files and their sizes.
    pub outputs: Vec<OutputFile>,
}

/// An output file of a run.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct OutputFile {
    /// File name.
    pub name: String,
    /// Size in bytes.
    pub bytes: u64,
}

/// What a run list is sorted by.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SortKey {
    /// When the run was made (then id).
    #[default]
    Created,
    /// Run id.
    Id,
    /// Plan name.
    Plan,
    /// State.
    State,
    /// Last state change.
    Updated,
    /// Pairs stored.
    Pairs,
}

impl SortKey {
    /// The names `sort=` takes.
    pub const NAMES: &'static str = "created, id, plan, state, updated, pairs";

    /// Parses a sort key's name.
    pub fn parse(s: &str) -> Result<SortKey, String> {
        Ok(match s {
            "created" => SortKey::Created,
            "id" => SortKey::Id,
            "plan" => SortKey::Plan,
            "state" => SortKey::State,
            "updated" => SortKey::Updated,
            "pairs" => SortKey::Pairs,
            other => return Err(format!("sort `{other}`: expected one of {}", SortKey::NAMES)),
        })
    }

    fn column(self) -> &'static str {
        match self {
            SortKey::Created => "r.created",
            SortKey::Id => "r.id",
            SortKey::Plan => "r.plan",
            SortKey::State => "r.state",
            SortKey::Updated => "r.updated",
            SortKey::Pairs => "r.pairs_done",
        }
    }
}

/// A query over runs. Empty filters match everything.
#[derive(Clone, Debug, PartialEq)]
pub struct RunQuery {
    /// Runs in any of these states.
    pub states: Vec<RunState>,
    /// Made at or after (Unix seconds).
    pub since: Option<f64>,
    /// Made before (Unix seconds).
    pub until: Option<f64>,
    /// Of this plan name.
    pub plan: Option<String>,
    /// With this tag.
    pub tag: Option<String>,
    /// Submitted by this key name.
    pub submitted_by: Option<String>,
    /// Containing this text (case-insensitive) in the id, plan name, note, error,
    /// submitter or a tag.
    pub text: Option<String>,
    /// Sort key.
    pub sort: SortKey,
    /// Largest first.
    pub descending: bool,
    /// At most this many rows (1 to [`MAX_PAGE`]).
    pub limit: usize,
    /// Rows skipped before the page.
    pub offset: usize,
}

/// The longest filter text a query takes, in bytes (SQLite refuses `LIKE` patterns
/// past 50,000 bytes, and escaping can double them).
pub const MAX_FILTER_TEXT: usize = 1024;

/// The longest free-text search (`q`), in bytes: it is matched as `%text%` against
/// seven columns of every run, at a cost of its length times each field's (notes of
/// 4,096 bytes), under the catalogue's lock that audit entries wait for; a search box's
/// text is a few words.
pub const MAX_SEARCH_TEXT: usize = 128;

impl RunQuery {
    /// Whether the query's values are ones the catalogue can run: the field at fault
    /// (its API name) and why, if not.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        if !(1..=MAX_PAGE).contains(&self.limit) {
            return Err(("limit", format!("{}: expected 1 to {MAX_PAGE}", self.limit)));
        }
        if i64::try_from(self.offset).is_err() {
            return Err(("offset", format!("{}: expected 0 to {}", self.offset, i64::MAX)));
        }
        check_span(self.since, self.until)?;
        if let Some(q) = &self.text
            && q.len() > MAX_SEARCH_TEXT
        {
            return Err((
                "q",
                format!("{} bytes: a search of at most {MAX_SEARCH_TEXT}", q.len()),
            ));
        }
        for (field, v) in [
            ("plan", &self.plan),
            ("tag", &self.tag),
            ("submitted_by", &self.submitted_by),
        ] {
            if let Some(v) = v
                && v.len() > MAX_FILTER_TEXT
            {
                return Err((field, format!("{} bytes: at most {MAX_FILTER_TEXT}", v.len())));
            }
        }
        Ok(())
    }
}

impl Default for RunQuery {
    fn default() -> RunQuery {
        RunQuery {
            states: Vec::new(),
            since: None,
            until: None,
            plan: None,
            tag: None,
            submitted_by: None,
            text: None,
            sort: SortKey::Created,
            descending: false,
            limit: MAX_PAGE,
            offset: 0,
        }
    }
}

/// One page of runs.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct RunPage {
    /// Runs matching the filters, in all pages.
    pub total: u64,
    /// The page's first row's place.
    pub offset: u64,
    /// The page.
    pub runs: Vec<RunRecord>,
}

/// A query over the audit trail, newest first.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct AuditQuery {
    /// At or after (Unix seconds).
    pub since: Option<f64>,
    /// Before (Unix seconds).
    pub until: Option<f64>,
    /// By this actor.
    pub actor: Option<String>,
    /// This action.
    pub action: Option<String>,
    /// On this target (a run id, a key name).
    pub target: Option<String>,
    /// At most this many (1 to [`MAX_PAGE`]; 0 means 100).
    pub limit: usize,
    /// Entries skipped.
    pub offset: usize,
}

impl AuditQuery {
    /// As [`RunQuery::check`], for what the audit trail's filters share with it.
    pub fn check(&self) -> Result<(), (&'static str, String)> {
        check_span(self.since, self.until)
    }
}

/// A `since` not before `until` matches nothing (`until` is exclusive): that is a
/// mistake in the query, refused rather than answered with an empty page.
fn check_span(since: Option<f64>, until: Option<f64>) -> Result<(), (&'static str, String)> {
    match (since, until) {
        (Some(a), Some(b)) if a >= b => Err((
            "until",
            format!(
                "{} is not after since ({}): nothing can match (until is exclusive)",
                crate::access::format_time(b),
                crate::access::format_time(a)
            ),
        )),
        _ => Ok(()),
    }
}

/// One page of the audit trail.
#[derive(Clone, Debug, PartialEq, Serialize, ToSchema)]
pub struct AuditPage {
    /// Entries matching, in all pages.
    pub total: u64,
    /// The page's first entry's place.
    pub offset: u64,
    /// The entries, newest first.
    pub entries: Vec<AuditEntry>,
}

/// A state's name as stored and as the API spells it.
pub fn state_str(s: RunState) -> &'static str {
    crate::run_dir::state_name(s)
}

fn parse_state(s: &str) -> RunState {
    crate::run_dir::parse_state(s).unwrap_or(RunState::Failed)
}

/// `%` and `_` in `text` taken literally by a `LIKE … ESCAPE '\'`.
fn like_pattern(text: &str) -> String {
    let mut p = String::from("%");
    for c in text.chars() {
        if matches!(c, '%' | '_' | '\\') {
            p.push('\\');
        }
        p.push(c);
    }
    p.push('%');
    p
}

/// A WHERE clause and its parameters.
#[derive(Default)]
struct Filter {
    clauses: Vec<String>,
    params: Vec<Box<dyn ToSql>>,
}

impl Filter {
    /// Adds `clause`, whose `?` marks take `values` in order (numbered after the
    /// parameters already added).
    fn add(&mut self, clause: &str, values: Vec<Box<dyn ToSql>>) {
        let mut numbered = String::new();
        let mut n = self.params.len();
        for (i, part) in clause.split('?').enumerate() {
            if i > 0 {
                n += 1;
                numbered.push_str(&format!("?{n}"));
            }
            numbered.push_str(part);
        }
        self.params.extend(values);
        self.clauses.push(numbered);
    }

    fn sql(&self) -> String {
        if self.clauses.is_empty() {
            String::new()
        } else {
            format!(" WHERE {}", self.clauses.join(" AND "))
        }
    }
}

impl Catalogue {
    /// A page of runs matching `q`.
    pub fn query(&self, q: &RunQuery) -> Result<RunPage, CatalogueError> {
        let mut f = Filter::default();
        if !q.states.is_empty() {
            let marks = vec!["?"; q.states.len()].join(", ");
            f.add(
                &format!("r.state IN ({marks})"),
                q.states
                    .iter()
                    .map(|s| Box::new(state_str(*s)) as Box<dyn ToSql>)
                    .collect(),
            );
        }
        if let Some(t) = q.since {
            f.add("r.created >= ?", vec![Box::new(t)]);
        }
        if let Some(t) = q.until {
            f.add("r.created < ?", vec![Box::new(t)]);
        }
        if let Some(p) = &q.plan {
            f.add("r.plan = ?", vec![Box::new(p.clone())]);
        }
        if let Some(t) = &q.tag {
            f.add(
                "EXISTS (SELECT 1 FROM tags t WHERE t.run_id = r.id AND t.tag = ?)",
                vec![Box::new(t.clone())],
            );
        }
        if let Some(s) = &q.submitted_by {
            f.add("r.submitted_by = ?", vec![Box::new(s.clone())]);
        }
        if let Some(text) = q.text.as_deref().filter(|t| !t.is_empty()) {
            let p = like_pattern(text);
            f.add(
                "(r.id LIKE ? ESCAPE '\\' OR r.plan LIKE ? ESCAPE '\\' OR r.note LIKE ? ESCAPE '\\' \
                 OR r.error LIKE ? ESCAPE '\\' OR r.submitted_by LIKE ? ESCAPE '\\' \
                 OR r.imported LIKE ? ESCAPE '\\' \
                 OR EXISTS (SELECT 1 FROM tags t WHERE t.run_id = r.id AND t.tag LIKE ? ESCAPE '\\'))",
                (0..7).map(|_| Box::new(p.clone()) as Box<dyn ToSql>).collect(),
            );
        }
        let limit = q.limit.clamp(1, MAX_PAGE);
        let dir = if q.descending { "DESC" } else { "ASC" };
        let wh = f.sql();
        let conn = self.conn();
        let total: i64 = conn
            .query_row(
                &format!("SELECT COUNT(*) FROM runs r{wh}"),
                params_from_iter(f.params.iter()),
                |r| r.get(0),
            )
            .map_err(self.sqlite())?;
        let sql = format!(
            "SELECT r.id, r.plan, r.state, r.stage, r.instrument, r.submitted_by, r.again_of,
                r.created, r.updated, r.pairs_total, r.pairs_done, r.error, r.method, r.recon_s,
                r.final_loss, r.note, r.imported
             FROM runs r{wh} ORDER BY {col} {dir}, r.id {dir} LIMIT {limit} OFFSET {offset}",
            col = q.sort.column(),
            offset = q.offset,
        );
        let mut stmt = conn.prepare(&sql).map_err(self.sqlite())?;
        let mut runs: Vec<RunRecord> = stmt
            .query_map(params_from_iter(f.params.iter()), row_to_record)
            .map_err(self.sqlite())?
            .collect::<Result<_, _>>()
            .map_err(self.sqlite())?;
        drop(stmt);
        for r in &mut runs {
            fill_children(&conn, r).map_err(self.sqlite())?;
        }
        Ok(RunPage {
            total: total as u64,
            offset: q.offset as u64,
            runs,
        })
    }

    /// One run, with its plan's text.
    pub fn get(&self, id: &str) -> Result<Option<(RunRecord, String)>, CatalogueError> {
        let conn = self.conn();
        let row = conn
            .query_row(
                "SELECT r.id, r.plan, r.state, r.stage, r.instrument, r.submitted_by, r.again_of,
                    r.created, r.updated, r.pairs_total, r.pairs_done, r.error, r.method, r.recon_s,
                    r.final_loss, r.note, r.imported, r.plan_text
                 FROM runs r WHERE r.id = ?1",
                [id],
                |row| Ok((row_to_record(row)?, row.get::<_, String>(17)?)),
            )
            .optional()
            .map_err(self.sqlite())?;
        let Some((mut rec, text)) = row else {
            return Ok(None);
        };
        fill_children(&conn, &mut rec).map_err(self.sqlite())?;
        Ok(Some((rec, text)))
    }

    /// A page of the audit trail, newest first.
    pub fn audit(&self, q: &AuditQuery) -> Result<AuditPage, CatalogueError> {
        let mut f = Filter::default();
        if let Some(t) = q.since {
            f.add("a.at >= ?", vec![Box::new(t)]);
        }
        if let Some(t) = q.until {
            f.add("a.at < ?", vec![Box::new(t)]);
        }
        for (col, v) in [
            ("a.actor", &q.actor),
            ("a.action", &q.action),
            ("a.target", &q.target),
        ] {
            if let Some(v) = v {
                f.add(&format!("{col} = ?"), vec![Box::new(v.clone())]);
            }
        }
        let limit = if q.limit == 0 { 100 } else { q.limit.min(MAX_PAGE) };
        let wh = f.sql();
        let conn = self.conn();
        let total: i64 = conn
            .query_row(
                &format!("SELECT COUNT(*) FROM audit a{wh}"),
                params_from_iter(f.params.iter()),
                |r| r.get(0),
            )
            .map_err(self.sqlite())?;
        let sql = format!(
            "SELECT a.id, a.at, a.actor, a.role, a.action, a.target, a.outcome, a.detail, a.peer
             FROM audit a{wh} ORDER BY a.at DESC, a.id DESC LIMIT {limit} OFFSET {}",
            q.offset
        );
        let mut stmt = conn.prepare(&sql).map_err(self.sqlite())?;
        let entries = stmt
            .query_map(params_from_iter(f.params.iter()), |r| {
                Ok(AuditEntry {
                    id: r.get(0)?,
                    at_unix_s: r.get(1)?,
                    actor: r.get(2)?,
                    role: r.get(3)?,
                    action: r.get(4)?,
                    target: r.get(5)?,
                    outcome: r.get(6)?,
                    detail: r.get(7)?,
                    peer: r.get(8)?,
                })
            })
            .map_err(self.sqlite())?
            .collect::<Result<_, _>>()
            .map_err(self.sqlite())?;
        Ok(AuditPage {
            total: total as u64,
            offset: q.offset as u64,
            entries,
        })
    }

    /// The actions the audit trail holds, sorted: what an `action` filter that
    /// matched nothing could have named.
    pub fn audit_actions(&self) -> Result<Vec<String>, CatalogueError> {
        let conn = self.conn();
        let mut stmt = conn
            .prepare("SELECT DISTINCT action FROM audit ORDER BY action")
            .map_err(self.sqlite())?;
        let actions = stmt
            .query_map([], |r| r.get(0))
            .map_err(self.sqlite())?
            .collect::<Result<_, _>>()
            .map_err(self.sqlite())?;
        Ok(actions)
    }
}

fn row_to_record(r: &rusqlite::Row<'_>) -> rusqlite::Result<RunRecord> {
    Ok(RunRecord {
        id: r.get(0)?,
        plan: r.get(1)?,
        state: parse_state(&r.get::<_, String>(2)?),
        stage: r.get(3)?,
        instrument: r.get(4)?,
        submitted_by: r.get(5)?,
        again_of: r.get(6)?,
        created_unix_s: r.get(7)?,
        updated_unix_s: r.get(8)?,
        pairs_total: r.get::<_, i64>(9)?.max(0) as u64,
        pairs_done: r.get::<_, i64>(10)?.max(0) as u64,
        error: r.get(11)?,
        method: r.get(12)?,
        recon_s: r.get(13)?,
        final_loss: r.get(14)?,
        note: r.get(15)?,
        imported: r.get(16)?,
        tags: Vec::new(),
        timings: Vec::new(),
        history: Vec::new(),
        outputs: Vec::new(),
    })
}

/// Reads a run's tags, timings, state changes and outputs.
fn fill_children(conn: &rusqlite::Connection, r: &mut RunRecord) -> rusqlite::Result<()> {
    let mut stmt = conn.prepare_cached("SELECT tag FROM tags WHERE run_id = ?1 ORDER BY tag")?;
    r.tags = stmt
        .query_map([&r.id], |row| row.get(0))?
        .collect::<Result<_, _>>()?;
    let mut stmt =
        conn.prepare_cached("SELECT stage, seconds FROM timings WHERE run_id = ?1 ORDER BY seq")?;
    r.timings = stmt
        .query_map([&r.id], |row| Ok((row.get(0)?, row.get(1)?)))?
        .collect::<Result<_, _>>()?;
    let mut stmt =
        conn.prepare_cached("SELECT at, state, by FROM state_changes WHERE run_id = ?1 ORDER BY seq")?;
    r.history = stmt
        .query_map([&r.id], |row| {
            Ok(StateChange {
                at_unix_s: row.get(0)?,
                state: parse_state(&row.get::<_, String>(1)?),
                by: row.get(2)?,
            })
        })?
        .collect::<Result<_, _>>()?;
    let mut stmt = conn.prepare_cached("SELECT name, bytes FROM outputs WHERE run_id = ?1 ORDER BY name")?;
    r.outputs = stmt
        .query_map([&r.id], |row| {
            Ok(OutputFile {
                name: row.get(0)?,
                bytes: row.get::<_, i64>(1)?.max(0) as u64,
            })
        })?
        .collect::<Result<_, _>>()?;
    Ok(())
}

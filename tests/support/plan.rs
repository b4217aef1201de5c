//! The capture plan the tests share: `tests/data/plans/small-fbp.toml` (a small
//! confocal capture solved by FBP, about a second on the simulator at time-scale 0),
//! and [`SmallPlan::set`] for a test's variant of it (a run name, a finer grid, a
//! longer dwell, a 3D-GTR fit), so that each test states only what it changes.
//!
//! The end-to-end crate exports it from `support/lib.rs`; the daemon's own tests and
//! benchmarks, which cannot depend on that crate, include this file
//! (`daemon/tests/common/mod.rs`, `daemon/benches/*.rs`), so there is one copy.
use std::fmt::Debug;

/// The shared plan, with a test's edits.
#[derive(Clone, Debug)]
pub struct SmallPlan {
    text: String,
}

impl Default for SmallPlan {
    /// `tests/data/plans/small-fbp.toml` as it is.
    fn default() -> Self {
        SmallPlan {
            text: include_str!("../data/plans/small-fbp.toml").to_owned(),
        }
    }
}

impl SmallPlan {
    /// The plan with `name` as its name (the run directory's suffix).
    pub fn named(name: &str) -> Self {
        SmallPlan::default().set("name", name)
    }

    /// Sets `key` (dotted, as in the plan's docs and its error messages:
    /// `los.dwell-ms`, `recon.gtr.epochs`) to `value`, written as `{:?}` writes it:
    /// TOML for numbers, arrays of them, booleans and plain strings. The key's line is
    /// replaced, or a line is added at the end of its table, or the table at the end of
    /// the plan; a misspelt key reaches the plan's loader, which refuses it.
    pub fn set(mut self, key: &str, value: impl Debug) -> Self {
        let (table, name) = key.rsplit_once('.').unwrap_or(("", key));
        let line = format!("{name} = {value:?}");
        let mut lines: Vec<String> = self.text.lines().map(str::to_owned).collect();
        let mut current = "";
        // The key's own line, else the line after its table's last key.
        let (mut found, mut end) = (None, None);
        for (i, l) in lines.iter().enumerate() {
            let t = l.trim();
            if let Some(header) = t.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
                current = header.trim();
                continue;
            }
            if current != table || t.is_empty() || t.starts_with('#') {
                continue;
            }
            end = Some(i + 1);
            if t.split_once('=').is_some_and(|(k, _)| k.trim() == name) {
                found = Some(i);
            }
        }
        match (found, end) {
            (Some(i), _) => lines[i] = line,
            (None, Some(i)) => lines.insert(i, line),
            (None, None) if table.is_empty() => lines.insert(0, line),
            (None, None) => lines.extend([format!("[{table}]"), line]),
        }
        self.text = lines.join("\n") + "\n";
        self
    }

    /// Removes `key` (dotted, as for [`SmallPlan::set`]) from the plan, if it is there:
    /// a pair mode that does not read it refuses it (`pairs.offset-mm` beside
    /// `pairs.mode = "scanned"`).
    pub fn unset(mut self, key: &str) -> Self {
        let (table, name) = key.rsplit_once('.').unwrap_or(("", key));
        let mut current = String::new();
        let lines: Vec<&str> = self
            .text
            .lines()
            .filter(|l| {
                let t = l.trim();
                if let Some(header) = t.strip_prefix('[').and_then(|h| h.strip_suffix(']')) {
                    current = header.trim().to_owned();
                    return true;
                }
                !(current == table && t.split_once('=').is_some_and(|(k, _)| k.trim() == name))
            })
            .collect();
        self.text = lines.join("\n") + "\n";
        self
    }

    /// Adds `tables` (TOML text, e.g. a `[suspend]` table) at the end of the plan.
    pub fn with(mut self, tables: &str) -> Self {
        self.text.push_str(tables);
        self
    }

    /// The plan's text.
    pub fn toml(&self) -> String {
        self.text.clone()
    }
}

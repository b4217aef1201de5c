//! A TOML file held in memory with the helpers to report errors against it.
use std::fmt;
use std::path::{Path, PathBuf};

use serde::de::DeserializeOwned;
use toml::de::{DeTable, DeValue};

/// A problem with a configuration file, located as precisely as the file allows.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read at all.
    #[error("cannot read {}: {source}; check the path (relative paths are taken from the current directory)", path.display())]
    Read {
        /// The file that was asked for.
        path: PathBuf,
        /// Why reading failed.
        source: std::io::Error,
    },
    /// The file is not UTF-8 text.
    #[error(
        "{} is not UTF-8 text ({source}): a TOML file is UTF-8; save it as UTF-8, or check that this is the file you meant",
        path.display()
    )]
    NotText {
        /// The file.
        path: PathBuf,
        /// Where the text stops being UTF-8.
        source: std::string::FromUtf8Error,
    },
    /// The file was read but its content is wrong.
    #[error("{location}: {message}")]
    Invalid {
        /// File, line and key.
        location: Location,
        /// What is wrong and what to do.
        message: String,
    },
}

impl ConfigError {
    /// The dotted key the error is about, when it is about one.
    pub fn key(&self) -> Option<&str> {
        match self {
            Self::Invalid { location, .. } => location.key.as_deref(),
            Self::Read { .. } | Self::NotText { .. } => None,
        }
    }

    /// The 1-based line the error points at, when known.
    pub fn line(&self) -> Option<usize> {
        match self {
            Self::Invalid { location, .. } => location.line,
            Self::Read { .. } | Self::NotText { .. } => None,
        }
    }
}

/// Where in a file a problem is.
#[derive(Debug, Clone)]
pub struct Location {
    /// The file.
    pub path: PathBuf,
    /// 1-based line, when known.
    pub line: Option<usize>,
    /// Dotted key path such as `galvo.laser.origin[2]`, when known.
    pub key: Option<String>,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.path.display())?;
        if let Some(line) = self.line {
            write!(f, ":{line}")?;
        }
        if let Some(key) = &self.key {
            write!(f, ": key `{key}`")?;
        }
        Ok(())
    }
}

/// The text of a TOML file and where it came from.
#[derive(Debug, Clone)]
pub struct TomlSource {
    path: PathBuf,
    text: String,
}

/// Largest config, plan or scene file read, bytes (4 MiB: the largest plan in use is a
/// few KiB; a file of tens of MB is a mistake or an attack, and its parse would take
/// hundreds of times its size in memory).
pub const MAX_TOML_BYTES: u64 = 4 << 20;

impl TomlSource {
    /// Reads `path` into memory.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let read = |source| ConfigError::Read {
            path: path.to_owned(),
            source,
        };
        let bytes = periscope_recon::io::read_regular_capped(path, MAX_TOML_BYTES).map_err(read)?;
        let text = String::from_utf8(bytes).map_err(|source| ConfigError::NotText {
            path: path.to_owned(),
            source,
        })?;
        Ok(Self::from_text(path, text))
    }

    /// Wraps text that did not come from disk (an HTTP body, a test); `path` is what
    /// error messages will call it.
    pub fn from_text(path: impl Into<PathBuf>, text: impl Into<String>) -> Self {
        Self {
            path: path.into(),
            text: text.into(),
        }
    }

    /// The file's path, as given.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The file's text.
    pub fn text(&self) -> &str {
        &self.text
    }

    /// Stage one: deserialise the raw structure, reporting syntax errors, unknown keys
    /// and type mismatches with their line and key path.
    pub fn parse<T: DeserializeOwned>(&self) -> Result<T, ConfigError> {
        let deserializer =
            toml::de::Deserializer::parse(&self.text).map_err(|err| self.toml_error(&err, None))?;
        serde_path_to_error::deserialize(deserializer).map_err(|err| {
            let key = err.path().to_string();
            let key = (key != ".").then_some(key);
            self.toml_error(err.inner(), key)
        })
    }

    /// Stage two helper: an error about `key` (dotted, with `[i]` for array items),
    /// located at the line where that key is written, or where its table starts.
    pub fn invalid(&self, key: &str, message: impl Into<String>) -> ConfigError {
        ConfigError::Invalid {
            location: Location {
                path: self.path.clone(),
                line: self.locate(key).map(|offset| self.line_of(offset)),
                key: Some(key.to_owned()),
            },
            message: short_numbers(&message.into()),
        }
    }

    fn toml_error(&self, err: &toml::de::Error, key: Option<String>) -> ConfigError {
        let line = err.span().map(|span| self.line_of(span.start));
        let mut message = short_numbers(err.message().trim_end());
        if message.starts_with("unknown field") {
            message.push_str("; remove it or check its spelling (keys are kebab-case)");
        } else if message.starts_with("missing field") {
            message.push_str("; add it (see the example files in configs/)");
        } else if message.starts_with("duplicate key") {
            // The parser names no key: its span covers the one written a second time.
            let span = err.span();
            let written = span
                .clone()
                .and_then(|span| self.text.get(span))
                .map(str::trim)
                .filter(|t| !t.is_empty() && t.len() <= 200 && !t.contains('\n'));
            // A table header's span is its name, inside the brackets.
            let header = span.is_some_and(|span| {
                let start = self.text[..span.start.min(self.text.len())]
                    .rfind('\n')
                    .map_or(0, |i| i + 1);
                self.text[start..].trim_start().starts_with('[')
            });
            message = match written {
                Some(t) if header => format!(
                    "duplicate table `[{t}]`: it is already written above; move its keys into that one"
                ),
                Some(k) => format!("duplicate key `{k}`: it is already set above; keep one"),
                None => format!("{message}: a key or table is written twice; keep one"),
            };
        }
        ConfigError::Invalid {
            location: Location {
                path: self.path.clone(),
                line,
                key,
            },
            message,
        }
    }

    fn line_of(&self, offset: usize) -> usize {
        let offset = offset.min(self.text.len());
        self.text.as_bytes()[..offset]
            .iter()
            .filter(|&&b| b == b'\n')
            .count()
            + 1
    }

    /// Byte offset of the deepest part of `key` that exists in the document.
    fn locate(&self, key: &str) -> Option<usize> {
        let table = DeTable::parse(&self.text).ok()?;
        let mut best = None;
        let mut current: Option<&DeValue<'_>> = None;
        let mut root = Some(table.get_ref());
        for part in split_key(key) {
            let found = match (part, root.take(), current) {
                (KeyPart::Name(name), Some(table), _) => table
                    .iter()
                    .find(|(k, _)| k.get_ref().as_ref() == name)
                    .map(|(k, v)| (k.span().start, v)),
                (KeyPart::Name(name), None, Some(DeValue::Table(table))) => table
                    .iter()
                    .find(|(k, _)| k.get_ref().as_ref() == name)
                    .map(|(k, v)| (k.span().start, v)),
                (KeyPart::Index(i), None, Some(DeValue::Array(items))) => {
                    items.get(i).map(|v| (v.span().start, v))
                }
                _ => None,
            };
            let Some((offset, value)) = found else { break };
            best = Some(offset);
            current = Some(value.get_ref());
        }
        best
    }
}

enum KeyPart<'a> {
    Name(&'a str),
    Index(usize),
}

fn split_key(key: &str) -> impl Iterator<Item = KeyPart<'_>> {
    key.split('.').flat_map(|segment| {
        let (name, rest) = segment.split_once('[').unwrap_or((segment, ""));
        let indices = rest
            .split('[')
            .filter_map(|i| i.trim_end_matches(']').parse().ok())
            .map(KeyPart::Index);
        (!name.is_empty())
            .then_some(KeyPart::Name(name))
            .into_iter()
            .chain(indices)
    })
}

/// `message` with each number written out past 20 characters (`1e300` as Rust and
/// serde print it: 301 digits) in scientific notation; shorter ones, whole `u64`s
/// included, as they are.
fn short_numbers(message: &str) -> String {
    let bytes = message.as_bytes();
    let mut out = String::with_capacity(message.len());
    let mut i = 0;
    while i < bytes.len() {
        // A number starts at a digit not inside a word (`x2`, `v1`).
        let starts = bytes[i].is_ascii_digit() && (i == 0 || !bytes[i - 1].is_ascii_alphanumeric());
        if !starts {
            let c = message[i..].chars().next().unwrap_or_default();
            out.push(c);
            i += c.len_utf8().max(1);
            continue;
        }
        let mut j = i;
        while j < bytes.len() && (bytes[j].is_ascii_digit() || bytes[j] == b'.') {
            j += 1;
        }
        // A sentence's full stop is not part of the number.
        let text = message[i..j].trim_end_matches('.');
        let end = i + text.len();
        match text.parse::<f64>() {
            Ok(v) if text.len() > 20 => out.push_str(&format!("{v:e}")),
            _ => out.push_str(text),
        }
        i = end;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields, rename_all = "kebab-case")]
    #[allow(dead_code)]
    struct Raw {
        top: u32,
        inner: Inner,
    }

    #[derive(Debug, serde::Deserialize)]
    #[serde(deny_unknown_fields, rename_all = "kebab-case")]
    #[allow(dead_code)]
    struct Inner {
        pair: [f64; 2],
        bin_width: f64,
    }

    const GOOD: &str = "top = 1\n\n[inner]\npair = [1.0, 2.0]\nbin-width = 3.0\n";

    /// The parser's "duplicate key" names no key: the message names the one written
    /// twice, or the table opened twice.
    #[test]
    fn a_key_or_table_written_twice_is_named() {
        let src = TomlSource::from_text("x.toml", GOOD.replace("bin-width = 3.0", "pair = [3.0, 4.0]"));
        let err = src.parse::<Raw>().unwrap_err();
        assert_eq!(err.line(), Some(5), "{err}");
        assert!(
            err.to_string()
                .contains("duplicate key `pair`: it is already set above"),
            "{err}"
        );
        let src = TomlSource::from_text("x.toml", format!("{GOOD}\n[inner]\n"));
        let err = src.parse::<Raw>().unwrap_err();
        assert_eq!(err.line(), Some(7), "{err}");
        assert!(err.to_string().contains("duplicate table `[inner]`"), "{err}");
    }

    #[test]
    fn a_huge_float_is_quoted_short() {
        let src = TomlSource::from_text("x.toml", GOOD.replace("top = 1", "top = 1e300"));
        let err = src.parse::<Raw>().unwrap_err().to_string();
        assert!(err.contains("floating point `1e300`, expected u32"), "{err}");
        for (long, short) in [
            (
                "floating point `2.5`, expected u32",
                "floating point `2.5`, expected u32",
            ),
            (
                "18446744073709551615 is out of range.",
                "18446744073709551615 is out of range.",
            ),
            (
                &format!("{} is out of range, v2", 1e300),
                "1e300 is out of range, v2",
            ),
            (&format!("{} is too small.", 1.5e-30), "1.5e-30 is too small."),
            ("run 20261101-100000-wall, é 3", "run 20261101-100000-wall, é 3"),
        ] {
            assert_eq!(short_numbers(long), short, "{long}");
        }
        let src = TomlSource::from_text("x.toml", GOOD);
        let err = src
            .invalid("top", format!("{} is out of range", 1e40))
            .to_string();
        assert!(err.ends_with("key `top`: 1e40 is out of range"), "{err}");
    }

    #[test]
    fn type_errors_name_line_and_key() {
        let src = TomlSource::from_text("x.toml", GOOD.replace("bin-width = 3.0", "bin-width = \"a\""));
        let err = src.parse::<Raw>().unwrap_err();
        assert_eq!(err.line(), Some(5), "{err}");
        assert_eq!(err.key(), Some("inner.bin-width"), "{err}");
        assert!(
            err.to_string().starts_with("x.toml:5: key `inner.bin-width`"),
            "{err}"
        );
    }

    #[test]
    fn unknown_keys_say_what_to_do() {
        let src = TomlSource::from_text("x.toml", format!("{GOOD}bogus = 1\n"));
        let err = src.parse::<Raw>().unwrap_err().to_string();
        assert!(err.contains("bogus") && err.contains("remove it"), "{err}");
        assert!(err.contains("x.toml:6"), "{err}");
    }

    #[test]
    fn syntax_errors_have_a_line() {
        let src = TomlSource::from_text("x.toml", "top = 1\n[inner\n");
        let err = src.parse::<Raw>().unwrap_err();
        assert_eq!(err.line(), Some(2), "{err}");
    }

    #[test]
    fn validation_errors_find_nested_keys_and_array_items() {
        let src = TomlSource::from_text("x.toml", GOOD);
        assert_eq!(src.invalid("inner.pair[1]", "m").line(), Some(4));
        assert_eq!(src.invalid("inner.bin-width", "m").line(), Some(5));
        assert_eq!(src.invalid("top", "m").line(), Some(1));
        // A key that is absent points at its nearest existing parent.
        assert_eq!(src.invalid("inner.missing", "m").line(), Some(3));
        assert_eq!(src.invalid("nowhere", "m").line(), None);
    }
}

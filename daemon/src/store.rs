//! Run storage, `runs/<id>/`: provenance, the append-only histogram log, the relay and
//! pair plan, events and outputs.
//!
//! The histogram log is the only copy of what the instrument measured, so it is
//! written for crashes: one self-describing record per pair (its pair index, flags,
//! settings and counts, then a CRC-32 of all of it), appended and fsynced in batches.
//! On resume, records are read back until the first one that is incomplete or fails
//! its CRC; the file is cut there, and capture continues with the first pair that has
//! no valid record. So a `kill -9` loses at most the unsynced tail, which is measured
//! again, and no pair is ever stored twice.
use std::fs::{self, File, OpenOptions};
use std::io::{self, BufReader, Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use periscope_drivers::HistogramFlags;
use serde::{Deserialize, Serialize};

/// Record magic, `PHR1`.
const MAGIC: [u8; 4] = *b"PHR1";
/// Record header length, bytes.
const HEADER: usize = 32;
/// Sync the log after this many records...
const SYNC_EVERY: usize = 32;
/// ...or this long after the last sync, whichever comes first.
const SYNC_INTERVAL: Duration = Duration::from_millis(500);

/// The histogram log's file name in a run directory.
pub const HISTOGRAM_LOG: &str = "histograms.bin";

/// One stored measurement.
#[derive(Clone, Debug, PartialEq)]
pub struct Record {
    /// Index into the run's planned pairs.
    pub pair: u32,
    /// Flags of the histograms summed into it.
    pub flags: HistogramFlags,
    /// Bin width, ps.
    pub bin_width_ps: u32,
    /// Offset of bin 0, ps.
    pub offset_ps: u32,
    /// Total dwell, µs.
    pub dwell_us: u64,
    /// Counts.
    pub counts: Vec<u32>,
}

impl Record {
    fn encode(&self) -> Vec<u8> {
        let mut b = Vec::with_capacity(HEADER + 4 * self.counts.len() + 4);
        b.extend_from_slice(&MAGIC);
        b.extend_from_slice(&self.pair.to_le_bytes());
        let flags = u32::from(self.flags.overflow) | (u32::from(self.flags.saturated) << 1);
        b.extend_from_slice(&flags.to_le_bytes());
        b.extend_from_slice(&(self.counts.len() as u32).to_le_bytes());
        b.extend_from_slice(&self.bin_width_ps.to_le_bytes());
        b.extend_from_slice(&self.offset_ps.to_le_bytes());
        b.extend_from_slice(&self.dwell_us.to_le_bytes());
        for c in &self.counts {
            b.extend_from_slice(&c.to_le_bytes());
        }
        let crc = crc32fast::hash(&b);
        b.extend_from_slice(&crc.to_le_bytes());
        b
    }
}

/// The append-only histogram log.
pub struct HistogramLog {
    file: File,
    path: PathBuf,
    unsynced: usize,
    last_sync: Instant,
}

/// What reading a log back found.
#[derive(Debug)]
pub struct Recovered {
    /// The valid records, in file order.
    pub records: Vec<Record>,
    /// Length of the valid prefix, bytes.
    pub valid_bytes: u64,
    /// Bytes cut from the end (an incomplete or corrupted tail).
    pub discarded_bytes: u64,
}

fn u32_at(b: &[u8], i: usize) -> u32 {
    u32::from_le_bytes(b[i..i + 4].try_into().expect("4 bytes"))
}

impl HistogramLog {
    /// Creates a new, empty log (fails if one exists: a run is never overwritten).
    pub fn create(dir: &Path) -> io::Result<HistogramLog> {
        let path = dir.join(HISTOGRAM_LOG);
        let file = OpenOptions::new().create_new(true).append(true).open(&path)?;
        sync_dir(dir);
        Ok(HistogramLog {
            file,
            path,
            unsynced: 0,
            last_sync: Instant::now(),
        })
    }

    /// Reads a log back, cuts any invalid tail off the file, and opens it for
    /// appending. Later records for a pair already stored are dropped (cannot happen
    /// with this writer, but the reader does not trust the file).
    pub fn recover(dir: &Path) -> io::Result<(HistogramLog, Recovered)> {
        let path = dir.join(HISTOGRAM_LOG);
        if !path.exists() {
            return Ok((
                HistogramLog::create(dir)?,
                Recovered {
                    records: Vec::new(),
                    valid_bytes: 0,
                    discarded_bytes: 0,
                },
            ));
        }
        let got = read_log(dir)?;
        let file = OpenOptions::new().append(true).open(&path)?;
        if got.discarded_bytes > 0 {
            // Cut at the end of the valid prefix as read (not "length minus tail",
            // which a file that changed in between would make wrong).
            file.set_len(got.valid_bytes)?;
            file.sync_all()?;
        }
        Ok((
            HistogramLog {
                file,
                path,
                unsynced: 0,
                last_sync: Instant::now(),
            },
            got,
        ))
    }

    /// Appends one record; syncs every 32 records or 0.5 s, whichever comes first.
    pub fn append(&mut self, record: &Record) -> io::Result<()> {
        self.file.write_all(&record.encode())?;
        self.unsynced += 1;
        if self.unsynced >= SYNC_EVERY || self.last_sync.elapsed() >= SYNC_INTERVAL {
            self.sync()?;
        }
        Ok(())
    }

    /// Forces everything appended so far to disk.
    pub fn sync(&mut self) -> io::Result<()> {
        if self.unsynced > 0 {
            self.file.sync_data()?;
            self.unsynced = 0;
        }
        self.last_sync = Instant::now();
        Ok(())
    }

    /// The log's path.
    pub fn path(&self) -> &Path {
        &self.path
    }
}

impl Drop for HistogramLog {
    fn drop(&mut self) {
        let _ = self.sync();
    }
}

/// Reads a run's histogram log without changing it: the valid records, in file order,
/// up to the first incomplete or corrupted one. Later records for a pair already read
/// are dropped (this writer never produces them, but the reader does not trust the
/// file).
pub fn read_log(dir: &Path) -> io::Result<Recovered> {
    let path = dir.join(HISTOGRAM_LOG);
    let mut bytes = Vec::new();
    BufReader::new(File::open(&path)?).read_to_end(&mut bytes)?;
    Ok(parse_log(&bytes))
}

/// Decodes a histogram log held in memory: the records up to the first one that is
/// incomplete, fails its CRC, or carries impossible settings (no bins, more than
/// 2^20, a zero bin width). Any input gives an answer; nothing here panics.
pub fn parse_log(bytes: &[u8]) -> Recovered {
    let mut records = Vec::new();
    let mut seen = std::collections::HashSet::new();
    let mut at = 0usize;
    while bytes.len() - at >= HEADER + 4 {
        let b = &bytes[at..];
        if b[..4] != MAGIC {
            break;
        }
        let bins = u32_at(b, 12) as usize;
        if bins == 0 || bins > MAX_RECORD_BINS {
            break;
        }
        let len = HEADER + 4 * bins + 4;
        if b.len() < len || crc32fast::hash(&b[..len - 4]) != u32_at(b, len - 4) {
            break;
        }
        let flags = u32_at(b, 8);
        let rec = Record {
            pair: u32_at(b, 4),
            flags: HistogramFlags {
                overflow: flags & 1 != 0,
                saturated: flags & 2 != 0,
            },
            bin_width_ps: u32_at(b, 16),
            offset_ps: u32_at(b, 20),
            dwell_us: u64::from_le_bytes(b[24..32].try_into().expect("8 bytes")),
            counts: b[HEADER..len - 4]
                .chunks_exact(4)
                .map(|c| u32::from_le_bytes(c.try_into().expect("4")))
                .collect(),
        };
        if rec.bin_width_ps == 0 {
            break;
        }
        if seen.insert(rec.pair) {
            records.push(rec);
        }
        at += len;
    }
    Recovered {
        records,
        valid_bytes: at as u64,
        discarded_bytes: (bytes.len() - at) as u64,
    }
}

/// Most bins a stored record may have (the TDC protocol's own limit is 65,536).
const MAX_RECORD_BINS: usize = 1 << 20;

fn sync_dir(dir: &Path) {
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

/// Reads a UTF-8 text file of at most `limit` bytes; a larger file is refused before
/// anything is read, so a file that grew (or was replaced) cannot exhaust memory.
pub fn read_text_capped(path: &Path, limit: u64) -> io::Result<String> {
    let file = File::open(path)?;
    let len = file.metadata()?.len();
    if len > limit {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!(
                "{} is {len} bytes, more than the {limit} a text file here may have",
                path.display()
            ),
        ));
    }
    let mut text = String::with_capacity(len as usize);
    file.take(limit + 1).read_to_string(&mut text)?;
    if text.len() as u64 > limit {
        return Err(io::Error::new(
            io::ErrorKind::InvalidData,
            format!("{} grew past {limit} bytes while it was read", path.display()),
        ));
    }
    Ok(text)
}

/// Writes `bytes` to `path` atomically (temporary file, fsync, rename).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> io::Result<()> {
    let tmp = path.with_extension("tmp");
    {
        let mut f = File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
    }
    fs::rename(&tmp, path)?;
    if let Some(dir) = path.parent() {
        sync_dir(dir);
    }
    Ok(())
}

/// Where a run is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
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
}

impl RunInfo {
    /// Reads `run.json` from a run directory.
    pub fn load(dir: &Path) -> io::Result<RunInfo> {
        let text = fs::read_to_string(dir.join("run.json"))?;
        serde_json::from_str(&text).map_err(|e| io::Error::new(io::ErrorKind::InvalidData, e))
    }

    /// Writes `run.json` atomically.
    pub fn save(&self, dir: &Path) -> io::Result<()> {
        let text = serde_json::to_string_pretty(self).expect("run info serialises");
        write_atomic(&dir.join("run.json"), text.as_bytes())
    }
}

/// A fresh run id: plan name and UTC time, made unique within `root`.
pub fn new_run_dir(root: &Path, plan: &str) -> io::Result<PathBuf> {
    fs::create_dir_all(root)?;
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
            Ok(()) => return Ok(dir),
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

    fn rec(pair: u32) -> Record {
        Record {
            pair,
            flags: HistogramFlags {
                overflow: pair.is_multiple_of(2),
                saturated: false,
            },
            bin_width_ps: 16,
            offset_ps: 12_000,
            dwell_us: 1000,
            counts: (0..8).map(|k| k * pair).collect(),
        }
    }

    #[test]
    fn records_survive_a_reopen_and_a_torn_tail_is_cut() {
        let dir = tempfile::tempdir().unwrap();
        {
            let mut log = HistogramLog::create(dir.path()).unwrap();
            for p in 0..5 {
                log.append(&rec(p)).unwrap();
            }
        }
        // A torn write: half a record at the end.
        let half = rec(5).encode();
        let mut f = OpenOptions::new()
            .append(true)
            .open(dir.path().join(HISTOGRAM_LOG))
            .unwrap();
        f.write_all(&half[..half.len() / 2]).unwrap();
        drop(f);
        let (mut log, got) = HistogramLog::recover(dir.path()).unwrap();
        assert_eq!(got.records, (0..5).map(rec).collect::<Vec<_>>());
        assert_eq!(got.discarded_bytes, (half.len() / 2) as u64);
        log.append(&rec(5)).unwrap();
        drop(log);
        let (_, again) = HistogramLog::recover(dir.path()).unwrap();
        assert_eq!(again.records.len(), 6);
        assert_eq!(again.discarded_bytes, 0);
    }

    #[test]
    fn a_flipped_bit_ends_the_valid_prefix() {
        let dir = tempfile::tempdir().unwrap();
        {
            let mut log = HistogramLog::create(dir.path()).unwrap();
            for p in 0..3 {
                log.append(&rec(p)).unwrap();
            }
        }
        let path = dir.path().join(HISTOGRAM_LOG);
        let mut bytes = fs::read(&path).unwrap();
        let one = rec(0).encode().len();
        bytes[one + HEADER + 2] ^= 1; // inside record 1's counts
        fs::write(&path, &bytes).unwrap();
        let (_, got) = HistogramLog::recover(dir.path()).unwrap();
        assert_eq!(got.records.len(), 1);
        assert_eq!(got.discarded_bytes, (2 * one) as u64);
        assert!(
            HistogramLog::create(dir.path()).is_err(),
            "an existing log is never overwritten"
        );
    }

    #[test]
    fn dates_are_civil() {
        assert_eq!(civil_from_days(0), (1970, 1, 1));
        assert_eq!(civil_from_days(20_778), (2026, 11, 21));
    }
}

//! The daemon's metrics in the Prometheus text format (`GET /metrics`), through the
//! Prometheus project's Rust client (`prometheus-client`).
//!
//! Two kinds of value: those the daemon counts as things happen (stage durations,
//! reconstruction times, request latencies and errors: histograms and counters held
//! here and updated by the worker and the API), and those read off the service's state
//! at scrape time (emission, interlock, diffuser, count rates, reading age, pair rate,
//! queue length, runs per state: gauges set by [`Metrics::encode`]'s caller just
//! before encoding). Every name starts `periscope_`; `docs/metrics.md` lists them.
use std::sync::Mutex;

use prometheus_client::encoding::EncodeLabelSet;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{Histogram, exponential_buckets};
use prometheus_client::registry::Registry;

/// The `Content-Type` of `GET /metrics`.
pub const CONTENT_TYPE: &str = prometheus_client::encoding::prometheus_text::CONTENT_TYPE;

/// A stage's label.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct StageLabel {
    /// The stage's name (`los-scan`, `capture`, `reconstruction`, `reading`, ...).
    pub stage: String,
}

/// A run state's label.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct StateLabel {
    /// The state's name.
    pub state: String,
}

/// A request's labels: its method and route template (never the raw path, whose run
/// ids would make a series per run).
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RouteLabel {
    /// HTTP method.
    pub method: String,
    /// Route template (`/api/v1/runs/{id}`), or `unmatched`.
    pub route: String,
}

/// A failed request's labels.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct ErrorLabel {
    /// HTTP method.
    pub method: String,
    /// Route template, or `unmatched`.
    pub route: String,
    /// The status code.
    pub status: String,
}

/// A device's boolean reading's label.
#[derive(Clone, Debug, Hash, PartialEq, Eq, EncodeLabelSet)]
pub struct RateLabel {
    /// `sync` or `detector`.
    pub channel: String,
}

/// What the service's state says at scrape time.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Snapshot {
    /// Laser emission (from the last device reading), if read.
    pub emission: Option<bool>,
    /// Interlock closed, if read.
    pub interlock_closed: Option<bool>,
    /// Diffuser in, if read.
    pub diffuser_in: Option<bool>,
    /// Sync and detector count rates (counts/s), if read.
    pub rates: Option<(f64, f64)>,
    /// Age of the device reading (s).
    pub reading_age_s: Option<f64>,
    /// Seconds between the idle worker's device readings (`[api] status-interval-s`).
    pub status_interval_s: f64,
    /// Whether a run holds the instrument.
    pub busy: bool,
    /// Pairs per second of the running capture.
    pub pair_rate: f64,
    /// Photon counts per second of wall time in the running capture.
    pub capture_counts_rate: f64,
    /// Runs waiting in the queue.
    pub queue_length: usize,
    /// Whether the queue is locked.
    pub queue_locked: bool,
    /// Runs per state, from the catalogue.
    pub runs: Vec<(String, u64)>,
}

/// Buckets of the stage-duration histograms: doubling from 0.05 s to 29 h (22
/// buckets), since captures and reconstructions run for hours (until 2026-12-07 they
/// stopped at 27 min, and every longer stage fell in `+Inf`).
fn stage_buckets() -> impl Iterator<Item = f64> {
    exponential_buckets(0.05, 2.0, 22)
}

/// The daemon's metrics.
pub struct Metrics {
    registry: Registry,
    emission: Gauge,
    interlock: Gauge,
    diffuser: Gauge,
    reading_known: Gauge,
    rates: Family<RateLabel, Gauge<f64, std::sync::atomic::AtomicU64>>,
    reading_age: Gauge<f64, std::sync::atomic::AtomicU64>,
    status_interval: Gauge<f64, std::sync::atomic::AtomicU64>,
    busy: Gauge,
    pair_rate: Gauge<f64, std::sync::atomic::AtomicU64>,
    counts_rate: Gauge<f64, std::sync::atomic::AtomicU64>,
    queue_length: Gauge,
    queue_locked: Gauge,
    runs: Family<StateLabel, Gauge>,
    stages: Family<StageLabel, Histogram>,
    recon: Histogram,
    runs_finished: Family<StateLabel, Counter>,
    requests: Family<RouteLabel, Histogram>,
    errors: Family<ErrorLabel, Counter>,
    auth_failures: Counter,
    role_refusals: Counter,
    capture_pairs: Counter,
    capture_photons: Counter,
    /// Encoding is serialised (the families lock their maps; one scrape at a time is
    /// plenty).
    encoding: Mutex<()>,
}

impl Default for Metrics {
    fn default() -> Metrics {
        Metrics::new()
    }
}

impl Metrics {
    /// Registers every metric.
    pub fn new() -> Metrics {
        let mut registry = Registry::with_prefix("periscope");
        let m = Metrics {
            registry: Registry::default(),
            emission: Gauge::default(),
            interlock: Gauge::default(),
            diffuser: Gauge::default(),
            reading_known: Gauge::default(),
            rates: Family::default(),
            reading_age: Gauge::default(),
            status_interval: Gauge::default(),
            busy: Gauge::default(),
            pair_rate: Gauge::default(),
            counts_rate: Gauge::default(),
            queue_length: Gauge::default(),
            queue_locked: Gauge::default(),
            runs: Family::default(),
            stages: Family::new_with_constructor(|| Histogram::new(stage_buckets())),
            recon: Histogram::new(stage_buckets()),
            runs_finished: Family::default(),
            requests: Family::new_with_constructor(|| Histogram::new(exponential_buckets(0.0005, 2.0, 16))),
            errors: Family::default(),
            auth_failures: Counter::default(),
            role_refusals: Counter::default(),
            capture_pairs: Counter::default(),
            capture_photons: Counter::default(),
            encoding: Mutex::new(()),
        };
        registry.register(
            "laser_emission",
            "Laser emitting (1) or not (0), as the last device reading saw it; see periscope_reading_age_seconds",
            m.emission.clone(),
        );
        registry.register(
            "interlock_closed",
            "Interlock loop closed (1, emission allowed) or open (0), as last read",
            m.interlock.clone(),
        );
        registry.register(
            "diffuser_in",
            "LOS diffuser in the beam (1) or out (0), as last read",
            m.diffuser.clone(),
        );
        registry.register(
            "reading_valid",
            "Whether the last device reading succeeded (1) or failed or was never taken (0)",
            m.reading_known.clone(),
        );
        registry.register(
            "count_rate_hertz",
            "Histogrammer count rates as last read (sync after the divider, detector input)",
            m.rates.clone(),
        );
        registry.register(
            "reading_age_seconds",
            "Seconds since the devices were last read (a run holds them while it runs)",
            m.reading_age.clone(),
        );
        registry.register(
            "status_interval_seconds",
            "Seconds between the idle worker's device readings ([api] status-interval-s): the stale-reading alert's scale",
            m.status_interval.clone(),
        );
        registry.register(
            "instrument_busy",
            "A run holds the instrument (1) or not (0)",
            m.busy.clone(),
        );
        registry.register(
            "capture_pair_rate",
            "Pairs per second of the running capture (0 when none)",
            m.pair_rate.clone(),
        );
        registry.register(
            "capture_counts_rate",
            "Photon counts per second of wall time of the running capture",
            m.counts_rate.clone(),
        );
        registry.register(
            "queue_length",
            "Runs waiting in the queue",
            m.queue_length.clone(),
        );
        registry.register(
            "queue_locked",
            "The queue is locked for maintenance (1): no run starts",
            m.queue_locked.clone(),
        );
        registry.register("runs", "Runs in the catalogue per state", m.runs.clone());
        registry.register(
            "stage_duration_seconds",
            "Duration of each finished run stage",
            m.stages.clone(),
        );
        registry.register(
            "recon_duration_seconds",
            "Duration of each finished reconstruction stage",
            m.recon.clone(),
        );
        registry.register(
            "runs_finished",
            "Runs that ended, by the state they ended in, since the daemon started",
            m.runs_finished.clone(),
        );
        registry.register(
            "http_request_duration_seconds",
            "API request latency by method and route (time to the response's head)",
            m.requests.clone(),
        );
        registry.register(
            "http_errors",
            "API responses with status 400 or above, by method, route and status",
            m.errors.clone(),
        );
        registry.register(
            "auth_failures",
            "Requests refused for a missing, unknown, expired or revoked key",
            m.auth_failures.clone(),
        );
        registry.register(
            "role_refusals",
            "Requests refused because the key's role is below what they need (403 forbidden-role)",
            m.role_refusals.clone(),
        );
        registry.register(
            "capture_pairs",
            "Pairs measured and stored by every capture since the daemon started (rate() gives pairs per second over any window)",
            m.capture_pairs.clone(),
        );
        registry.register(
            "capture_photons",
            "Photon counts in the histograms of those pairs",
            m.capture_photons.clone(),
        );
        Metrics { registry, ..m }
    }

    /// A capture stored `pairs` more pairs, whose histograms hold `counts` photons.
    pub fn pairs_measured(&self, pairs: u64, counts: u64) {
        self.capture_pairs.inc_by(pairs);
        self.capture_photons.inc_by(counts);
    }

    /// A stage finished after `seconds`.
    pub fn stage_finished(&self, stage: &str, seconds: f64) {
        self.stages
            .get_or_create(&StageLabel { stage: stage.into() })
            .observe(seconds);
        if stage == "reconstruction" {
            self.recon.observe(seconds);
        }
    }

    /// A run ended in `state`.
    pub fn run_finished(&self, state: &str) {
        self.runs_finished
            .get_or_create(&StateLabel { state: state.into() })
            .inc();
    }

    /// An API request was answered with `status` after `seconds`.
    pub fn request(&self, method: &str, route: &str, status: u16, seconds: f64) {
        let label = RouteLabel {
            method: method.into(),
            route: route.into(),
        };
        self.requests.get_or_create(&label).observe(seconds);
        if status >= 400 {
            self.errors
                .get_or_create(&ErrorLabel {
                    method: label.method,
                    route: label.route,
                    status: status.to_string(),
                })
                .inc();
        }
    }

    /// A request was refused for its key (missing, unknown, expired, revoked).
    pub fn auth_failed(&self) {
        self.auth_failures.inc();
    }

    /// A request was refused for its key's role (a good key of too low a role: a
    /// dashboard holding an e-stop key reads the status every 2 s and is refused).
    pub fn role_refused(&self) {
        self.role_refusals.inc();
    }

    /// The metrics as Prometheus text, with the gauges set from `s`.
    pub fn encode(&self, s: &Snapshot) -> String {
        let _one = self.encoding.lock().unwrap_or_else(|p| p.into_inner());
        let flag = |g: &Gauge, v: Option<bool>| g.set(i64::from(v.unwrap_or(false)));
        flag(&self.emission, s.emission);
        flag(&self.interlock, s.interlock_closed);
        flag(&self.diffuser, s.diffuser_in);
        self.reading_known.set(i64::from(s.emission.is_some()));
        let (sync, det) = s.rates.unwrap_or((0.0, 0.0));
        self.rates
            .get_or_create(&RateLabel {
                channel: "sync".into(),
            })
            .set(sync);
        self.rates
            .get_or_create(&RateLabel {
                channel: "detector".into(),
            })
            .set(det);
        self.reading_age.set(s.reading_age_s.unwrap_or(f64::INFINITY));
        self.status_interval.set(s.status_interval_s);
        self.busy.set(i64::from(s.busy));
        self.pair_rate.set(s.pair_rate);
        self.counts_rate.set(s.capture_counts_rate);
        self.queue_length.set(s.queue_length as i64);
        self.queue_locked.set(i64::from(s.queue_locked));
        for state in crate::run_dir::STATE_NAMES.split(", ") {
            let n = s.runs.iter().find(|(st, _)| st == state).map_or(0, |(_, n)| *n);
            self.runs
                .get_or_create(&StateLabel { state: state.into() })
                .set(n as i64);
        }
        let mut out = String::new();
        prometheus_client::encoding::prometheus_text::encode(&mut out, &self.registry)
            .expect("writing to a String does not fail");
        out
    }
}

//! The calibration's scans on the instrument, through the device traits only: the
//! SPAD arm's first-bounce ranges of the flat target with the diffuser in, then, with
//! the diffuser out, the SPAD angles that see the laser's spot for a grid of laser
//! angles. The laser is on only while a scan measures; every exit, an error, a stop
//! request or a panic included, leaves it off and both arms parked
//! ([`Devices::make_safe`]), as a run's do.
use std::time::{Duration, Instant};

use periscope_drivers::{EmergencyOff, EmergencyPark, Error as _, ErrorKind, OpticalAngles, TdcConfig};
use periscope_recon::TimeAxis;

use super::model::Geometry;
use super::{CalibrateError, Measurements, RangeSample, Settings, SpotSample};
use crate::config::InstrumentConfig;
use crate::devices::{DeviceBackend, Devices, OpenError};
use crate::pipeline::{Control, panic_message, peak};

/// Fewest counts above the background at a spot that count as seeing it.
const MIN_SPOT_COUNTS: f64 = 50.0;
/// How finely a spot's edge is located, radians (2 µrad: 4 µm at 2 m).
const EDGE_TOLERANCE: f64 = 2e-6;
/// Chords through a spot: x, y, then x again (each refines the other's line).
const CHORDS: usize = 3;
/// Largest relative difference of a spot's widths along x and y before it counts as
/// partly hidden.
const MAX_WIDTH_MISMATCH: f64 = 0.2;

/// The instrument opened for calibration.
pub struct Calibrator {
    config: InstrumentConfig,
    devices: Devices,
    control: Control,
}

impl Calibrator {
    /// Opens the instrument's devices: `backend`, or the one `config` names (with the
    /// SPAD free-running, [`InstrumentConfig::with_spad_ungated`]) when `None`.
    /// `control` stops the scans at their next checkpoint and feeds the laser's
    /// keepalive as a run's does.
    pub fn open(
        config: &InstrumentConfig,
        backend: Option<&dyn DeviceBackend>,
        control: Control,
    ) -> Result<Calibrator, CalibrateError> {
        let own;
        let backend = match backend {
            Some(b) => b,
            None => {
                own = crate::devices::backend(&config.with_spad_ungated())?;
                own.as_ref()
            }
        };
        let mut devices = Devices::open(backend, &|| control.stopping()).map_err(|e| match e {
            OpenError::Interrupted => CalibrateError::Stopped,
            e => CalibrateError::Open(e),
        })?;
        crate::signals::register_laser(devices.laser.emergency_off());
        devices.laser.watch_progress(control.progress(config.laser.stall));
        Ok(Calibrator {
            config: config.clone(),
            devices,
            control,
        })
    }

    /// Switches this calibration's laser off from any thread (signals, e-stop).
    pub fn emergency_off(&self) -> EmergencyOff {
        self.devices.laser.emergency_off()
    }

    /// Parks this calibration's arms (laser arm, SPAD arm) from any thread (a forced
    /// exit after a signal).
    pub fn emergency_park(&self) -> [EmergencyPark; 2] {
        [
            self.devices.laser_arm.emergency_park(),
            self.devices.spad.emergency_park(),
        ]
    }

    /// Runs both scans, then makes the instrument safe whatever happened.
    pub fn measure(mut self, settings: &Settings) -> Result<Measurements, CalibrateError> {
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| self.scans(settings)))
            .unwrap_or_else(|payload| {
                Err(CalibrateError::Panicked {
                    message: panic_message(payload.as_ref()),
                })
            });
        let safe = self.devices.make_safe();
        if let Err(e) = &safe {
            tracing::error!("could not make the instrument safe: {e}");
        }
        let measured = result?;
        safe?;
        Ok(measured)
    }

    fn scans(&mut self, settings: &Settings) -> Result<Measurements, CalibrateError> {
        let (ranges, tried) = self.range_scan(settings)?;
        super::enough_ranges(ranges.len(), tried)?;
        let nominal = super::nominal_geometry(&self.config, settings, &ranges)?;
        let spots = self.spot_scan(settings, &nominal)?;
        Ok(Measurements {
            ranges,
            range_angles: tried,
            spots,
        })
    }

    fn checkpoint(&self) -> Result<(), CalibrateError> {
        if self.control.stopping() {
            Err(CalibrateError::Stopped)
        } else {
            Ok(())
        }
    }

    fn settle(&self) -> Duration {
        (self.config.laser_arm.settle.max(self.config.spad_arm.settle) * 20).max(Duration::from_millis(200))
    }

    fn configure(&mut self, dwell: Duration) -> Result<(), CalibrateError> {
        let tdc = &self.config.tdc;
        self.devices.tdc.configure(&TdcConfig {
            bin_width: tdc.bin_width,
            bins: tdc.bins,
            offset: tdc.offset,
            sync_divider: tdc.sync_divider,
            acquisition: dwell,
        })?;
        Ok(())
    }

    /// Emission on to measure; an emergency off latched earlier refuses it.
    fn laser_on(&mut self) -> Result<(), CalibrateError> {
        self.checkpoint()?;
        // The histogrammer must answer before the laser goes on.
        self.devices.tdc.status()?;
        match self.devices.laser.set_emission(true) {
            Err(e) if e.kind() == ErrorKind::Interrupted => return Err(CalibrateError::Stopped),
            r => r?,
        }
        // As a run's: the sync the counter reads once its rate meter shows it, with
        // the laser still on, before anything is measured.
        let control = self.control.clone();
        let wait = |d: Duration| {
            let until = Instant::now() + d;
            while Instant::now() < until {
                if control.stopping() {
                    return Err(CalibrateError::Stopped);
                }
                std::thread::sleep((until - Instant::now()).min(Duration::from_millis(20)));
            }
            Ok(())
        };
        let latency = self.devices.tdc.rate_latency();
        let after = self.devices.tdc.sync_after_divider();
        wait(latency)?;
        self.watch_laser()?;
        let first = self.devices.tdc.status()?.rates.sync;
        if self.config.sync_fault(first, after).is_none() {
            return Ok(());
        }
        // Read again after the meter's latency before it is believed: a counter
        // reopened or reconfigured meanwhile reads its old rate, or none, that long.
        wait(latency)?;
        self.watch_laser()?;
        let second = self.devices.tdc.status()?.rates.sync;
        match self.config.sync_fault(second, after) {
            Some(fault) => Err(CalibrateError::Sync(fault)),
            None => Ok(()),
        }
    }

    /// Fails if emission stopped behind our back (interlock, watchdog).
    fn watch_laser(&mut self) -> Result<(), CalibrateError> {
        let state = self.devices.laser.laser_state()?;
        if !state.interlock_closed {
            return Err(CalibrateError::LaserLost("the interlock opened".into()));
        }
        if !state.emission {
            return Err(CalibrateError::LaserLost(
                "emission stopped (the controller's watchdog or another client)".into(),
            ));
        }
        Ok(())
    }

    fn acquire(&mut self) -> Result<Vec<u32>, CalibrateError> {
        let control = self.control.clone();
        match self.devices.tdc.acquire_until(&|| control.stopping()) {
            Ok(h) => Ok(h.counts),
            Err(e) if e.kind() == ErrorKind::Interrupted => Err(CalibrateError::Stopped),
            Err(e) => Err(e.into()),
        }
    }

    /// The SPAD sweeps an N × N grid over the central `span` of its limits under the
    /// diffused laser; each return's path comes from the centroid of its peak.
    fn range_scan(&mut self, settings: &Settings) -> Result<(Vec<RangeSample>, usize), CalibrateError> {
        crate::logging::notice(&format!(
            "calibration 1/2: first-bounce ranges at {n} × {n} SPAD angles (diffuser in)",
            n = settings.grid
        ));
        self.configure(settings.range_dwell)?;
        self.devices.laser_arm.park()?;
        self.devices.laser_arm.wait_settled(Duration::from_secs(2))?;
        self.devices.laser.set_diffuser(true)?;
        self.laser_on()?;
        let grid = grid(self.config.spad_arm.limits, settings.span, settings.grid);
        let axis = TimeAxis::of_tdc(
            self.config.tdc.offset,
            self.config.tdc.bin_width,
            self.config.tdc.bins as usize,
            self.config.tdc.system_delay,
        );
        let sigma_bins =
            self.config.spad.jitter_fwhm / (8.0 * std::f64::consts::LN_2).sqrt() / self.config.tdc.bin_width;
        let dwell = settings.range_dwell.as_secs_f64();
        let settle = self.settle();
        let mut out = Vec::new();
        for (i, &angles) in grid.iter().enumerate() {
            self.checkpoint()?;
            self.devices.spad.move_settled(angles, settle)?;
            let counts = self.acquire()?;
            let counts = crate::record::corrected_counts(&counts, dwell, &self.config);
            if let Some(b) = centroid_peak(&counts, sigma_bins) {
                out.push(RangeSample {
                    spad: angles,
                    path: axis.centre(b),
                });
            }
            if (i + 1) % settings.grid == 0 {
                self.watch_laser()?;
            }
        }
        self.devices.laser.set_emission(false)?;
        self.devices.laser.set_diffuser(false)?;
        Ok((out, grid.len()))
    }

    /// For each laser angle of a grid, finds the SPAD angles that see the laser's spot:
    /// a search outwards from where `nominal` says it is, then chords through the spot
    /// at half its height, whose midpoints are its centre (the spot's profile is
    /// symmetric about its centre along any line on the target). A spot partly hidden
    /// from the SPAD is left out; the fit refuses fewer than [`super::MIN_SPOTS`].
    fn spot_scan(
        &mut self,
        settings: &Settings,
        nominal: &Geometry,
    ) -> Result<Vec<SpotSample>, CalibrateError> {
        let lasers = grid(self.config.laser_arm.limits, settings.spot_span, settings.spots);
        crate::logging::notice(&format!(
            "calibration 2/2: the laser spot at {} laser angles (diffuser out)",
            lasers.len()
        ));
        self.configure(settings.spot_dwell)?;
        self.devices.laser.set_diffuser(false)?;
        // The background (dark and ambient counts) with the laser off.
        self.devices
            .spad
            .move_settled(OpticalAngles { x: 0.0, y: 0.0 }, self.settle())?;
        let background = total(&self.acquire()?);
        self.laser_on()?;
        let mut out = Vec::new();
        for &laser in &lasers {
            self.checkpoint()?;
            self.devices.laser_arm.move_settled(laser, self.settle())?;
            let expected = nominal.spot(laser).ok_or(CalibrateError::NoSpot {
                laser,
                why: "the configured poses put this spot off the target or behind the SPAD arm",
            })?;
            match self.find_spot(settings, expected, background, laser)? {
                Some(spad) => out.push(SpotSample { laser, spad }),
                None => crate::logging::notice(&format!(
                    "  the spot at laser angles ({:.2}°, {:.2}°) is cut (partly hidden from the SPAD, or at the SPAD arm's limits): left out",
                    laser.x.to_degrees(),
                    laser.y.to_degrees()
                )),
            }
            self.watch_laser()?;
        }
        self.devices.laser.set_emission(false)?;
        Ok(out)
    }

    /// Total counts at SPAD angles `a` (0 outside the SPAD arm's limits).
    fn counts_at(&mut self, a: OpticalAngles) -> Result<f64, CalibrateError> {
        if !self.config.spad_arm.limits.contains(a) {
            return Ok(0.0);
        }
        self.checkpoint()?;
        let settle = self.settle();
        self.devices.spad.move_settled(a, settle)?;
        Ok(total(&self.acquire()?))
    }

    fn find_spot(
        &mut self,
        settings: &Settings,
        expected: OpticalAngles,
        background: f64,
        laser: OpticalAngles,
    ) -> Result<Option<OpticalAngles>, CalibrateError> {
        let floor = background + MIN_SPOT_COUNTS.max(10.0 * background.sqrt());
        // Outwards from the expected angles, nearest first, one step at a time.
        let step = settings.spot_step;
        let reach = (settings.spot_search / step).ceil() as i64;
        let mut offsets: Vec<(i64, i64)> = (-reach..=reach)
            .flat_map(|i| (-reach..=reach).map(move |j| (i, j)))
            .filter(|(i, j)| i * i + j * j <= reach * reach)
            .collect();
        offsets.sort_by_key(|(i, j)| i * i + j * j);
        let mut found = None;
        for (i, j) in offsets {
            let a = OpticalAngles {
                x: expected.x + i as f64 * step,
                y: expected.y + j as f64 * step,
            };
            let c = self.counts_at(a)?;
            if c > floor {
                found = Some((a, c));
                break;
            }
        }
        let limits = self.config.spad_arm.limits;
        let (mut centre, mut top) = found.ok_or(if limits.contains(expected) {
            CalibrateError::NoSpot {
                laser,
                why: "no SPAD angle within the search saw it: check that the SPAD is not gated \
                      and that the configured poses are within a degree or two of the truth",
            }
        } else {
            CalibrateError::SpotOutsideLimits {
                laser,
                expected,
                limits,
            }
        })?;
        // The brightest of the neighbours, so the chords run through the spot's body.
        for _ in 0..8 {
            let mut best = (centre, top);
            for (i, j) in [(1, 0), (-1, 0), (0, 1), (0, -1)] {
                let a = OpticalAngles {
                    x: centre.x + i as f64 * step / 2.0,
                    y: centre.y + j as f64 * step / 2.0,
                };
                let c = self.counts_at(a)?;
                if c > best.1 {
                    best = (a, c);
                }
            }
            if best.0 == centre {
                break;
            }
            (centre, top) = best;
        }
        let level = background + 0.5 * (top - background);
        let mut widths = [0.0; 2];
        for chord in 0..CHORDS {
            let along_x = chord % 2 == 0;
            let mut ends = [0.0; 2];
            for (k, sign) in [-1.0, 1.0].into_iter().enumerate() {
                ends[k] = match self.edge(centre, along_x, sign, step / 2.0, level, settings.spot_search)? {
                    Edge::At(e) => e,
                    // A spot the limits cut has no true chord there: left out, as a
                    // spot cut by something in front of the SPAD is.
                    Edge::AtLimit => return Ok(None),
                    Edge::NotFound => {
                        return Err(CalibrateError::NoSpot {
                            laser,
                            why: "its edge was not found within the search: is stray light saturating the SPAD?",
                        });
                    }
                };
            }
            let mid = 0.5 * (ends[0] + ends[1]);
            widths[usize::from(!along_x)] = ends[1] - ends[0];
            if along_x {
                centre.x = mid;
            } else {
                centre.y = mid;
            }
        }
        // A round spot is about as wide along x as along y (the projection changes
        // that by a few per cent); one that is not is cut by something between it and
        // the SPAD, and its chords' midpoints are not its centre.
        let [wx, wy] = widths;
        if (wx - wy).abs() > MAX_WIDTH_MISMATCH * wx.max(wy) {
            return Ok(None);
        }
        Ok(Some(centre))
    }

    /// Where the counts fall below `level` going from `from` (above it) along x or y
    /// in direction `sign`: stepping out by `step`, then bisecting; [`Edge::NotFound`]
    /// if they do not within `reach`, [`Edge::AtLimit`] if the SPAD arm's limits come
    /// first.
    fn edge(
        &mut self,
        from: OpticalAngles,
        along_x: bool,
        sign: f64,
        step: f64,
        level: f64,
        reach: f64,
    ) -> Result<Edge, CalibrateError> {
        let at = |t: f64| {
            if along_x {
                OpticalAngles { x: t, y: from.y }
            } else {
                OpticalAngles { x: from.x, y: t }
            }
        };
        let start = if along_x { from.x } else { from.y };
        let (mut inside, mut outside) = (start, start);
        loop {
            outside += sign * step;
            if (outside - start).abs() > reach {
                return Ok(Edge::NotFound);
            }
            // Past the SPAD arm's limits nothing is measured: an edge found there is
            // the limit's, not the spot's.
            if !self.config.spad_arm.limits.contains(at(outside)) {
                return Ok(Edge::AtLimit);
            }
            if self.counts_at(at(outside))? < level {
                break;
            }
            inside = outside;
        }
        while (outside - inside).abs() > EDGE_TOLERANCE {
            let mid = 0.5 * (inside + outside);
            if self.counts_at(at(mid))? < level {
                outside = mid;
            } else {
                inside = mid;
            }
        }
        Ok(Edge::At(0.5 * (inside + outside)))
    }
}

/// What [`Calibrator::edge`] found.
enum Edge {
    /// The edge, an angle along the chord.
    At(f64),
    /// The counts stay above the level within the search.
    NotFound,
    /// The chord reaches the SPAD arm's limits first: the spot is cut there.
    AtLimit,
}

/// An N × N serpentine grid over the central `span` (a fraction) of `limits`.
fn grid(limits: periscope_drivers::AngleLimits, span: f64, n: usize) -> Vec<OpticalAngles> {
    let at = |r: [f64; 2], i: usize| {
        let (c, h) = (0.5 * (r[0] + r[1]), 0.5 * (r[1] - r[0]) * span);
        if n == 1 {
            c
        } else {
            c - h + 2.0 * h * i as f64 / (n - 1) as f64
        }
    };
    let mut out = Vec::with_capacity(n * n);
    for iy in 0..n {
        for jx in 0..n {
            let ix = if iy % 2 == 0 { jx } else { n - 1 - jx };
            out.push(OpticalAngles {
                x: at(limits.x, ix),
                y: at(limits.y, iy),
            });
        }
    }
    out
}

fn total(counts: &[u32]) -> f64 {
    counts.iter().map(|&c| f64::from(c)).sum()
}

/// The return's position as a fractional bin (bin k's centre reads k, as
/// [`peak`]'s): the background-subtracted centroid over the peak ± 4σ of the timing
/// jitter (plus a bin). Unlike the parabola through three bins, whose bias swings with
/// where the return falls inside its bin, the centroid keeps the mean arrival time.
/// `None` when no peak stands out, or when the return is cut by either end of the
/// histogram (its centroid would lie early or late by the part cut off).
pub(crate) fn centroid_peak(counts: &[f32], sigma_bins: f64) -> Option<f64> {
    let (b, _) = peak(counts)?;
    let mut sorted: Vec<f32> = counts.iter().copied().filter(|c| c.is_finite()).collect();
    sorted.sort_by(f32::total_cmp);
    let background = f64::from(*sorted.get(sorted.len() / 2)?);
    let half = (4.0 * sigma_bins).ceil() as isize + 1;
    let centre = b.round() as isize;
    if centre - half < 0 || centre + half >= counts.len() as isize {
        return None;
    }
    let (mut mass, mut moment) = (0.0, 0.0);
    for k in centre - half..=centre + half {
        let c = f64::from(counts[k as usize]) - background;
        mass += c;
        moment += c * k as f64;
    }
    let b = moment / mass;
    (mass > 0.0 && b.is_finite()).then_some(b)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_centroid_keeps_a_return_between_bins() {
        // A Gaussian return of σ = 1.6 bins centred at 40.3 over a flat background.
        for mu in [40.0, 40.3, 40.5, 40.8] {
            let counts: Vec<f32> = (0..128)
                .map(|k| {
                    let z = (k as f64 - mu) / 1.6;
                    (5.0 + 1000.0 * (-0.5 * z * z).exp()) as f32
                })
                .collect();
            let b = centroid_peak(&counts, 1.6).unwrap();
            assert!((b - mu).abs() < 1e-3, "{mu}: {b}");
        }
        assert_eq!(centroid_peak(&[0.0f32; 16], 1.0), None);
        // A return cut by the window's end is not a range: its centroid would lie early.
        let cut: Vec<f32> = (0..128)
            .map(|k| {
                let z = (k as f64 - 126.0) / 1.6;
                (5.0 + 1000.0 * (-0.5 * z * z).exp()) as f32
            })
            .collect();
        assert_eq!(centroid_peak(&cut, 1.6), None);
        assert_eq!(
            centroid_peak(&cut[..120], 1.6),
            None,
            "a rising edge at the last bin"
        );
    }

    #[test]
    fn the_grid_spans_the_centre_of_the_limits() {
        let limits = periscope_drivers::AngleLimits {
            x: [-0.2, 0.2],
            y: [-0.1, 0.3],
        };
        let g = grid(limits, 0.5, 3);
        assert_eq!(g.len(), 9);
        assert!((g[0].x + 0.1).abs() < 1e-12 && (g[0].y - 0.0).abs() < 1e-12);
        // Serpentine: the second row runs back.
        assert!((g[3].x - 0.1).abs() < 1e-12 && (g[3].y - 0.1).abs() < 1e-12);
    }
}

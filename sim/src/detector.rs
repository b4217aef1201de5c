//! The detector model: photon budget, timing jitter, dark counts and ambient light,
//! gating, pile-up and dead time, and Poisson noise. Turns the transport's photon
//! arrivals (per pulse, in TDC time) into the histogram a TDC would report.
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution, Poisson};

/// Speed of light, m/s.
pub const C0: f64 = 299_792_458.0;

/// Photon energy constant h·c, J·m.
const HC: f64 = 6.626_070_15e-34 * C0;

/// Oversampling of the arrival histogram before the jitter convolution.
pub(crate) const OVERSAMPLE: usize = 4;

/// Everything that sets what a pixel's histogram looks like besides the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Detector {
    /// TDC bin width, seconds.
    pub bin_width: f64,
    /// Number of bins.
    pub bins: usize,
    /// TDC time of the start of bin 0, seconds.
    pub offset: f64,
    /// Fixed delay added to every arrival (cables, electronics), seconds.
    pub system_delay: f64,
    /// Combined timing jitter (laser, SPAD, TDC), full width at half maximum, seconds.
    pub jitter_fwhm: f64,
    /// SPAD photon detection efficiency, 0..1.
    pub efficiency: f64,
    /// Dark count rate, Hz.
    pub dark_count_rate: f64,
    /// Ambient background count rate at the detector (already detected), Hz.
    pub ambient_rate: f64,
    /// Dead time, seconds (non-paralysable, applied with pile-up).
    pub dead_time: f64,
    /// Laser average power, W.
    pub laser_power: f64,
    /// Laser wavelength, m.
    pub wavelength: f64,
    /// Pulse repetition rate, Hz.
    pub repetition_rate: f64,
    /// Laser pulses a TDC cycle spans (the sync divider): the counter times each
    /// photon from the last of every `sync_divider` syncs, so a cycle's window holds
    /// the light of each of its pulses, the k-th `k / repetition_rate` later. 1: one.
    pub sync_divider: u32,
    /// Collection aperture area, m².
    pub aperture_area: f64,
    /// Area of the relay spot the SPAD sees (and the laser spot's size), m².
    pub spot_area: f64,
    /// Solid angle the LOS diffuser spreads the laser into, sr.
    pub diffuser_solid_angle: f64,
    /// Overall optical transmission (filters, lenses, galvo mirrors), 0..1.
    pub transmission: f64,
    /// Gate: photons arriving before the pair's direct path plus this path-length
    /// margin (metres) are blocked, for each pulse of a cycle
    /// ([`Detector::expected_counts`]); `None` = no gating.
    pub gate_margin: Option<f64>,
    /// Model pile-up (Coates) and dead time.
    pub pile_up: bool,
}

impl Detector {
    /// The default simulated instrument's detector (`configs/instrument/sim.toml`:
    /// 400 mW at 532 nm and 10 MHz, SPAD efficiency 0.3, 60 ps jitter, 10 mm aperture,
    /// 5 mm spots, 25° diffuser, gated 10 cm past the direct path), with 512 bins of
    /// 16 ps from 12 ns. For tests and benchmarks that need a realistic detector and
    /// change only what they study.
    pub fn example() -> Detector {
        let half_angle = 25f64.to_radians();
        Detector {
            bin_width: 16e-12,
            bins: 512,
            offset: 12e-9,
            system_delay: 0.0,
            jitter_fwhm: 60e-12,
            efficiency: 0.3,
            dark_count_rate: 100.0,
            ambient_rate: 2000.0,
            dead_time: 50e-9,
            laser_power: 0.4,
            wavelength: 532e-9,
            repetition_rate: 10e6,
            sync_divider: 1,
            aperture_area: std::f64::consts::PI * 0.005f64.powi(2),
            spot_area: std::f64::consts::PI * 0.0025f64.powi(2),
            diffuser_solid_angle: 2.0 * std::f64::consts::PI * (1.0 - half_angle.cos()),
            transmission: 0.5,
            gate_margin: Some(0.1),
            pile_up: false,
        }
    }

    /// Photons per laser pulse.
    pub fn photons_per_pulse(&self) -> f64 {
        self.laser_power / self.repetition_rate / (HC / self.wavelength)
    }

    /// TDC cycles (syncs after the divider) during `dwell` seconds.
    pub fn cycles(&self, dwell: f64) -> f64 {
        dwell * self.repetition_rate / f64::from(self.sync_divider.max(1))
    }

    /// Fractional bin of an arrival with total path length `path` (metres), from the
    /// cycle's first pulse.
    pub fn bin_of_path(&self, path: f64) -> f64 {
        (path / C0 + self.system_delay - self.offset) / self.bin_width
    }

    /// The fractional bins an arrival of path `path` lands in within one cycle: one a
    /// pulse of the cycle, a pulse period apart ([`Detector::sync_divider`]).
    pub fn bins_of_path(&self, path: f64) -> impl Iterator<Item = f64> {
        let (first, period) = (
            self.bin_of_path(path),
            1.0 / self.repetition_rate / self.bin_width,
        );
        (0..self.sync_divider.max(1)).map(move |k| first + f64::from(k) * period)
    }

    /// Whether the SPAD's dead time after a detection in one cycle's window can reach
    /// into the next cycle's window: the dead time longer than the cycle's period less
    /// the window's span. Otherwise a first-photon TDC loses nothing to it beyond what
    /// Coates' model counts (one detection a cycle), and `sim.toml`'s 50 ns dead time
    /// against a 100 ns cycle and a 16 ns window loses nothing.
    pub fn dead_time_reaches_next_cycle(&self) -> bool {
        let period = f64::from(self.sync_divider.max(1)) / self.repetition_rate;
        self.dead_time > period - self.bins as f64 * self.bin_width
    }

    /// The fraction of each of `len` bins the gate leaves open, the gate opening at
    /// `gate_bin` for the cycle's first pulse. A gated SPAD is gated on every laser
    /// pulse, not once a cycle: with a sync divider of N the k-th pulse's light comes k
    /// periods later ([`Detector::bins_of_path`]), and so does its gate. The first
    /// pulse's gate is shut from the window's start to `gate_bin`; each later pulse's
    /// the same span k periods on, reaching back to the pair's direct path (`gate_bin`
    /// less the margin) where that lies before the window's start, so that every
    /// pulse's direct return is blocked. Until 2026-12-07 the gate opened once a cycle,
    /// and with a window longer than a period the later pulses' direct returns passed
    /// ungated.
    fn gate_open(&self, gate_bin: f64, len: usize) -> Vec<f64> {
        let bins = len as f64;
        let period = 1.0 / self.repetition_rate / self.bin_width;
        let direct = gate_bin - self.gate_margin.map_or(0.0, |m| m / C0 / self.bin_width);
        // The shut spans in bins, in order, merged where they overlap (a gate that
        // opens more than a period into its pulse's span is shut until the next opens).
        let mut shut: Vec<(f64, f64)> = Vec::new();
        for k in 0..self.sync_divider.max(1) {
            let shift = if k == 0 { 0.0 } else { f64::from(k) * period };
            let (lo, hi) = (shift + direct.min(0.0), shift + gate_bin);
            if !(lo < bins) {
                break;
            }
            match shut.last_mut() {
                Some(last) if lo <= last.1 => last.1 = last.1.max(hi),
                _ => shut.push((lo, hi)),
            }
        }
        let mut open = vec![1.0; len];
        for (lo, hi) in shut {
            let first = lo.max(0.0) as usize;
            for (b, o) in open.iter_mut().enumerate().skip(first) {
                let b = b as f64;
                if b >= hi {
                    break;
                }
                // The part of the bin [b, b + 1) the span covers.
                *o -= (hi.min(b + 1.0) - lo.max(b)).max(0.0);
            }
        }
        open.iter_mut().for_each(|o| *o = f64::clamp(*o, 0.0, 1.0));
        open
    }

    /// Jitter standard deviation in bins.
    fn sigma_bins(&self) -> f64 {
        self.jitter_fwhm / (2.0 * (2.0 * std::f64::consts::LN_2).sqrt()) / self.bin_width
    }

    /// Convolves an oversampled arrival histogram (photons per pulse, `OVERSAMPLE`
    /// sub-bins per bin) with the Gaussian jitter integrated over each output bin.
    pub(crate) fn blur(&self, fine: &[f64]) -> Vec<f64> {
        let mut out = vec![0.0; self.bins];
        let sigma = self.sigma_bins().max(1e-6);
        let reach = (5.0 * sigma).ceil() as isize + 1;
        // Kernel weight for a sub-bin centred at offset `d` (bins) from an output bin's
        // lower edge: Φ((1 − d)/σ) − Φ(−d/σ).
        let cdf = |z: f64| 0.5 * libm::erfc(-z / std::f64::consts::SQRT_2);
        let taps: Vec<f64> = (-(reach * OVERSAMPLE as isize)..=(reach * OVERSAMPLE as isize))
            .map(|k| {
                let d = (k as f64 + 0.5) / OVERSAMPLE as f64;
                cdf((1.0 - d) / sigma) - cdf(-d / sigma)
            })
            .collect();
        let half = reach * OVERSAMPLE as isize;
        for (j, &v) in fine.iter().enumerate() {
            if v == 0.0 {
                continue;
            }
            // Sub-bin j sits at d = j/OVERSAMPLE − b (+ half a sub-bin) from bin b.
            let sub = j as isize;
            let b_lo = (sub - half).div_euclid(OVERSAMPLE as isize).max(0);
            let b_hi = ((sub + half).div_euclid(OVERSAMPLE as isize) + 1).min(self.bins as isize - 1);
            for b in b_lo..=b_hi {
                let k = sub - b * OVERSAMPLE as isize;
                if let Some(w) = taps.get((k + half) as usize) {
                    out[b as usize] += v * w;
                }
            }
        }
        out
    }

    /// Expected counts per bin over `dwell`, from the signal photons per pulse arriving
    /// in each bin (before efficiency) and the bin where the gate opens for the cycle's
    /// first pulse. The gate shuts and opens again for each later pulse of the cycle,
    /// a pulse period on ([`Detector::sync_divider`]).
    pub fn expected_counts(&self, signal: &[f64], gate_bin: Option<f64>, dwell: f64) -> Vec<f64> {
        self.expected_counts_after(signal, 0.0, gate_bin, dwell)
    }

    /// Detections a cycle expects between its sync and its window's start, which take
    /// the cycle's one recorded detection (Coates) before the window opens: the dark
    /// and ambient counts over that time (`offset` after the sync), and `before`, the
    /// signal photons a cycle that arrive then (before efficiency: an ungated SPAD's
    /// confocal direct return, with the window set past it). A gate shut until
    /// `gate_bin` blocks them, but for the noise after it opens where that is before
    /// the window.
    fn before_window(&self, before: f64, gate_bin: Option<f64>) -> f64 {
        let noise_rate = self.dark_count_rate + self.ambient_rate;
        let since_sync = self.offset.max(0.0);
        match gate_bin {
            None => self.efficiency * self.transmission * before.max(0.0) + noise_rate * since_sync,
            Some(g) => noise_rate * (-g * self.bin_width).clamp(0.0, since_sync),
        }
    }

    /// [`Detector::expected_counts`] with `before` signal photons a cycle arriving
    /// between the sync and the window's start (`Detector::before_window`): with
    /// pile-up on, a detection then is the cycle's one, and the window records nothing
    /// that cycle, so each bin is scaled by the chance that none came. Until 2026-12-07
    /// arrivals before the window were dropped, and an ungated SPAD whose window was
    /// set past the confocal direct return showed clean hidden returns where a real
    /// one is blinded.
    pub fn expected_counts_after(
        &self,
        signal: &[f64],
        before: f64,
        gate_bin: Option<f64>,
        dwell: f64,
    ) -> Vec<f64> {
        let noise = (self.dark_count_rate + self.ambient_rate) * self.bin_width;
        let mut rate: Vec<f64> = signal
            .iter()
            .map(|s| self.efficiency * self.transmission * s + noise)
            .collect();
        if let Some(g) = gate_bin {
            let open = self.gate_open(g, rate.len());
            for (r, fraction) in rate.iter_mut().zip(open) {
                *r *= fraction;
            }
        }
        let pulses = self.cycles(dwell);
        if !self.pile_up {
            return rate.iter().map(|r| r * pulses).collect();
        }
        // Coates: the first detection in a cycle is the one recorded, those before the
        // window included.
        let mut survive = (-self.before_window(before, gate_bin)).exp();
        let mut out: Vec<f64> = rate
            .iter()
            .map(|&r| {
                let p = survive * (1.0 - (-r).exp());
                survive *= (-r).exp();
                p * pulses
            })
            .collect();
        // Non-paralysable dead time on the total count rate, where it reaches from one
        // cycle's window into the next (else Coates has counted all it loses).
        if self.dead_time_reaches_next_cycle() {
            let total_rate: f64 = out.iter().sum::<f64>() / dwell.max(1e-12);
            let loss = 1.0 / (1.0 + total_rate * self.dead_time);
            out.iter_mut().for_each(|v| *v *= loss);
        }
        out
    }
}

/// Below this mean, draws use sequential inversion (one uniform, about λ + 1 steps);
/// most histogram bins hold a small fraction of a count, where building a general
/// Poisson sampler per bin would cost far more than the draw.
const SMALL_MEAN: f64 = 10.0;

/// One Poisson(λ) draw by inversion of the CDF, for small λ.
fn small_poisson(l: f64, p0: f64, rng: &mut ChaCha8Rng) -> u32 {
    use rand::Rng;
    let u: f64 = rng.random();
    let mut p = p0;
    let mut cdf = p;
    let mut k = 0u32;
    // The loop ends by k ≈ λ + 10√λ + 20 in all but floating-point pathologies; the
    // bound only guards against rounding leaving `cdf` just below `u`.
    while u > cdf && k < 200 {
        k += 1;
        p *= l / f64::from(k);
        cdf += p;
    }
    k
}

/// Poisson draws of `expected`, reproducible from `seed` and `stream` (e.g. the pair
/// index), independent of thread count. A mean a 32-bit bin counter cannot hold
/// (`u32::MAX` or more, infinite included) gives a full counter, `u32::MAX`, which the
/// devices flag as overflow, as they do a draw that reaches it; until 2026-12-07 a mean
/// beyond the Poisson sampler's range (1.8·10¹⁹) gave 0 counts and no flag.
pub fn sample_counts(expected: &[f64], seed: u64, stream: u64) -> Vec<u32> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    rng.set_stream(stream);
    // exp(−λ) of the previous bin: background bins share one mean.
    let mut last = (f64::NAN, 0.0);
    expected
        .iter()
        .map(|&l| {
            if !(l > 0.0) {
                0
            } else if l >= f64::from(u32::MAX) {
                u32::MAX
            } else if l < SMALL_MEAN {
                if l != last.0 {
                    last = (l, (-l).exp());
                }
                small_poisson(l, last.1, &mut rng)
            } else {
                // Below u32::MAX no Poisson::new fails; were it to, the counter is
                // reported full rather than empty.
                Poisson::new(l).map_or(u32::MAX, |p| p.sample(&mut rng).min(u32::MAX as f64) as u32)
            }
        })
        .collect()
}

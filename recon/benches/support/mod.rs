//! Helpers the recon benchmarks share: the time of criterion's last sample, the
//! process's peak memory and the arithmetic rate against the CPU's f32 FMA peak.
use std::cell::Cell;
use std::hint::black_box;
use std::time::{Duration, Instant};

use periscope_recon::gpu::{Compute, ComputeDevice};

/// Times a routine for `Bencher::iter_custom` and keeps the time per iteration of the
/// last sample criterion took, for the figures a bench prints besides criterion's own
/// (the share of the FMA peak). Criterion's median is still the figure to quote.
#[derive(Default)]
pub(crate) struct LastSample(Cell<Option<f64>>);

impl LastSample {
    /// Runs `routine` `iters` times and returns the time they took, as `iter_custom`
    /// wants it.
    pub(crate) fn time<T>(&self, iters: u64, mut routine: impl FnMut() -> T) -> Duration {
        let start = Instant::now();
        for _ in 0..iters {
            black_box(routine());
        }
        let elapsed = start.elapsed();
        self.0.set(Some(elapsed.as_secs_f64() / iters as f64));
        elapsed
    }

    /// Seconds per iteration in the last sample; `None` when criterion never ran the
    /// routine (a filter on the command line left it out).
    pub(crate) fn seconds(&self) -> Option<f64> {
        self.0.get()
    }
}

/// Peak resident set size of this process, MiB (NaN where /proc is unavailable).
pub(crate) fn peak_rss_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmHWM:"))
                .and_then(|l| l.split_whitespace().nth(1)?.parse::<f64>().ok())
        })
        .map_or(f64::NAN, |kib| kib / 1024.0)
}

/// The clock, GHz, as /proc/cpuinfo reports it (NaN where unavailable).
pub(crate) fn clock_ghz() -> f64 {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("cpu MHz"))
                .and_then(|l| l.split(':').nth(1)?.trim().parse::<f64>().ok())
        })
        .map_or(f64::NAN, |mhz| mhz / 1000.0)
}

/// The f32 fused-multiply-add peak of `threads` cores, GFLOP/s: two 256-bit FMA pipes
/// per core (x86-64 with AVX2: Zen 2 to 5, Intel since Haswell), 8 lanes each, 2 flops
/// per FMA, at the reported clock.
pub(crate) fn f32_fma_peak_gflops(threads: usize) -> f64 {
    threads as f64 * clock_ghz() * 2.0 * 8.0 * 2.0
}

/// One line on the arithmetic rate: `flops` counted operations done in `seconds`,
/// against the f32 FMA peak of the threads in use.
pub(crate) fn peak_share(flops: f64, seconds: f64) -> String {
    let threads = rayon::current_num_threads();
    let rate = flops / seconds / 1e9;
    let peak = f32_fma_peak_gflops(threads);
    format!(
        "{rate:.2} GFLOP/s counted, {:.1} % of the {threads}-core f32 FMA peak ({peak:.0} GFLOP/s)",
        100.0 * rate / peak
    )
}

/// The GPU the `_gpu` benchmarks run on: a hardware adapter, or a software one where
/// `PERISCOPE_BENCH_SOFTWARE_GPU` is set; `None`, saying why, otherwise.
pub(crate) fn bench_gpu() -> Option<Compute> {
    match Compute::open(ComputeDevice::Gpu) {
        Ok(c) if !c.info().software || std::env::var_os("PERISCOPE_BENCH_SOFTWARE_GPU").is_some() => {
            println!("GPU benchmarks on {}", c.info());
            Some(c)
        }
        Ok(c) => {
            println!(
                "GPU benchmarks left out: only a software adapter ({}); PERISCOPE_BENCH_SOFTWARE_GPU=1 runs them on it",
                c.info()
            );
            None
        }
        Err(e) => {
            println!("GPU benchmarks left out: {e}");
            None
        }
    }
}

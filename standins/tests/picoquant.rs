//! Periscope's PicoQuant driver through the real FFI path: the driver loads the
//! stand-in library by path, exactly as it loads the vendor's, and these tests hold it
//! to the vendor's published histogram-mode call sequence, the error codes, the flags,
//! a counter that vanishes mid-acquisition, and the settings it must refuse. The
//! stand-in's record of calls is what the library saw; its histograms come from the
//! simulated instrument.
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use periscope_drivers::picoquant::defin::{error, flag};
use periscope_drivers::picoquant::{Family, PicoQuantSettings, PicoQuantTdc, list_counters};
use periscope_drivers::{Error, ErrorKind, Histogrammer, TdcConfig};
use periscope_standins::client::{Standin, exclusive};

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// The shipped simulated instrument at `time_scale`, written into `dir` (its scene
/// path made absolute), for the stand-in's `Setup`.
fn sim_config(dir: &Path, time_scale: f64) -> PathBuf {
    let scene = root().join("configs/scenes/wall-letter.toml");
    let text = std::fs::read_to_string(root().join("configs/instrument/sim.toml"))
        .unwrap()
        .replace("../scenes/wall-letter.toml", &scene.to_string_lossy())
        .replace("[sim]\n", &format!("[sim]\ntime-scale = {time_scale}\n"));
    let path = dir.join("rig.toml");
    std::fs::write(&path, text).unwrap();
    path
}

/// A fresh stand-in whose simulated time runs at `time_scale`.
fn standin(dir: &Path, time_scale: f64) -> Standin {
    let s = Standin::load();
    s.setup(&sim_config(dir, time_scale));
    s
}

fn settings(family: Family, library: PathBuf) -> PicoQuantSettings {
    PicoQuantSettings {
        family,
        library,
        serial: None,
        channel: 0,
        sync_trigger: family.default_trigger(),
        input_trigger: family.default_trigger(),
        input_offset_ps: 0,
        timeout: Duration::from_millis(1000),
    }
}

fn config(bin_width_ps: f64, dwell_ms: u64) -> TdcConfig {
    TdcConfig {
        bin_width: bin_width_ps * 1e-12,
        bins: 1024,
        offset: 12e-9,
        sync_divider: 1,
        acquisition: Duration::from_millis(dwell_ms),
    }
}

/// Asserts that `calls` contains `expected` in this order (other calls may come
/// between); `*` in an expected call matches any argument.
fn assert_sequence(calls: &[String], expected: &[&str]) {
    let matches = |call: &str, want: &str| {
        let (cn, ca) = call.split_once('(').unwrap_or((call, ""));
        let (wn, wa) = want.split_once('(').unwrap_or((want, ""));
        cn == wn
            && (wa.is_empty()
                || ca
                    .split(", ")
                    .zip(wa.split(", "))
                    .all(|(c, w)| w == "*" || w.trim_end_matches(')') == c.trim_end_matches(')')))
    };
    let mut i = 0;
    for want in expected {
        match calls[i..].iter().position(|c| matches(c, want)) {
            Some(p) => i += p + 1,
            None => panic!("`{want}` not found after call {i} in:\n{}", calls.join("\n")),
        }
    }
}

#[test]
fn the_vendors_multiharp_demo_sequence_runs_through_the_driver() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let mut tdc = PicoQuantTdc::open(settings(Family::MultiHarp, s.path())).unwrap();
    let info = tdc.identify().unwrap();
    assert_eq!(info.serial, "1045678");
    assert!(info.model.contains("MultiHarp"), "{info:?}");
    tdc.configure(&config(20.0, 30)).unwrap();
    // The rates (and the warnings made from them) are read once the meters read true,
    // 400 ms after SetSyncDiv, as the demo waits; an acquisition before then skips them.
    std::thread::sleep(tdc.rate_latency());
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts.len(), 1024);
    assert!(
        h.counts.iter().any(|&c| c > 0),
        "dark and ambient counts reach the SPAD's input"
    );
    assert_eq!(h.config, config(20.0, 30));
    assert_sequence(
        &s.calls(),
        &[
            "MH_OpenDevice(0, *)",
            "MH_Initialize(0, 0, 0)",
            "MH_GetHardwareInfo(0, *, *, *)",
            "MH_GetSerialNumber(0, *)",
            "MH_GetNumOfInputChannels(0, *)",
            "MH_SetSyncEdgeTrg(0, -50, 0)",
            "MH_SetSyncChannelOffset(0, 0)",
            "MH_SetInputEdgeTrg(0, 0, -50, 0)",
            "MH_SetInputChannelOffset(0, 0, 0)",
            "MH_SetInputChannelEnable(0, 0, 1)",
            "MH_SetInputChannelEnable(0, 1, 0)",
            "MH_SetSyncDiv(0, 1)",
            // 1024 bins: the smallest length code MH_GetHistogram reads is 2 (4096 bins).
            "MH_SetHistoLen(0, 2, *)",
            "MH_SetBinning(0, 2)",
            "MH_SetOffset(0, 12)",
            "MH_GetResolution(0, *)",
            "MH_ClearHistMem(0)",
            "MH_StartMeas(0, 30)",
            "MH_CTCStatus(0, *)",
            "MH_StopMeas(0)",
            "MH_GetHistogram(0, *, 0)",
            "MH_GetFlags(0, *)",
            "MH_GetElapsedMeasTime(0, *)",
            "MH_GetSyncRate(0, *)",
            "MH_GetCountRate(0, 0, *)",
            "MH_GetWarnings(0, *)",
        ],
    );
    let status = tdc.status().unwrap();
    assert_eq!(status.rates.sync, 10e6, "the laser's 10 MHz, divider 1");
    assert_eq!(status.acquisitions, 1);
    drop(tdc);
    assert_eq!(s.calls().last().map(String::as_str), Some("MH_CloseDevice(0)"));
}

#[test]
fn the_vendors_hydraharp_demo_sequence_calibrates_and_sets_cfd_levels() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let mut tdc = PicoQuantTdc::open(settings(Family::HydraHarp, s.path())).unwrap();
    tdc.configure(&config(16.0, 20)).unwrap();
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts.len(), 1024);
    assert_sequence(
        &s.calls(),
        &[
            "HH_OpenDevice(0, *)",
            "HH_Initialize(0, 0, 0)",
            "HH_GetHardwareInfo(0, *, *, *)",
            "HH_Calibrate(0)",
            "HH_SetSyncCFD(0, 50, 10)",
            "HH_SetInputCFD(0, 0, 50, 10)",
            "HH_SetSyncDiv(0, 1)",
            "HH_SetHistoLen(0, 0, *)",
            "HH_SetBinning(0, 4)",
            "HH_StartMeas(0, 20)",
            "HH_GetHistogram(0, *, 0, 0)",
            "HH_GetFlags(0, *)",
        ],
    );
    assert!(
        !s.calls().iter().any(|c| c.starts_with("MH_")),
        "the HydraHarp driver calls HHLib only"
    );
}

#[test]
fn only_the_configured_spad_input_is_read() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    // The stand-in's counter has its SPAD on the first input; the driver reads the third.
    let mut tdc = PicoQuantTdc::open(PicoQuantSettings {
        channel: 2,
        ..settings(Family::MultiHarp, s.path())
    })
    .unwrap();
    tdc.configure(&config(20.0, 30)).unwrap();
    let h = tdc.acquire().unwrap();
    assert!(h.counts.iter().all(|&c| c == 0), "input 3 has no detector");
    assert!(s.calls().iter().any(|c| c == "MH_GetHistogram(0, *, 2)"));
    drop(tdc);
    let err = PicoQuantTdc::open(PicoQuantSettings {
        channel: 4,
        ..settings(Family::MultiHarp, s.path())
    })
    .err()
    .expect("a 4-input counter has no input 5");
    assert_eq!(err.kind(), ErrorKind::OutOfRange, "{err}");
    assert!(err.to_string().contains("tdc.channel"), "{err}");
}

#[test]
fn the_counter_is_opened_by_serial_number() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    s.plug(Family::MultiHarp, 1, "2000001", 4, 0);
    s.plug(Family::MultiHarp, 3, "3000003", 8, 0);
    let found = list_counters(Family::MultiHarp, &s.path()).unwrap().1;
    let serials: Vec<_> = found.iter().map(|f| (f.index, f.serial.as_str())).collect();
    assert_eq!(serials, [(0, "1045678"), (1, "2000001"), (3, "3000003")]);
    assert!(
        found
            .iter()
            .all(|f| f.model.as_deref().is_some_and(|m| m.contains("MultiHarp")))
    );

    s.clear_calls();
    let mut tdc = PicoQuantTdc::open(PicoQuantSettings {
        serial: Some("3000003".into()),
        ..settings(Family::MultiHarp, s.path())
    })
    .unwrap();
    assert_eq!(tdc.index(), 3);
    assert_eq!(tdc.identify().unwrap().serial, "3000003");
    assert_sequence(
        &s.calls(),
        &[
            "MH_OpenDevice(0, *)",
            "MH_CloseDevice(0)",
            "MH_OpenDevice(1, *)",
            "MH_CloseDevice(1)",
            "MH_OpenDevice(2, *)",
            "MH_OpenDevice(3, *)",
            "MH_Initialize(3, 0, 0)",
        ],
    );
    // The others are free for another program.
    let other = PicoQuantTdc::open(settings(Family::MultiHarp, s.path())).unwrap();
    assert_eq!(other.index(), 0);

    let err = PicoQuantTdc::open(PicoQuantSettings {
        serial: Some("9999999".into()),
        ..settings(Family::MultiHarp, s.path())
    })
    .err()
    .expect("no such serial");
    assert_eq!(err.kind(), ErrorKind::Disconnected, "{err}");
    assert!(
        err.to_string().contains("9999999") && err.to_string().contains("2000001"),
        "{err}"
    );
}

#[test]
fn library_error_codes_become_kinds_carrying_the_librarys_own_string() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let f = Family::MultiHarp;
    let cases = [
        (
            "StartMeas",
            error::DEVICE_BUSY,
            ErrorKind::Busy,
            "MH_ERROR_DEVICE_BUSY",
        ),
        (
            "ClearHistMem",
            -41,
            ErrorKind::Timeout,
            "MH_ERROR_DONEALL_TIMEOUT",
        ),
        (
            "GetHistogram",
            error::NOT_INITIALIZED,
            ErrorKind::Device,
            "MH_ERROR_NOT_INITIALIZED",
        ),
        (
            "GetFlags",
            error::INVALID_ARGUMENT,
            ErrorKind::OutOfRange,
            "MH_ERROR_INVALID_ARGUMENT",
        ),
        ("CTCStatus", -46, ErrorKind::Device, "MH_ERROR_CALIB_FAIL"),
    ];
    let mut tdc = PicoQuantTdc::open(settings(f, s.path())).unwrap();
    tdc.configure(&config(20.0, 10)).unwrap();
    for (function, code, kind, text) in cases {
        s.fail_next(f, function, code);
        let e = tdc.acquire().expect_err(function);
        assert_eq!(e.kind(), kind, "{function} {code}: {e}");
        let msg = e.to_string();
        assert!(
            msg.contains(text) && msg.contains(&format!("MH_{function}")) && msg.contains(&code.to_string()),
            "{msg}"
        );
        assert_eq!(e.code(), Some(code));
        // The driver goes on with the next acquisition.
        tdc.acquire().unwrap();
    }
    // At configure and at open.
    s.fail_next(f, "SetOffset", error::INVALID_ARGUMENT);
    let e = tdc.configure(&config(20.0, 10)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::OutOfRange, "{e}");
    drop(tdc);
    s.fail_next(f, "Initialize", error::USB_DRIVERVER_MISMATCH);
    let e = PicoQuantTdc::open(settings(f, s.path())).err().unwrap();
    assert_eq!(e.kind(), ErrorKind::Protocol, "{e}");
    assert!(e.to_string().contains("MH_ERROR_USB_DRIVERVER_MISMATCH"), "{e}");
    // Through the one DeviceError the daemon holds: same kind, same words.
    s.fail_next(f, "Initialize", error::DEVICE_BUSY);
    let e: periscope_drivers::DeviceError = PicoQuantTdc::open(settings(f, s.path())).err().unwrap().into();
    assert_eq!(e.kind(), ErrorKind::Busy);
    assert!(
        e.device().contains("MultiHarp 1045678") && e.to_string().contains("MH_ERROR_DEVICE_BUSY"),
        "{e}"
    );
}

#[test]
fn overflow_fifo_and_dropped_counts_flag_the_histogram_and_a_lost_sync_fails_it() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let f = Family::MultiHarp;
    let mut tdc = PicoQuantTdc::open(settings(f, s.path())).unwrap();
    tdc.configure(&config(20.0, 10)).unwrap();
    assert!(!tdc.acquire().unwrap().flags.overflow);
    for bit in [flag::OVERFLOW, flag::FIFOFULL, flag::CNTS_DROPPED] {
        s.flag_next(f, 0, bit);
        let h = tdc.acquire().unwrap();
        assert!(h.flags.overflow, "flag {bit:#x}");
        assert!(
            !tdc.acquire().unwrap().flags.overflow,
            "the next histogram is clean"
        );
    }
    s.flag_next(f, 0, flag::SYNC_LOST);
    let e = tdc.acquire().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Device, "{e}");
    assert!(e.to_string().contains("sync"), "{e}");
    s.flag_next(f, 0, flag::SYSERROR);
    let e = tdc.acquire().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Device, "{e}");
    assert!(e.to_string().contains("hardware error"), "{e}");
    tdc.acquire().unwrap();
}

/// A laser whose sync stops just after a measurement: the counter's flags say nothing
/// (the measurement had its sync), but its rate meter reads a sync of 0, which makes
/// the detector's rate over it infinite. That is no pile-up: the histogram is kept
/// unflagged (until 2026-12-07 it came back flagged saturated), and the next
/// acquisition fails on the lost sync, naming it.
#[test]
fn a_sync_that_stops_after_a_measurement_is_named_not_taken_for_pile_up() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let f = Family::MultiHarp;
    let mut tdc = PicoQuantTdc::open(settings(f, s.path())).unwrap();
    tdc.configure(&config(20.0, 10)).unwrap();
    // Past the rate meters' settling after the configuration.
    std::thread::sleep(Duration::from_millis(450));
    let h = tdc.acquire().unwrap();
    assert!(!h.flags.saturated && !h.flags.overflow);
    s.sync_stops(f, 0);
    let last = tdc.acquire().unwrap();
    assert!(
        !last.flags.saturated && last.counts.iter().any(|&c| c > 0),
        "{:?}",
        last.flags
    );
    let e = tdc.acquire().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Device, "{e}");
    assert!(e.to_string().contains("sync signal was lost"), "{e}");
}

#[test]
fn a_counter_that_vanishes_mid_acquisition_is_reopened_or_reported_gone() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 1.0);
    let f = Family::MultiHarp;
    let mut tdc = PicoQuantTdc::open(settings(f, s.path())).unwrap();
    // A divider other than the device's default after Initialize, so that restoring it
    // shows in the calls.
    let divided = TdcConfig {
        sync_divider: 2,
        ..config(20.0, 50)
    };
    tdc.configure(&divided).unwrap();
    // The same divider again is not set again: each SetSyncDiv blinds the rate meters.
    s.clear_calls();
    tdc.configure(&divided).unwrap();
    assert!(
        !s.calls().iter().any(|c| c.starts_with("MH_SetSyncDiv")),
        "{:?}",
        s.calls()
    );

    // Back at once: reopened by serial, the settings restored, the acquisition repeated.
    s.clear_calls();
    let armed = AtomicBool::new(true);
    let h = tdc
        .acquire_until(&|| {
            if armed.swap(false, Ordering::SeqCst) {
                s.vanish(f, 0, 0);
            }
            false
        })
        .unwrap();
    assert_eq!(h.counts.len(), 1024);
    assert_sequence(
        &s.calls(),
        &[
            "MH_StartMeas(0, 50)",
            "MH_CTCStatus(0, *)",
            "MH_CloseDevice(0)",
            "MH_OpenDevice(0, *)",
            "MH_Initialize(0, 0, 0)",
            "MH_SetSyncDiv(0, 2)",
            "MH_SetHistoLen(0, 2, *)",
            "MH_SetBinning(0, 2)",
            "MH_StartMeas(0, 50)",
            "MH_GetHistogram(0, *, 0)",
        ],
    );

    // Gone for good: the acquisition fails as a disconnect, and says so.
    let armed = AtomicBool::new(true);
    let e = tdc
        .acquire_until(&|| {
            if armed.swap(false, Ordering::SeqCst) {
                s.vanish(f, 0, u32::MAX);
            }
            false
        })
        .unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    assert!(
        e.to_string().contains("MH_ERROR_USB_VCMD_FAIL") && e.to_string().contains("reopened"),
        "{e}"
    );
    assert_eq!(tdc.status().unwrap_err().kind(), ErrorKind::Disconnected);
}

#[test]
fn a_stop_ends_a_long_acquisition_on_the_device_within_the_poll() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 1.0);
    let mut tdc = PicoQuantTdc::open(settings(Family::MultiHarp, s.path())).unwrap();
    tdc.configure(&config(20.0, 5_000)).unwrap();
    let t = Instant::now();
    let e = tdc
        .acquire_until(&|| t.elapsed() > Duration::from_millis(30))
        .unwrap_err();
    let took = t.elapsed();
    assert_eq!(e.kind(), ErrorKind::Interrupted, "{e}");
    assert!(took < Duration::from_millis(200), "stopped after {took:?}");
    assert_eq!(s.calls().last().map(String::as_str), Some("MH_StopMeas(0)"));
    tdc.configure(&config(20.0, 10)).unwrap();
    tdc.acquire().unwrap();
}

#[test]
fn settings_the_counter_cannot_take_exactly_are_refused_not_rounded() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let mut mh = PicoQuantTdc::open(settings(Family::MultiHarp, s.path())).unwrap();
    let refused = |tdc: &mut PicoQuantTdc, c: TdcConfig, words: &str| {
        let e = tdc.configure(&c).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::OutOfRange, "{c:?}: {e}");
        assert!(e.to_string().contains(words), "{e}");
    };
    // 5 ps × 2^n: 16 ps is not one.
    refused(&mut mh, config(16.0, 10), "5, 10, 20, 40");
    refused(
        &mut mh,
        TdcConfig {
            acquisition: Duration::from_micros(1500),
            ..config(20.0, 1)
        },
        "whole milliseconds",
    );
    refused(
        &mut mh,
        TdcConfig {
            offset: 12.5e-9,
            ..config(20.0, 10)
        },
        "whole nanoseconds",
    );
    refused(
        &mut mh,
        TdcConfig {
            sync_divider: 17,
            ..config(20.0, 10)
        },
        "1 to 16",
    );
    refused(
        &mut mh,
        TdcConfig {
            bins: 70_000,
            ..config(20.0, 10)
        },
        "65536",
    );
    assert!(mh.config().is_none(), "nothing refused is kept");
    let mut hh = PicoQuantTdc::open(settings(Family::HydraHarp, s.path())).unwrap();
    refused(
        &mut hh,
        TdcConfig {
            sync_divider: 3,
            ..config(16.0, 10)
        },
        "1, 2, 4, 8 or 16",
    );
    hh.configure(&TdcConfig {
        sync_divider: 4,
        bins: 3000,
        ..config(16.0, 10)
    })
    .unwrap();
    assert_eq!(
        hh.acquire().unwrap().counts.len(),
        3000,
        "the first `bins` of a 4096-bin histogram"
    );
}

#[test]
fn a_missing_library_says_which_path_was_tried_and_what_to_install() {
    let e = PicoQuantTdc::open(settings(Family::MultiHarp, "/nonexistent/mh150/mhlib.so".into()))
        .err()
        .expect("no library there");
    assert_eq!(e.kind(), ErrorKind::Disconnected, "{e}");
    let msg = e.to_string();
    assert!(
        msg.contains("/nonexistent/mh150/mhlib.so") && msg.contains("MHLib") && msg.contains("tdc.library"),
        "{msg}"
    );
    // A library that is not PicoQuant's: the first missing function is named.
    let e = PicoQuantTdc::open(settings(Family::MultiHarp, "libm.so.6".into()))
        .err()
        .unwrap();
    assert_eq!(e.kind(), ErrorKind::Protocol, "{e}");
    assert!(e.to_string().contains("MH_GetLibraryVersion"), "{e}");
}

/// The rate meter as the vendor's demos describe it: for 400 ms after `Initialize` the
/// sync reads 0, and for 400 ms after `SetSyncDiv` the rate from before; then the
/// laser's own rate, whatever the divider ("corrected for the divider setting", the
/// manuals' `SetSyncDiv`), which the driver says. The driver's `rate_latency` is that
/// time.
#[test]
fn the_sync_rate_meter_lags_initialise_and_set_sync_div() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let mut tdc = PicoQuantTdc::open(settings(Family::MultiHarp, s.path())).unwrap();
    assert_eq!(tdc.rate_latency(), Duration::from_millis(400));
    tdc.configure(&config(20.0, 10)).unwrap();
    assert_eq!(
        tdc.status().unwrap().rates.sync,
        0.0,
        "read at once after Initialize"
    );
    std::thread::sleep(tdc.rate_latency());
    assert_eq!(tdc.status().unwrap().rates.sync, 10e6);
    tdc.configure(&TdcConfig {
        sync_divider: 2,
        ..config(20.0, 10)
    })
    .unwrap();
    assert_eq!(
        tdc.status().unwrap().rates.sync,
        10e6,
        "read at once after SetSyncDiv"
    );
    std::thread::sleep(tdc.rate_latency());
    assert_eq!(tdc.status().unwrap().rates.sync, 10e6, "the undivided rate");
    assert_eq!(tdc.sync_after_divider(), Some(false));
}

/// Within 400 ms of `SetSyncDiv` the rate meters read nothing true (a sync of 0 after
/// `Initialize`), so the warnings made from them would call every histogram piled up:
/// the driver reads neither then, and flags nothing.
#[test]
fn no_histogram_is_flagged_from_rates_the_meter_has_not_settled() {
    let _one = exclusive();
    let tmp = tempfile::tempdir().unwrap();
    let s = standin(tmp.path(), 0.0);
    let mut tdc = PicoQuantTdc::open(settings(Family::MultiHarp, s.path())).unwrap();
    tdc.configure(&config(20.0, 10)).unwrap();
    s.clear_calls();
    let h = tdc.acquire().unwrap();
    assert!(!h.flags.saturated, "{:?}", h.flags);
    assert!(
        !s.calls().iter().any(|c| c.starts_with("MH_GetWarnings")),
        "{:?}",
        s.calls()
    );
}

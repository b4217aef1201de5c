//! Software overhead per measured pair (issue: drivers): move both galvo pairs, wait
//! until both report settled, acquire one histogram, through the real drivers and the
//! real wire code against the simulated devices, with simulated settling and dwell set
//! to zero and no scene physics (the histogrammer returns dark counts), so what is
//! timed is protocol encoding and decoding, the pseudo-terminal round trips, frame
//! CRCs and the drivers' checks. Target: under 200 µs per pair.
//!
//! Timed: `PAIRS` pairs (default 2,000) in a loop, median over `REPS` runs (default 5),
//! reported per pair, for 512- and 4,096-bin histograms. Not timed: connecting,
//! configuring.
use std::time::{Duration, Instant};

use glam::DVec3;
use periscope_drivers::galvo::{SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::UsbTdc;
use periscope_drivers::{AngleLimits, GalvoPair, GalvoPose, Histogrammer, OpticalAngles, TdcConfig};
use periscope_sim::Detector;
use periscope_sim::devices::{Arm, Rig, RigSettings};

fn env(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let pairs = env("PAIRS", 2000);
    let reps = env("REPS", 5);
    let limits = AngleLimits {
        x: [-0.35, 0.35],
        y: [-0.35, 0.35],
    };
    let pose = |x| GalvoPose::looking(DVec3::new(x, 0.0, 2.0), -DVec3::Z, DVec3::Y).unwrap();
    let detector = Detector::example();
    let rig = Rig::new(
        None,
        RigSettings {
            laser_pose: pose(-0.1),
            spad_pose: pose(0.1),
            limits: [limits; 2],
            settle: [Duration::from_micros(300); 2],
            detector,
            time_scale: 0.0,
            seed: 1,
            interlock_closed: true,
        },
    );
    let settings = |name: &str| SerialGalvoSettings {
        name: name.into(),
        limits,
        timeout: Duration::from_millis(200),
        settle: Duration::ZERO,
        watchdog: None,
    };
    let mut laser = SerialGalvo::open(settings("laser"), Box::new(rig.galvo_connector(Arm::Laser))).unwrap();
    let mut spad = SerialGalvo::open(settings("spad"), Box::new(rig.galvo_connector(Arm::Spad))).unwrap();
    let mut tdc = UsbTdc::new(rig.tdc_transport(), Duration::from_millis(200));
    println!("pairs per run: {pairs}, runs: {reps}");
    let start = Instant::now();
    for _ in 0..pairs {
        laser.position().unwrap();
    }
    println!(
        "one galvo round trip (POS): {:.1} µs",
        start.elapsed().as_secs_f64() / pairs as f64 * 1e6
    );
    for bins in [512u32, 4096] {
        tdc.configure(&TdcConfig {
            bin_width: 16e-12,
            bins,
            offset: 12e-9,
            sync_divider: 1,
            acquisition: Duration::from_micros(1),
        })
        .unwrap();
        let mut per_pair = Vec::new();
        for _ in 0..reps {
            let start = Instant::now();
            for k in 0..pairs {
                let t = (k % 64) as f64 / 64.0 * 0.3 - 0.15;
                let a = OpticalAngles { x: t, y: -t / 2.0 };
                laser.move_to(a).unwrap();
                spad.move_to(OpticalAngles { x: -t, y: t / 3.0 }).unwrap();
                laser.wait_settled(Duration::from_secs(1)).unwrap();
                spad.wait_settled(Duration::from_secs(1)).unwrap();
                let h = tdc.acquire().unwrap();
                assert_eq!(h.counts.len(), bins as usize);
            }
            per_pair.push(start.elapsed().as_secs_f64() / pairs as f64);
        }
        per_pair.sort_by(f64::total_cmp);
        println!(
            "move+settle+acquire, {bins} bins: median {:.1} µs/pair (min {:.1}, max {:.1}) = {:.0} pairs/s",
            per_pair[reps / 2] * 1e6,
            per_pair[0] * 1e6,
            per_pair[reps - 1] * 1e6,
            1.0 / per_pair[reps / 2]
        );
    }
}

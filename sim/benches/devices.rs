//! Software overhead per measured pair (issue: drivers): move both galvo pairs, wait
//! until both report settled, acquire one histogram, through the real drivers and the
//! real wire code against the simulated devices, with simulated settling and dwell set
//! to zero and no scene physics (the histogrammer returns dark counts), so what is
//! timed is protocol encoding and decoding, the pseudo-terminal round trips, frame
//! CRCs and the drivers' checks. Target: under 200 µs per pair.
//!
//! Timed (criterion, group `devices`; one iteration is one pair, so criterion's median
//! time is the time per pair to quote and its throughput line is pairs per second): one
//! galvo round trip alone (POS), and move + settle + acquire for 512- and 4,096-bin
//! histograms. Not timed: connecting, configuring.
use std::time::Duration;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use glam::DVec3;
use periscope_drivers::galvo::{SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::UsbTdc;
use periscope_drivers::{AngleLimits, GalvoPair, GalvoPose, Histogrammer, OpticalAngles, TdcConfig};
use periscope_sim::Detector;
use periscope_sim::devices::{Arm, Rig, RigSettings};

fn devices(c: &mut Criterion) {
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
            noise: true,
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

    let mut group = c.benchmark_group("devices");
    // About 200 µs an iteration: criterion's default 100 samples fit in 5 s.
    group
        .warm_up_time(Duration::from_secs(1))
        .measurement_time(Duration::from_secs(5))
        .throughput(Throughput::Elements(1));
    group.bench_function("galvo POS round trip", |b| b.iter(|| laser.position().unwrap()));
    for bins in [512u32, 4096] {
        tdc.configure(&TdcConfig {
            bin_width: 16e-12,
            bins,
            offset: 12e-9,
            sync_divider: 1,
            acquisition: Duration::from_micros(1),
        })
        .unwrap();
        // The angles cycle through 64 steps across the iterations, as a scan would.
        let mut k = 0usize;
        group.bench_function(format!("move-settle-acquire {bins} bins"), |b| {
            b.iter(|| {
                let t = (k % 64) as f64 / 64.0 * 0.3 - 0.15;
                k += 1;
                let a = OpticalAngles { x: t, y: -t / 2.0 };
                laser.move_to(a).unwrap();
                spad.move_to(OpticalAngles { x: -t, y: t / 3.0 }).unwrap();
                laser.wait_settled(Duration::from_secs(1)).unwrap();
                spad.wait_settled(Duration::from_secs(1)).unwrap();
                let h = tdc.acquire().unwrap();
                assert_eq!(h.counts.len(), bins as usize);
            })
        });
    }
    group.finish();
}

criterion_group!(benches, devices);
criterion_main!(benches);

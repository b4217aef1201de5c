//! Tests against real devices, excluded by default: they need the lab instrument.
//! Run on the lab machine, serialised (they share the hardware):
//!
//! ```text
//! PERISCOPE_GALVO_PORT=/dev/ttyUSB1 PERISCOPE_TDC_USB=1d50:6189 \
//!   cargo test -p periscope-drivers --features hardware-tests -- --test-threads=1
//! ```
//!
//! The galvo test moves the SPAD arm (never the laser arm, and never switches the
//! laser) within ±2°, and parks it.
#![cfg(feature = "hardware-tests")]

use std::time::Duration;

use periscope_drivers::galvo::{PortConnector, SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::{RusbTransport, UsbTdc};
use periscope_drivers::{AngleLimits, GalvoPair, Histogrammer, OpticalAngles, TdcConfig};

fn env(name: &str) -> String {
    std::env::var(name).unwrap_or_else(|_| panic!("set {name} to run the hardware tests"))
}

#[test]
fn spad_arm_moves_and_settles() {
    let lim = 2f64.to_radians();
    let mut g = SerialGalvo::open(
        SerialGalvoSettings {
            name: "spad".into(),
            limits: AngleLimits {
                x: [-lim, lim],
                y: [-lim, lim],
            },
            timeout: Duration::from_millis(200),
            settle: Duration::from_micros(400),
            watchdog: None,
        },
        Box::new(PortConnector {
            path: env("PERISCOPE_GALVO_PORT"),
            baud: 115_200,
        }),
    )
    .unwrap();
    for target in [
        OpticalAngles { x: lim / 2.0, y: 0.0 },
        OpticalAngles {
            x: 0.0,
            y: -lim / 2.0,
        },
    ] {
        let at = g.move_settled(target, Duration::from_millis(100)).unwrap();
        assert!((at.x - target.x).abs() < 1e-5 && (at.y - target.y).abs() < 1e-5);
    }
    g.park().unwrap();
}

#[test]
fn histogrammer_acquires() {
    let transport = RusbTransport::open(env("PERISCOPE_TDC_USB").parse().unwrap()).unwrap();
    let mut tdc = UsbTdc::open(transport, Duration::from_millis(500)).unwrap();
    tdc.identify().unwrap();
    tdc.configure(&TdcConfig {
        bin_width: 16e-12,
        bins: 1024,
        offset: 0.0,
        sync_divider: 1,
        acquisition: Duration::from_millis(100),
    })
    .unwrap();
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts.len(), 1024);
}

/// The laser controller's watchdog (protocol revision 2): switched on and then left
/// silent, the controller must end emission within its timeout and count the trip.
/// It switches the laser on, so it runs only when also given
/// `PERISCOPE_ALLOW_EMISSION=1`, with the beam on a dump and the enclosure closed.
#[test]
fn laser_watchdog_ends_emission_when_the_host_goes_silent() {
    use periscope_drivers::Laser;
    use periscope_drivers::galvo::Connector;
    use periscope_drivers::galvo::protocol::encode_line;

    let port = env("PERISCOPE_LASER_PORT");
    assert_eq!(
        env("PERISCOPE_ALLOW_EMISSION"),
        "1",
        "this test switches the laser on: set PERISCOPE_ALLOW_EMISSION=1 with the beam on a dump"
    );
    let connector = || PortConnector {
        path: port.clone(),
        baud: 115_200,
    };
    let settings = SerialGalvoSettings {
        name: "laser".into(),
        limits: AngleLimits {
            x: [-0.01, 0.01],
            y: [-0.01, 0.01],
        },
        timeout: Duration::from_millis(200),
        settle: Duration::from_micros(400),
        watchdog: None,
    };
    let mut g = SerialGalvo::open(settings.clone(), Box::new(connector())).unwrap();
    let (_, trips_before) = g.watchdog().unwrap();
    drop(g);
    // A bare link: WDOG 100, LASER ON, then silence.
    let mut link = connector().connect().unwrap();
    let mut buf = [0u8; 128];
    for (tag, body) in [(1u8, "WDOG 100"), (2, "LASER ON")] {
        link.send(encode_line(tag, body).as_bytes()).unwrap();
        let n = link.receive(&mut buf, Duration::from_millis(200)).unwrap();
        assert!(buf[..n].starts_with(format!("{tag:02X} OK").as_bytes()), "{body}");
    }
    std::thread::sleep(Duration::from_millis(250));
    drop(link);
    let mut g = SerialGalvo::open(settings, Box::new(connector())).unwrap();
    let state = g.laser_state().unwrap();
    let (_, trips) = g.watchdog().unwrap();
    g.set_emission(false).unwrap();
    assert!(
        !state.emission,
        "the controller kept emitting after 250 ms of silence"
    );
    assert_eq!(trips, trips_before + 1);
}

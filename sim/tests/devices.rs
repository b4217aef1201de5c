//! The real drivers against the simulated devices, through the real wire code: the
//! galvo firmware on a pseudo-terminal and the histogrammer behind the USB transport.
//! One test per injected fault shows the documented behaviour: a retry that recovers,
//! or an error of the documented kind, and never a wrong position or histogram
//! accepted. The last section holds the in-process devices to the same behaviour and
//! the same counts.
use std::time::{Duration, Instant};

use glam::DVec3;
use periscope_drivers::galvo::{SerialGalvo, SerialGalvoSettings};
use periscope_drivers::tdc::UsbTdc;
use periscope_drivers::{
    AngleLimits, Error, ErrorKind, GalvoPair, GalvoPose, Histogrammer, Laser, OpticalAngles, Parked,
    Progress, TdcConfig,
};
use periscope_sim::detector::C0;
use periscope_sim::devices::{Arm, Fault, GalvoFault, Rig, RigSettings, SimTdcTransport, TdcFault};
use periscope_sim::scene::{ShapeKind, Surface};
use periscope_sim::{Detector, Mesh, Scene, World, shapes};

const TIMEOUT: Duration = Duration::from_millis(100);

fn limits(deg: f64) -> AngleLimits {
    let r = deg.to_radians();
    AngleLimits {
        x: [-r, r],
        y: [-r, r],
    }
}

fn rig() -> Rig {
    let patch = Mesh::rectangle([-0.05, 0.05], [-0.05, 0.05])
        .transformed(glam::DMat3::IDENTITY, DVec3::new(0.0, 0.0, 0.5));
    let scene = Scene {
        name: "devices".into(),
        relay: Surface {
            label: "relay".into(),
            shape: ShapeKind::Plane,
            mesh: shapes::plane([2.0, 2.0]),
            albedo: 0.8,
            variation: None,
        },
        hidden: vec![Surface {
            label: "patch".into(),
            shape: ShapeKind::Mesh,
            mesh: patch,
            albedo: 0.9,
            variation: None,
        }],
    };
    let pose = |x: f64| GalvoPose::looking(DVec3::new(x, 0.0, 2.0), -DVec3::Z, DVec3::Y).unwrap();
    Rig::new(
        Some(World::new(scene, 0.01, 1)),
        RigSettings {
            laser_pose: pose(-0.1),
            spad_pose: pose(0.1),
            limits: [limits(20.0), limits(20.0)],
            settle: [Duration::from_micros(300); 2],
            detector: Detector::example(),
            time_scale: 1.0,
            seed: 3,
            interlock_closed: true,
            noise: true,
        },
    )
}

fn galvo(rig: &Rig, arm: Arm, driver_limits_deg: f64) -> SerialGalvo {
    SerialGalvo::new(
        SerialGalvoSettings {
            name: format!("{arm:?}").to_lowercase(),
            limits: limits(driver_limits_deg),
            timeout: TIMEOUT,
            settle: Duration::from_micros(300),
            watchdog: None,
        },
        Box::new(rig.galvo_connector(arm)),
    )
}

fn tdc(rig: &Rig) -> UsbTdc<SimTdcTransport> {
    // Sequence numbers from 1, so the fault tests can name the acquisition a frame
    // came from (a driver opened for real starts at a random one).
    let mut tdc = UsbTdc::with_sequence(rig.tdc_transport(), TIMEOUT, 0);
    tdc.configure(&TDC_CONFIG).unwrap();
    tdc
}

/// 512 bins of 16 ps from 12 ns, 50 ms acquisitions.
const TDC_CONFIG: TdcConfig = TdcConfig {
    bin_width: 16e-12,
    bins: 512,
    offset: 12e-9,
    sync_divider: 1,
    acquisition: Duration::from_millis(50),
};

fn angles(x: f64, y: f64) -> OpticalAngles {
    OpticalAngles { x, y }
}

#[test]
fn controllers_identify_and_move_through_the_pty() {
    let rig = rig();
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    let info = laser.identify().unwrap();
    assert_eq!((info.model.as_str(), info.protocol), ("PGC-2", 2));
    let target = angles(0.05, -0.02);
    let start = Instant::now();
    let settled = laser.move_settled(target, Duration::from_secs(1)).unwrap();
    assert!(
        start.elapsed() >= Duration::from_micros(300),
        "returned before the settling time"
    );
    assert!((settled.x - target.x).abs() < 1e-7 && (settled.y - target.y).abs() < 1e-7);
    assert_eq!(rig.pointing().0, target);
    assert_eq!(laser.position().unwrap(), target);
    laser.park().unwrap();
    assert_eq!(
        laser.wait_settled(Duration::from_secs(1)).unwrap(),
        angles(0.0, 0.0)
    );
}

#[test]
fn targets_outside_the_limits_never_move_the_mirrors() {
    let rig = rig();
    // The driver's own limits: refused before anything is sent.
    let mut spad = galvo(&rig, Arm::Spad, 10.0);
    let err = spad.move_to(angles(0.3, 0.0)).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::OutOfRange);
    assert!(err.to_string().contains("outside the limits"), "{err}");
    assert_eq!(rig.pointing().1, angles(0.0, 0.0));
    // A driver configured wider than the firmware: the controller refuses.
    let mut wide = galvo(&rig, Arm::Spad, 40.0);
    wide.move_to(angles(0.5, 0.0)).unwrap();
    let err = wide.wait_settled(Duration::from_secs(1)).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::OutOfRange);
    assert_eq!(rig.pointing().1, angles(0.0, 0.0));
    // NaN is never a target.
    assert_eq!(
        spad.move_to(angles(f64::NAN, 0.0)).unwrap_err().kind(),
        ErrorKind::OutOfRange
    );
}

/// `LIM` reports the firmware's limits with the seven decimals the wire carries, and
/// the firmware holds moves to what it reports: a move to the reported limit is
/// accepted, and so is one to the host's own limit of the same angle (sent rounded
/// onto it); one a reported digit beyond is refused. On the wire and in process
/// alike. Until 2026-12-07 the firmware checked the unrounded limits, and refused
/// `MOVE 0.3490659`, the ±20° it reported, with `ERR 4`.
#[test]
fn a_move_at_the_reported_limit_is_accepted() {
    let rig = rig();
    let twenty = 20f64.to_radians();
    // A driver configured wider than the firmware, so that the firmware decides.
    let mut wide = galvo(&rig, Arm::Spad, 40.0);
    let reported = wide.hard_limits().unwrap();
    assert_eq!(reported.x, [-0.3490659, 0.3490659], "±20° to seven decimals");
    assert!(reported.x[1] > twenty, "the premise: 20° rounds outward");
    let corner = angles(reported.x[1], reported.y[0]);
    assert_eq!(wide.move_settled(corner, Duration::from_secs(1)).unwrap(), corner);
    assert_eq!(rig.pointing().1, corner);
    let beyond = angles(reported.x[1] + 1e-7, 0.0);
    wide.move_to(beyond).unwrap();
    let err = wide.wait_settled(Duration::from_secs(1)).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::OutOfRange, "{err}");
    assert_eq!(rig.pointing().1, corner);
    drop(wide);
    // A driver whose limits are the firmware's, moving to its exact limit: the wire
    // carries it as the reported one.
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    spad.park().unwrap();
    assert_eq!(rig.pointing().1, angles(0.0, 0.0));
    spad.move_settled(angles(twenty, -twenty), Duration::from_secs(1))
        .unwrap();
    assert_eq!(rig.pointing().1, corner);
    drop(spad);
    // In process: the same, the target rounded as the wire would carry it.
    let mut local = rig.in_process_galvo(Arm::Spad, limits(20.0), None);
    local.park().unwrap();
    local
        .move_settled(angles(twenty, -twenty), Duration::from_secs(1))
        .unwrap();
    assert_eq!(rig.pointing().1, corner);
    let mut local_wide = rig.in_process_galvo(Arm::Spad, limits(40.0), None);
    local_wide.park().unwrap();
    let err = local_wide.move_to(beyond).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::OutOfRange, "{err}");
    assert_eq!(rig.pointing().1, angles(0.0, 0.0));
}

#[test]
fn the_interlock_gates_the_laser() {
    let rig = rig();
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    rig.set_interlock(false);
    let err = laser.set_emission(true).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Interlock);
    assert!(!laser.interlock_closed().unwrap());
    assert!(!rig.emission());
    rig.set_interlock(true);
    laser.set_emission(true).unwrap();
    assert!(laser.laser_state().unwrap().emission);
    // Opening the loop stops emission at once.
    rig.set_interlock(false);
    assert!(!laser.laser_state().unwrap().emission);
    // The SPAD arm's controller has no laser.
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    assert_eq!(spad.set_emission(true).unwrap_err().kind(), ErrorKind::Device);
}

#[test]
fn the_los_histogram_peaks_at_the_first_bounce_path() {
    let rig = rig();
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    let mut tdc = tdc(&rig);
    laser.set_diffuser(true).unwrap();
    laser.set_emission(true).unwrap();
    let (l, s) = rig.origins();
    let p = DVec3::new(0.2, -0.1, 0.0);
    let pose = GalvoPose::looking(s, -DVec3::Z, DVec3::Y).unwrap();
    spad.move_settled(pose.angles_for(p).unwrap(), Duration::from_secs(1))
        .unwrap();
    let h = tdc.acquire().unwrap();
    let peak = (0..h.counts.len()).max_by_key(|&b| h.counts[b]).unwrap();
    let path = p.distance(l) + p.distance(s);
    let expected_bin = (path / C0 - 12e-9) / 16e-12;
    assert!(
        (peak as f64 + 0.5 - expected_bin).abs() < 2.0,
        "peak {peak}, expected {expected_bin:.1}"
    );
    // Laser off: only dark counts.
    laser.set_emission(false).unwrap();
    let dark: u64 = tdc.acquire().unwrap().counts.iter().map(|&c| u64::from(c)).sum();
    assert!(dark < 50, "dark counts {dark}");
}

#[test]
fn an_nlos_pair_sees_the_hidden_patch() {
    let rig = rig();
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    let mut tdc = tdc(&rig);
    laser.set_emission(true).unwrap();
    let (l, s) = rig.origins();
    let (xi, xd) = (DVec3::new(-0.1, 0.0, 0.0), DVec3::new(0.1, 0.0, 0.0));
    let look = |o| GalvoPose::looking(o, -DVec3::Z, DVec3::Y).unwrap();
    laser
        .move_settled(look(l).angles_for(xi).unwrap(), Duration::from_secs(1))
        .unwrap();
    spad.move_settled(look(s).angles_for(xd).unwrap(), Duration::from_secs(1))
        .unwrap();
    let h = tdc.acquire().unwrap();
    // The hidden return: the patch at z = 0.5 is 2 × ~0.51 m of hidden path.
    let path = xi.distance(l) + xd.distance(s) + 2.0 * DVec3::new(0.1, 0.0, 0.5).length();
    let bin = ((path / C0 - 12e-9) / 16e-12) as usize;
    let near: u32 = h.counts[bin.saturating_sub(8)..bin + 8].iter().sum();
    assert!(near > 20, "only {near} counts near bin {bin}");
}

// ---- Galvo faults -------------------------------------------------------------

fn moved_ok_after(fault: GalvoFault) -> (SerialGalvo, Rig) {
    let rig = rig();
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    spad.identify().unwrap();
    rig.inject(Fault::Galvo(Arm::Spad, fault));
    let target = angles(0.1, 0.05);
    let got = spad.move_settled(target, Duration::from_secs(1)).unwrap();
    assert_eq!(got, target, "after {fault:?}");
    assert_eq!(rig.pointing().1, target);
    (spad, rig)
}

#[test]
fn a_dropped_reply_is_retried_once() {
    moved_ok_after(GalvoFault::DropReply);
    let rig = rig();
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    rig.inject(Fault::Galvo(Arm::Spad, GalvoFault::DropReply));
    rig.inject(Fault::Galvo(Arm::Spad, GalvoFault::DropReply));
    let err = spad.position().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Timeout);
    assert!(err.to_string().contains("no reply to `POS`"), "{err}");
}

#[test]
fn a_corrupted_reply_is_retried_once_and_never_accepted() {
    moved_ok_after(GalvoFault::CorruptChecksum);
    let rig = rig();
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    spad.move_settled(angles(0.02, 0.01), Duration::from_secs(1))
        .unwrap();
    rig.inject(Fault::Galvo(Arm::Spad, GalvoFault::CorruptChecksum));
    rig.inject(Fault::Galvo(Arm::Spad, GalvoFault::CorruptChecksum));
    let err = spad.position().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Protocol);
    assert!(err.to_string().contains("checksum"), "{err}");
}

#[test]
fn garbage_on_the_line_is_skipped() {
    moved_ok_after(GalvoFault::Garbage);
}

#[test]
fn a_stalled_controller_is_retried_and_its_late_reply_ignored() {
    let (mut spad, _rig) = moved_ok_after(GalvoFault::Stall(TIMEOUT + Duration::from_millis(30)));
    // The late reply to the first MOVE must not be taken as a later command's reply.
    std::thread::sleep(Duration::from_millis(50));
    assert_eq!(spad.position().unwrap(), angles(0.1, 0.05));
}

#[test]
fn an_unplugged_controller_is_reconnected() {
    moved_ok_after(GalvoFault::Disconnect { refused_connects: 0 });
    // Still gone after the retry: a Disconnected error, then back once it is.
    let rig = rig();
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    spad.identify().unwrap();
    rig.inject(Fault::Galvo(
        Arm::Spad,
        GalvoFault::Disconnect { refused_connects: 1 },
    ));
    let err = spad.position().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Disconnected);
    assert!(err.to_string().contains("plugged in"), "{err}");
    assert_eq!(spad.position().unwrap(), angles(0.0, 0.0));
}

#[test]
fn an_unplugged_laser_controller_comes_back_with_the_laser_off() {
    let rig = rig();
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    laser.set_emission(true).unwrap();
    rig.inject(Fault::Galvo(
        Arm::Laser,
        GalvoFault::Disconnect { refused_connects: 0 },
    ));
    let state = laser.laser_state().unwrap();
    assert!(
        !state.emission,
        "a power-cycled controller must not report emission"
    );
}

// ---- Histogrammer faults ------------------------------------------------------

fn acquire_after(fault: TdcFault) -> (UsbTdc<SimTdcTransport>, periscope_drivers::Histogram) {
    let rig = rig();
    let mut tdc = tdc(&rig);
    rig.inject(Fault::Tdc(fault));
    let h = tdc.acquire().unwrap();
    let sent = tdc
        .transport_mut()
        .sent_counts(h.sequence)
        .expect("a frame with that sequence was sent")
        .to_vec();
    assert_eq!(
        h.counts, sent,
        "after {fault:?} the driver returned other counts than the device produced"
    );
    (tdc, h)
}

#[test]
fn a_stalled_acquisition_is_repeated() {
    let (_, h) = acquire_after(TdcFault::Stall);
    assert_eq!(h.sequence, 2, "the first acquisition never produced a frame");
}

#[test]
fn a_corrupted_frame_is_discarded_and_reacquired() {
    let (_, h) = acquire_after(TdcFault::CorruptCrc);
    assert_eq!(h.sequence, 2);
    let rig = rig();
    let mut tdc = tdc(&rig);
    rig.inject(Fault::Tdc(TdcFault::CorruptCrc));
    rig.inject(Fault::Tdc(TdcFault::CorruptCrc));
    let err = tdc.acquire().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Protocol);
    assert!(err.to_string().contains("CRC"), "{err}");
}

#[test]
fn a_frame_split_over_short_reads_is_reassembled() {
    let (_, h) = acquire_after(TdcFault::ShortRead);
    assert_eq!(h.sequence, 1, "a split frame needs no second acquisition");
}

#[test]
fn a_truncated_frame_is_reacquired() {
    let (_, h) = acquire_after(TdcFault::Truncated);
    assert_eq!(h.sequence, 2);
}

#[test]
fn a_stale_frame_is_dropped() {
    let rig = rig();
    let mut tdc = tdc(&rig);
    tdc.acquire().unwrap();
    rig.inject(Fault::Tdc(TdcFault::StaleFrame));
    let h = tdc.acquire().unwrap();
    assert_eq!(h.sequence, 2);
    assert_eq!(h.counts, tdc.transport_mut().sent_counts(2).unwrap());
}

#[test]
fn overflow_is_flagged_not_hidden() {
    let (_, h) = acquire_after(TdcFault::Overflow);
    assert!(h.flags.overflow);
    let (_, clean) = acquire_after(TdcFault::ShortRead);
    assert!(!clean.flags.overflow);
}

#[test]
fn an_unplugged_histogrammer_is_reopened_and_reconfigured() {
    let (mut tdc, h) = acquire_after(TdcFault::Disconnect { refused_reopens: 0 });
    assert_eq!(h.config.bins, 512);
    // Settings were restored on the device, not just remembered by the driver.
    assert_eq!(tdc.status().unwrap().rates.sync, 10e6);
    let rig = rig();
    let mut tdc = tdc_fresh(&rig);
    rig.inject(Fault::Tdc(TdcFault::Disconnect { refused_reopens: 1 }));
    let err = tdc.acquire().unwrap_err();
    assert_eq!(err.kind(), ErrorKind::Disconnected);
    assert!(err.to_string().contains("periscope devices"), "{err}");
    // Plugged back in: the next acquisition reopens, reconfigures and succeeds.
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts.len(), 512);
}

fn tdc_fresh(rig: &Rig) -> UsbTdc<SimTdcTransport> {
    tdc(rig)
}

#[test]
fn acquiring_unconfigured_or_with_bad_settings_is_refused() {
    let rig = rig();
    let mut tdc = UsbTdc::new(rig.tdc_transport(), TIMEOUT);
    assert_eq!(tdc.acquire().unwrap_err().kind(), ErrorKind::Device);
    let bad = TdcConfig {
        bin_width: 16e-12,
        bins: 0,
        offset: 0.0,
        sync_divider: 1,
        acquisition: Duration::from_millis(1),
    };
    assert_eq!(tdc.configure(&bad).unwrap_err().kind(), ErrorKind::OutOfRange);
    let negative = TdcConfig {
        bins: 16,
        offset: -1e-9,
        ..bad
    };
    assert_eq!(
        tdc.configure(&negative).unwrap_err().kind(),
        ErrorKind::OutOfRange
    );
    let info = tdc.identify().unwrap();
    assert_eq!(info.model, "PTDC-SIM");
}

// ---- The laser watchdog and the paths that switch emission off --------------------

use periscope_drivers::galvo::protocol::encode_line;
use periscope_drivers::galvo::{Connector, PortConnector};
use periscope_sim::devices::EmissionCause;

/// How far a watchdog trip may land from its nominal time: the firmware evaluates it
/// exactly, so only the test's own scheduling adds to it.
const TRIP_SLACK: Duration = Duration::from_millis(60);

/// When emission went off at or after `since`, waiting up to `limit` for it.
fn wait_off(rig: &Rig, since: Instant, limit: Duration) -> Option<Instant> {
    loop {
        if let Some(t) = rig.off_since(since) {
            return Some(t);
        }
        if since.elapsed() > limit {
            return None;
        }
        std::thread::sleep(Duration::from_millis(1));
    }
}

#[test]
fn a_host_that_goes_silent_is_cut_off_by_the_watchdog() {
    let rig = rig();
    // A bare link: the host switches the laser on and then says nothing more, as a
    // daemon that died would.
    let mut link = rig.galvo_connector(Arm::Laser).connect().unwrap();
    let on = Instant::now();
    link.send(encode_line(0x01, "LASER ON").as_bytes()).unwrap();
    let mut buf = [0u8; 64];
    let n = link.receive(&mut buf, Duration::from_secs(1)).unwrap();
    assert!(
        buf[..n].starts_with(b"01 OK"),
        "{:?}",
        String::from_utf8_lossy(&buf[..n])
    );
    assert!(rig.emission());
    while rig.emission() {
        assert!(
            on.elapsed() < Duration::from_secs(2),
            "the watchdog never tripped"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    let change = *rig.emission_changes().last().unwrap();
    assert_eq!(change.cause, EmissionCause::Watchdog);
    let after = change.at - on;
    assert!(
        after >= Duration::from_millis(500) && after <= Duration::from_millis(500) + TRIP_SLACK,
        "tripped {after:?} after the last line; the timeout is 500 ms"
    );
    assert_eq!(rig.watchdog().1, 1);
}

/// `WDOG` counts the watchdog's trips since power-up (docs/protocols/galvo-serial.md):
/// a controller that loses power comes back counting from 0, as it comes back with
/// emission off and the 500 ms timeout. Until 2026-12-07 the trips from before the
/// power loss were still counted.
#[test]
fn a_power_loss_resets_the_watchdog_trip_count() {
    use periscope_drivers::galvo::protocol::decode_line;
    let rig = rig();
    // A bare link: a 50 ms watchdog, the laser on, then silence until it trips.
    let mut link = rig.galvo_connector(Arm::Laser).connect().unwrap();
    let mut ask = |tag: u8, body: &str| {
        let reply = exchange(link.as_mut(), encode_line(tag, body).trim_end());
        let (_, answer) = decode_line(reply.as_bytes()).unwrap();
        answer.to_owned()
    };
    assert_eq!(ask(0x01, "WDOG 50"), "OK 50 0");
    assert_eq!(ask(0x02, "LASER ON"), "OK");
    let on = Instant::now();
    while rig.emission() {
        assert!(
            on.elapsed() < Duration::from_secs(2),
            "the watchdog never tripped"
        );
        std::thread::sleep(Duration::from_millis(5));
    }
    assert_eq!(rig.watchdog(), (Duration::from_millis(50), 1));
    drop(link);
    // The controller loses power at a host's next request; the driver reconnects and
    // asks again.
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    laser.identify().unwrap();
    rig.inject(Fault::Galvo(
        Arm::Laser,
        GalvoFault::Disconnect { refused_connects: 0 },
    ));
    assert_eq!(laser.watchdog().unwrap(), (Duration::from_millis(500), 0));
    assert_eq!(rig.watchdog(), (Duration::from_millis(500), 0));
    assert!(!rig.emission());
}

/// The serial laser driver on `rig`'s laser controller, with a 100 ms watchdog.
fn wire_laser(rig: &Rig) -> SerialGalvo {
    SerialGalvo::new(
        SerialGalvoSettings {
            name: "laser".into(),
            limits: limits(20.0),
            timeout: TIMEOUT,
            settle: Duration::from_micros(300),
            watchdog: Some(Duration::from_millis(100)),
        },
        Box::new(rig.galvo_connector(Arm::Laser)),
    )
}

#[test]
fn the_drivers_keepalive_holds_emission_and_stops_with_the_driver() {
    let rig = rig();
    let mut laser = wire_laser(&rig);
    laser.set_emission(true).unwrap();
    assert_eq!(laser.watchdog().unwrap(), (Duration::from_millis(100), 0));
    // Ten timeouts without a single ordinary request: the keepalive feeds it.
    std::thread::sleep(Duration::from_secs(1));
    assert!(rig.emission(), "the keepalive did not hold emission on");
    assert_eq!(rig.watchdog().1, 0);
    // Dropped with emission on (a panic unwinding): LASER OFF on the way out.
    let dropped = Instant::now();
    drop(laser);
    let off = wait_off(&rig, dropped, Duration::from_secs(1))
        .expect("the laser is still on after the driver was dropped");
    assert!(off - dropped < Duration::from_millis(20), "{:?}", off - dropped);
    assert_eq!(rig.emission_changes().last().unwrap().cause, EmissionCause::Host);
}

/// A laser driver watching a run's progress (`Laser::watch_progress`) feeds the
/// watchdog while the run beats, and stops once the run has shown no progress for the
/// limit: the watchdog then switches the laser off. Both the wire driver and the
/// in-process one, each with a 100 ms watchdog.
#[test]
fn the_keepalive_stops_when_the_watched_run_stops_making_progress() {
    let limit = Duration::from_millis(300);
    let watchdog = Duration::from_millis(100);
    for wire in [true, false] {
        let rig = rig();
        let mut laser: Box<dyn Laser<Error = periscope_drivers::galvo::GalvoError>> = if wire {
            Box::new(wire_laser(&rig))
        } else {
            Box::new(rig.in_process_galvo(Arm::Laser, limits(20.0), Some(watchdog)))
        };
        let progress = Progress::new(limit);
        laser.watch_progress(progress.clone());
        laser.set_emission(true).unwrap();
        // Beating every 20 ms for seven limits: emission holds.
        let start = Instant::now();
        while start.elapsed() < 7 * limit {
            progress.beat();
            std::thread::sleep(Duration::from_millis(20));
        }
        assert!(rig.emission(), "wire {wire}: emission dropped while the run beat");
        assert_eq!(rig.watchdog().1, 0, "wire {wire}");
        // No more beats (a run stuck in a call): off by the watchdog within the limit
        // plus the watchdog's timeout, not before the limit.
        progress.beat();
        let last = Instant::now();
        let off = wait_off(&rig, last, Duration::from_secs(3))
            .unwrap_or_else(|| panic!("wire {wire}: the laser stayed on with the run stalled"));
        let change = *rig.emission_changes().last().unwrap();
        assert_eq!(change.cause, EmissionCause::Watchdog, "wire {wire}");
        assert!(
            off - last >= limit && off - last <= limit + watchdog + TRIP_SLACK,
            "wire {wire}: off {:?} after the last beat (limit {limit:?}, watchdog {watchdog:?})",
            off - last
        );
        drop(laser);
    }
}

#[test]
fn a_starved_firmware_thread_does_not_count_queued_keepalives_late() {
    // The firmware thread reads nothing for four timeouts while the driver's keepalive
    // goes on writing: a real controller would have taken every keepalive on time, so
    // the watchdog must not trip (it did, when lines were stamped as the thread read
    // them: the loaded-CI flake). Silence the firmware has seen still trips it
    // (`a_host_that_goes_silent_is_cut_off_by_the_watchdog`).
    let rig = rig();
    let mut laser = wire_laser(&rig);
    laser.set_emission(true).unwrap();
    rig.inject(Fault::Galvo(
        Arm::Laser,
        GalvoFault::Starve(Duration::from_millis(400)),
    ));
    assert!(laser.laser_state().unwrap().emission);
    std::thread::sleep(Duration::from_millis(600));
    assert!(
        rig.emission(),
        "the watchdog tripped on keepalives that waited in the line: {:?}",
        rig.emission_changes()
    );
    assert_eq!(rig.watchdog().1, 0);
    assert!(laser.laser_state().unwrap().emission);
    drop(laser);
    assert!(!rig.emission());
}

#[test]
fn an_emergency_off_lands_while_a_move_is_outstanding() {
    let rig = rig();
    let mut laser = galvo(&rig, Arm::Laser, 20.0);
    laser.set_emission(true).unwrap();
    let estop = laser.emergency_off();
    // The controller will answer the move only after 2 s; the driver waits for it.
    rig.inject(Fault::Galvo(
        Arm::Laser,
        GalvoFault::Stall(Duration::from_secs(2)),
    ));
    laser.move_to(angles(0.05, 0.05)).unwrap();
    let waiter = std::thread::spawn(move || {
        let r = laser.wait_settled(Duration::from_secs(5));
        (laser, r)
    });
    std::thread::sleep(Duration::from_millis(50));
    let pressed = Instant::now();
    estop.laser_off().unwrap();
    let off = wait_off(&rig, pressed, Duration::from_secs(1))
        .expect("LASER OFF out of band did not land within 1 s");
    assert!(off - pressed < Duration::from_millis(20), "{:?}", off - pressed);
    // The move still completes; the keepalive has stopped, so nothing turns it back on.
    let (mut laser, r) = waiter.join().unwrap();
    r.unwrap();
    assert!(!laser.laser_state().unwrap().emission);
}

/// A pair's emergency park from another thread while its driver waits on a settling
/// move: the out-of-band `PARK` lands at once (reported as sent: its answer is on the
/// link the driver reads), and latches the driver: the move it waited on ends
/// `Interrupted`, it sends no move from then on (the mirrors left parked), and its own
/// park still works, without waiting for the overridden move's answer. A closed
/// driver's handle reaches nothing.
#[test]
fn an_emergency_park_lands_while_a_move_is_outstanding_and_latches() {
    let rig = rig();
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    let park = spad.emergency_park();
    rig.inject(Fault::Galvo(Arm::Spad, GalvoFault::Stall(Duration::from_secs(1))));
    spad.move_to(angles(0.05, 0.05)).unwrap();
    let waiter = std::thread::spawn(move || {
        let r = spad.wait_settled(Duration::from_secs(5));
        (spad, r)
    });
    std::thread::sleep(Duration::from_millis(50));
    assert!(!rig.parked().1);
    let pressed = Instant::now();
    assert_eq!(park.park().unwrap(), Parked::Sent);
    while !rig.parked().1 {
        assert!(
            pressed.elapsed() < Duration::from_millis(100),
            "PARK out of band did not land: {:?}",
            rig.pointing()
        );
        std::thread::sleep(Duration::from_millis(1));
    }
    let (mut spad, r) = waiter.join().unwrap();
    assert_eq!(r.unwrap_err().kind(), ErrorKind::Interrupted);
    let e = spad.move_to(angles(0.1, 0.1)).unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Interrupted, "{e}");
    std::thread::sleep(Duration::from_millis(20));
    assert!(rig.parked().1, "{:?}", rig.pointing());
    spad.park().unwrap();
    drop(spad);
    assert_eq!(park.park().unwrap_err().kind(), ErrorKind::Disconnected);

    // The driver's own park with the overridden move's answer still to come: sent at
    // once, not after the move's stall.
    let mut spad = galvo(&rig, Arm::Spad, 20.0);
    let park = spad.emergency_park();
    rig.inject(Fault::Galvo(Arm::Spad, GalvoFault::Stall(Duration::from_secs(2))));
    spad.move_to(angles(-0.05, 0.05)).unwrap();
    std::thread::sleep(Duration::from_millis(20));
    park.park().unwrap();
    let t = Instant::now();
    spad.park().unwrap();
    assert!(t.elapsed() < Duration::from_millis(500), "{:?}", t.elapsed());
    assert!(rig.parked().1);
}

/// The firmware answers a `MOVE` an out-of-band `PARK` overrode with `ERR 9`, as
/// docs/protocols/galvo-serial.md asks of a controller, not `OK SETTLED` at a target
/// the pair never reached; a move no park touched is still answered settled.
#[test]
fn a_move_a_park_overrode_is_answered_interrupted() {
    use periscope_drivers::galvo::protocol::{ErrorCode, Reply, decode_line};
    let rig = rig();
    let mut link = rig.galvo_connector(Arm::Spad).connect().unwrap();
    // Reads lines until one with `tag` comes, for at most 3 s.
    let mut pending = Vec::new();
    let mut line_with = |link: &mut Box<dyn periscope_drivers::galvo::Link>, tag: u8| -> String {
        let t = Instant::now();
        loop {
            while let Some(end) = pending.iter().position(|&b| b == b'\n') {
                let line: Vec<u8> = pending.drain(..=end).collect();
                let (got, body) = decode_line(&line[..line.len() - 1]).unwrap();
                if got == tag {
                    return body.to_owned();
                }
            }
            assert!(
                t.elapsed() < Duration::from_secs(3),
                "no answer with tag {tag:02x}"
            );
            let mut buf = [0u8; 256];
            let n = link.receive(&mut buf, Duration::from_millis(100)).unwrap_or(0);
            pending.extend_from_slice(&buf[..n]);
        }
    };
    rig.inject(Fault::Galvo(
        Arm::Spad,
        GalvoFault::Stall(Duration::from_millis(500)),
    ));
    link.send(encode_line(0x01, "MOVE 0.0500000 0.0500000").as_bytes())
        .unwrap();
    std::thread::sleep(Duration::from_millis(50));
    link.send(encode_line(0x00, "PARK").as_bytes()).unwrap();
    assert_eq!(line_with(&mut link, 0x00), "OK");
    let moved = line_with(&mut link, 0x01);
    assert_eq!(
        Reply::parse(&moved),
        Some(Reply::Err(Some(ErrorCode::Interrupted), "interrupted by park")),
        "{moved}"
    );
    assert!(rig.parked().1);
    // A move nothing overrode.
    link.send(encode_line(0x02, "MOVE 0.0500000 0.0500000").as_bytes())
        .unwrap();
    let moved = line_with(&mut link, 0x02);
    assert!(moved.starts_with("OK SETTLED 0.05"), "{moved}");
    assert!(!rig.parked().1);
}

/// A port one host holds is refused to a second (the `serialport` crate opens ports
/// exclusively), and the refusal says the port is held, not that the controller is
/// unplugged; a path that is not there still says to check the cable and the path.
#[test]
fn a_port_another_host_holds_is_refused_as_held() {
    let rig = rig();
    let port = rig.serve_galvo_port(Arm::Spad).unwrap();
    let host = |path: &str| {
        SerialGalvo::new(
            SerialGalvoSettings {
                name: "spad".into(),
                limits: limits(20.0),
                timeout: TIMEOUT,
                settle: Duration::from_micros(300),
                watchdog: None,
            },
            Box::new(PortConnector {
                path: path.to_owned(),
                baud: 115_200,
            }),
        )
    };
    let mut first = host(port.path());
    first.identify().unwrap();
    let e = host(port.path()).identify().unwrap_err();
    assert_eq!(e.kind(), ErrorKind::Disconnected);
    assert!(
        e.to_string().contains("another program or process holds it"),
        "{e}"
    );
    let e = host("/dev/periscope-no-such-port").identify().unwrap_err();
    assert!(e.to_string().contains("plugged in"), "{e}");
    drop(first);
    host(port.path()).identify().unwrap();
}

#[test]
fn a_served_port_is_opened_by_path_and_outlives_its_hosts() {
    let rig = rig();
    let port = rig.serve_galvo_port(Arm::Laser).unwrap();
    let connector = || PortConnector {
        path: port.path().to_owned(),
        baud: 115_200,
    };
    let settings = || SerialGalvoSettings {
        name: "laser".into(),
        limits: limits(20.0),
        timeout: TIMEOUT,
        settle: Duration::from_micros(300),
        watchdog: None,
    };
    // One host identifies and goes; the firmware is still there for the next.
    let mut host = SerialGalvo::new(settings(), Box::new(connector()));
    assert_eq!(host.identify().unwrap().protocol, 2);
    drop(host);
    // The next switches the laser on and dies without a word: the watchdog ends it.
    let mut link = connector().connect().unwrap();
    link.send(encode_line(0x01, "LASER ON").as_bytes()).unwrap();
    let mut buf = [0u8; 64];
    link.receive(&mut buf, Duration::from_secs(1)).unwrap();
    assert!(rig.emission());
    let gone = Instant::now();
    drop(link);
    let off = wait_off(&rig, gone, Duration::from_secs(2)).expect("the watchdog did not end emission");
    assert_eq!(
        rig.emission_changes().last().unwrap().cause,
        EmissionCause::Watchdog
    );
    assert!(
        off - gone <= Duration::from_millis(500) + TRIP_SLACK,
        "{:?}",
        off - gone
    );
}

#[test]
fn a_long_acquisition_stops_within_the_poll_interval_and_is_aborted_on_the_device() {
    let rig = rig();
    let mut tdc = UsbTdc::new(rig.tdc_transport(), TIMEOUT);
    tdc.configure(&TdcConfig {
        bin_width: 16e-12,
        bins: 64,
        offset: 12e-9,
        sync_divider: 1,
        acquisition: Duration::from_secs(30),
    })
    .unwrap();
    let start = Instant::now();
    let stop_at = start + Duration::from_millis(100);
    let err = tdc.acquire_until(&|| Instant::now() >= stop_at).unwrap_err();
    let stopped = start.elapsed();
    assert_eq!(err.kind(), ErrorKind::Interrupted, "{err}");
    assert!(
        stopped < Duration::from_millis(100) + periscope_drivers::tdc::POLL * 3,
        "a 30 s dwell took {stopped:?} to stop"
    );
    // The aborted frame never turns up: a short acquisition afterwards gets its own.
    tdc.configure(&TdcConfig {
        bin_width: 16e-12,
        bins: 64,
        offset: 12e-9,
        sync_divider: 1,
        acquisition: Duration::from_millis(5),
    })
    .unwrap();
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts.len(), 64);
}

/// CRC-8/SMBUS written out from the protocol page (polynomial 0x07, init 0, no
/// reflection), independent of the drivers' implementation.
fn crc8(bytes: &[u8]) -> u8 {
    let mut c = 0u8;
    for &b in bytes {
        c ^= b;
        for _ in 0..8 {
            c = if c & 0x80 != 0 { (c << 1) ^ 0x07 } else { c << 1 };
        }
    }
    c
}

/// Sends one line to the simulated firmware and returns its reply line (without the
/// newline).
fn exchange(link: &mut dyn periscope_drivers::galvo::Link, line: &str) -> String {
    link.send(format!("{line}\n").as_bytes()).unwrap();
    let mut got = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(2);
    while !got.ends_with(b"\n") {
        assert!(Instant::now() < deadline, "no reply to {line:?}: {got:?}");
        let mut buf = [0u8; 256];
        let n = link.receive(&mut buf, Duration::from_millis(50)).unwrap();
        got.extend_from_slice(&buf[..n]);
    }
    String::from_utf8(got).unwrap().trim_end().to_owned()
}

/// The simulated firmware against the example lines of
/// `docs/protocols/galvo-serial.md`, typed in from the page (not made by our encoder):
/// it must parse each request and answer with the documented bytes.
#[test]
fn the_simulated_galvo_firmware_answers_the_documented_lines() {
    use periscope_drivers::galvo::Connector;
    assert_eq!(crc8(b"123456789"), 0xF4, "the page's check value");
    let rig = rig();
    let mut link = rig.galvo_connector(Arm::Laser).connect().unwrap();
    let link = link.as_mut();
    // Identity: the layout of the page's example, with this firmware's own words.
    let idn = exchange(link, "01 IDN*01");
    let (body, crc) = idn.split_once('*').unwrap();
    assert_eq!(
        u8::from_str_radix(crc, 16).unwrap(),
        crc8(body.as_bytes()),
        "{idn}"
    );
    let words: Vec<&str> = body.split(' ').collect();
    assert_eq!(
        (words[0], words[1], words[4], words[6]),
        ("01", "OK", "2", "LASER"),
        "{idn}"
    );
    for (request, reply) in [
        (
            "01 MOVE 0.1000000 -0.0500000*15",
            "01 OK SETTLED 0.1000000 -0.0500000*06",
        ),
        ("02 STAT*4D", "02 OK SETTLED 0.1000000 -0.0500000*22"),
        ("01 WDOG 250*BE", "01 OK 250 0*AF"),
        ("02 LASER ON*B0", "02 OK*FE"),
        ("01 LSTAT*3D", "01 OK ON CLOSED OUT*40"),
        ("00 KEEP*49", "00 OK*D2"),
        ("00 LASER OFF*5A", "00 OK*D2"),
        // A wrong checksum (the page's IDN line with CC 02): error 1, computed here.
        ("01 IDN*02", "01 ERR 1 bad checksum*A2"),
    ] {
        assert_eq!(exchange(link, request), reply, "answer to {request}");
    }
    assert!(!rig.emission());
    rig.set_interlock(false);
    assert_eq!(exchange(link, "01 LASER ON*08"), "01 ERR 6 interlock open*87");
    assert!(!rig.emission());
}

/// The simulated histogrammer against the bytes of `docs/protocols/tdc-usb.md`: the
/// documented `SET_CONFIG` is accepted and read back as sent, and `START` yields a
/// frame whose every field is read here by offset, with its CRC checked by zlib's
/// algorithm (`crc32fast`), not by our decoder.
#[test]
fn the_simulated_histogrammer_answers_the_documented_requests() {
    use periscope_drivers::tdc::UsbTransport;
    const CONFIG: [u8; 20] = [
        0x10, 0, 0, 0, 0x04, 0, 0, 0, 0xe0, 0x2e, 0, 0, 0x01, 0, 0, 0, 0xe8, 0x03, 0, 0,
    ];
    let rig = rig();
    let mut usb = rig.tdc_transport();
    let t = Duration::from_millis(100);
    usb.control_out(0x02, 0, 0, &CONFIG, t).unwrap();
    let mut back = [0u8; 20];
    assert_eq!(usb.control_in(0x03, 0, 0, &mut back, t).unwrap(), 20);
    assert_eq!(back, CONFIG);
    // START, sequence 0x0002_0001: wValue the low half, wIndex the high half.
    usb.control_out(0x04, 0x0001, 0x0002, &[], t).unwrap();
    let mut frame = Vec::new();
    let deadline = Instant::now() + Duration::from_secs(2);
    while frame.len() < 52 {
        assert!(Instant::now() < deadline, "no frame: {} bytes", frame.len());
        let mut buf = [0u8; 512];
        let n = usb
            .bulk_in(0x81, &mut buf, Duration::from_millis(20))
            .unwrap_or(0);
        frame.extend_from_slice(&buf[..n]);
    }
    let u32_at = |i: usize| u32::from_le_bytes(frame[i..i + 4].try_into().unwrap());
    assert_eq!(frame.len(), 52);
    assert_eq!(&frame[..8], b"PTDC\x01\x00\x20\x00");
    assert_eq!(u32_at(8), 0x0002_0001, "sequence");
    assert_eq!(u32_at(12) & !3, 0, "only the two documented flags");
    assert_eq!(
        (u32_at(16), u32_at(20), u32_at(24), u32_at(28)),
        (4, 16, 12_000, 1000)
    );
    assert_eq!(u32_at(48), crc32fast::hash(&frame[..48]));
    // GET_STATUS: idle again, one frame.
    let mut status = [0u8; 16];
    assert_eq!(usb.control_in(0x05, 0, 0, &mut status, t).unwrap(), 16);
    assert_eq!(status[0], 0, "idle");
    assert_eq!(u32::from_le_bytes(status[12..16].try_into().unwrap()), 1);
    // A config the page forbids (divider 0) is stalled.
    let mut zero_divider = CONFIG;
    zero_divider[12] = 0;
    assert!(usb.control_out(0x02, 0, 0, &zero_divider, t).is_err());
}

/// `GET_STATUS` reports the state docs/protocols/tdc-usb.md defines: 1 (acquiring)
/// while a `START`'s dwell runs, 0 (idle) before it, after an `ABORT`, and once the
/// dwell has ended with its frame waiting to be read. Until 2026-12-07 it always
/// reported idle.
#[test]
fn the_histogrammer_reports_acquiring_while_a_dwell_runs() {
    use periscope_drivers::tdc::UsbTransport;
    use periscope_drivers::tdc::protocol::WireConfig;
    let rig = rig();
    let mut usb = rig.tdc_transport();
    let t = Duration::from_millis(100);
    // 4 bins, a 500 ms dwell.
    let config = WireConfig {
        bin_width_ps: 16,
        bins: 4,
        offset_ps: 12_000,
        sync_divider: 1,
        acquisition_us: 500_000,
    };
    usb.control_out(0x02, 0, 0, &config.encode(), t).unwrap();
    let state = |usb: &mut SimTdcTransport| {
        let mut status = [0u8; 16];
        assert_eq!(usb.control_in(0x05, 0, 0, &mut status, t).unwrap(), 16);
        status[0]
    };
    assert_eq!(state(&mut usb), 0, "idle before START");
    usb.control_out(0x04, 1, 0, &[], t).unwrap();
    assert_eq!(state(&mut usb), 1, "acquiring while the dwell runs");
    usb.control_out(0x06, 0, 0, &[], t).unwrap();
    assert_eq!(state(&mut usb), 0, "idle after ABORT");
    usb.control_out(0x04, 2, 0, &[], t).unwrap();
    assert_eq!(state(&mut usb), 1, "acquiring while the dwell runs");
    std::thread::sleep(Duration::from_millis(600));
    assert_eq!(state(&mut usb), 0, "idle once the dwell has ended");
    // Its frame waits to be read, whole.
    let mut frame = [0u8; 512];
    assert_eq!(usb.bulk_in(0x81, &mut frame, t).unwrap(), 52);
    assert_eq!(
        u32::from_le_bytes(frame[8..12].try_into().unwrap()),
        2,
        "sequence"
    );
}

// ---- In process ------------------------------------------------------------------
//
// The same controller model and histogrammer reached without a wire, as the daemon's
// `sim.devices = "in-process"` does: what they model must match the wire-level devices.

/// The three acquisitions of an LOS point and two NLOS pairs, through any devices.
fn three_acquisitions(
    rig: &Rig,
    laser: &mut (impl GalvoPair<Error = periscope_drivers::galvo::GalvoError> + Laser),
    spad: &mut impl GalvoPair<Error = periscope_drivers::galvo::GalvoError>,
    tdc: &mut impl Histogrammer<Error = periscope_drivers::tdc::TdcError>,
) -> Vec<Vec<u32>> {
    let (l, s) = rig.origins();
    let look = |o| GalvoPose::looking(o, -DVec3::Z, DVec3::Y).unwrap();
    let mut out = Vec::new();
    laser.set_diffuser(true).unwrap();
    laser.set_emission(true).unwrap();
    spad.move_settled(
        look(s).angles_for(DVec3::new(0.2, -0.1, 0.0)).unwrap(),
        Duration::from_secs(1),
    )
    .unwrap();
    out.push(tdc.acquire().unwrap().counts);
    laser.set_diffuser(false).unwrap();
    for (xi, xd) in [(-0.1, 0.1), (0.03, -0.07)] {
        laser
            .move_settled(
                look(l).angles_for(DVec3::new(xi, 0.0, 0.0)).unwrap(),
                Duration::from_secs(1),
            )
            .unwrap();
        spad.move_settled(
            look(s).angles_for(DVec3::new(xd, 0.02, 0.0)).unwrap(),
            Duration::from_secs(1),
        )
        .unwrap();
        out.push(tdc.acquire().unwrap().counts);
    }
    laser.set_emission(false).unwrap();
    out
}

fn in_process_tdc(rig: &Rig) -> periscope_sim::devices::InProcessTdc {
    let mut tdc = rig.in_process_tdc();
    tdc.configure(&TDC_CONFIG).unwrap();
    tdc
}

#[test]
fn in_process_devices_measure_the_same_counts_as_the_wire_devices() {
    let wire_rig = rig();
    let wire = three_acquisitions(
        &wire_rig,
        &mut galvo(&wire_rig, Arm::Laser, 20.0),
        &mut galvo(&wire_rig, Arm::Spad, 20.0),
        &mut tdc(&wire_rig),
    );
    let local_rig = rig();
    let local = three_acquisitions(
        &local_rig,
        &mut local_rig.in_process_galvo(Arm::Laser, limits(20.0), None),
        &mut local_rig.in_process_galvo(Arm::Spad, limits(20.0), None),
        &mut in_process_tdc(&local_rig),
    );
    let total: u64 = wire.iter().flatten().map(|&c| u64::from(c)).sum();
    assert!(total > 100, "too few counts to compare: {total}");
    assert_eq!(wire, local, "the in-process devices measured different counts");
    assert_eq!(wire_rig.pointing(), local_rig.pointing());
}

#[test]
fn in_process_controllers_refuse_what_the_firmware_refuses() {
    let rig = rig();
    let mut spad = rig.in_process_galvo(Arm::Spad, limits(10.0), None);
    assert_eq!((spad.identify().unwrap().protocol), 2);
    // The configured limits, then the firmware's own.
    let err = spad.move_to(angles(0.3, 0.0)).unwrap_err();
    assert_eq!(err.kind(), ErrorKind::OutOfRange);
    let mut wide = rig.in_process_galvo(Arm::Spad, limits(40.0), None);
    assert_eq!(
        wide.move_to(angles(0.5, 0.0)).unwrap_err().kind(),
        ErrorKind::OutOfRange
    );
    assert_eq!(
        spad.move_to(angles(f64::NAN, 0.0)).unwrap_err().kind(),
        ErrorKind::OutOfRange
    );
    assert_eq!(rig.pointing().1, angles(0.0, 0.0));
    // Settling takes the firmware's settling time.
    let start = Instant::now();
    spad.move_settled(angles(0.05, -0.02), Duration::from_secs(1))
        .unwrap();
    assert!(start.elapsed() >= Duration::from_micros(300));
    assert_eq!(rig.pointing().1, angles(0.05, -0.02));
    spad.park().unwrap();
    assert_eq!(rig.pointing().1, angles(0.0, 0.0));
    // The SPAD arm has no laser; the interlock gates the laser arm's.
    assert_eq!(spad.set_emission(true).unwrap_err().kind(), ErrorKind::Device);
    let mut laser = rig.in_process_galvo(Arm::Laser, limits(20.0), None);
    rig.set_interlock(false);
    assert_eq!(laser.set_emission(true).unwrap_err().kind(), ErrorKind::Interlock);
    assert!(!rig.emission());
    rig.set_interlock(true);
    laser.set_emission(true).unwrap();
    rig.set_interlock(false);
    assert!(!laser.laser_state().unwrap().emission);
}

#[test]
fn the_in_process_laser_goes_off_by_its_off_switch_and_when_dropped() {
    let rig = rig();
    let mut laser = rig.in_process_galvo(Arm::Laser, limits(20.0), Some(Duration::from_millis(60)));
    // The keepalive holds emission on well past the watchdog while it is wanted.
    laser.set_emission(true).unwrap();
    std::thread::sleep(Duration::from_millis(250));
    assert!(rig.emission(), "the watchdog tripped under a live keepalive");
    assert_eq!(rig.watchdog(), (Duration::from_millis(60), 0));
    // The out-of-band switch, from another thread, while the device is held.
    let off = laser.emergency_off();
    assert!(off.is_open());
    std::thread::spawn(move || off.laser_off().unwrap())
        .join()
        .unwrap();
    assert!(!rig.emission());
    // The switch latches: this driver stays off (`an_emergency_off_latches_against_a_racing_laser_on`).
    assert_eq!(
        laser.set_emission(true).unwrap_err().kind(),
        ErrorKind::Interrupted
    );
    drop(laser);
    // Dropped with emission wanted (a run abandoned, a panic unwinding): off.
    let mut laser = rig.in_process_galvo(Arm::Laser, limits(20.0), Some(Duration::from_millis(60)));
    laser.set_emission(true).unwrap();
    let off = laser.emergency_off();
    drop(laser);
    assert!(!rig.emission());
    assert!(!off.is_open());
}

#[test]
fn the_in_process_histogrammer_reports_overflow_and_unplugging() {
    let rig = rig();
    let mut tdc = in_process_tdc(&rig);
    assert!(!tdc.acquire().unwrap().flags.overflow);
    rig.inject(Fault::Tdc(TdcFault::Overflow));
    assert!(tdc.acquire().unwrap().flags.overflow);
    // Unplugged, and one reopen refused, as on the wire: one acquisition fails, the
    // next finds it back with its settings (the driver restores them).
    rig.unplug_tdc(1);
    assert_eq!(tdc.acquire().unwrap_err().kind(), ErrorKind::Disconnected);
    let h = tdc.acquire().unwrap();
    assert_eq!(h.counts.len(), 512);
    // Acquiring before configuring is refused.
    let mut fresh = rig.in_process_tdc();
    assert_eq!(fresh.acquire().unwrap_err().kind(), ErrorKind::Device);
}

/// An emergency off latches, on the wire driver and the in-process one alike: the
/// driver it came from refuses `LASER ON` from then on (kind `Interrupted`), and a
/// switch-on racing the stop from another thread never leaves the laser on. Without
/// the latch a run that had passed its checkpoint switched the laser back on after an
/// e-stop's direct off.
#[test]
fn an_emergency_off_latches_against_a_racing_laser_on() {
    fn check<L: Laser<Error = periscope_drivers::galvo::GalvoError> + Send + 'static>(
        rig: &Rig,
        open: &dyn Fn() -> L,
    ) {
        // Off, then on: refused, and the laser stays off.
        let mut laser = open();
        laser.set_emission(true).unwrap();
        let estop = laser.emergency_off();
        estop.laser_off().unwrap();
        // The stop's LASER OFF goes out of band: on the wire it lands a moment later.
        let off_soon = || {
            let t = Instant::now();
            while rig.emission() && t.elapsed() < Duration::from_secs(1) {
                std::thread::sleep(Duration::from_millis(1));
            }
            !rig.emission()
        };
        let err = laser.set_emission(true).unwrap_err();
        assert_eq!(err.kind(), ErrorKind::Interrupted, "{err}");
        assert!(err.to_string().contains("emergency stop"), "{err}");
        assert!(off_soon());
        // Off still works, and a driver opened afresh may switch on again.
        laser.set_emission(false).unwrap();
        drop(laser);
        let mut fresh = open();
        fresh.set_emission(true).unwrap();
        fresh.set_emission(false).unwrap();
        drop(fresh);
        // Racing: one thread switches on over and over while the stop comes.
        for round in 0..20 {
            let mut laser = open();
            let estop = laser.emergency_off();
            let racer = std::thread::spawn(move || {
                let until = Instant::now() + Duration::from_millis(300);
                let mut refused = false;
                while !refused && Instant::now() < until {
                    refused = laser.set_emission(true).is_err();
                }
                (laser, refused)
            });
            std::thread::sleep(Duration::from_micros(200 * round));
            // Early rounds stop a driver that has not connected yet: nothing to deliver
            // (an error), but the latch holds all the same.
            let _ = estop.laser_off();
            let (laser, refused) = racer.join().unwrap();
            assert!(refused, "round {round}: LASER ON was not refused after the stop");
            assert!(off_soon(), "round {round}: the laser stayed on after the stop");
            drop(laser);
        }
    }
    let rig = rig();
    check(&rig, &|| galvo(&rig, Arm::Laser, 20.0));
    check(&rig, &|| rig.in_process_galvo(Arm::Laser, limits(20.0), None));
}

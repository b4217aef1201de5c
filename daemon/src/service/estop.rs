//! The e-stop: the laser off first (through the running run's direct path, else
//! through the laser controller opened for the purpose), then both arms parked, then
//! the queue held. Nothing queued in front of it can block it.
use super::*;
use periscope_drivers::Parked;

impl Service {
    /// Switches the running run's laser off through its direct path, if a run holds
    /// the devices (for signal handlers: quick, waits for nothing but a mutex).
    pub fn laser_off_now(&self) {
        let off = self.direct().laser_off.clone();
        if let Some(off) = off
            && let Err(e) = off.laser_off()
        {
            tracing::warn!(error = %e, "direct laser off failed");
        }
    }

    /// Parks the running run's arms through its own drivers, if a run holds the
    /// devices (for a forced exit: the run did not reach its checkpoint in time).
    /// Latches those drivers: the run moves neither arm again.
    pub fn park_now(&self) {
        // Cloned out first: the stop path's lock is not held through the wait.
        let park = self.direct().park.clone();
        crate::signals::park_within(park);
    }

    /// Emergency stop. In this order: the laser off through the running run's direct
    /// path (an out-of-band `LASER OFF` to the laser controller that nothing pending
    /// can hold up), the run aborted (it parks both arms on its way out), queued runs
    /// held as paused. A run that does not reach its checkpoint within 2 s has each
    /// arm parked through its own driver's [`periscope_drivers::EmergencyPark`] (the hardware keeps the
    /// ports and channels it holds closed to anyone else). With no run holding the
    /// devices, if the direct path fails, or for an arm not parked that way, the laser
    /// controller is opened on its own (neither the SPAD arm nor the histogrammer is
    /// needed) and switched off, then each arm parked. Nothing stops
    /// it half-way: every step is tried, and the report says what was done.
    pub fn estop(&self) -> Result<EstopReport, ServiceError> {
        let t = Instant::now();
        // No run starts until this e-stop is done (a run queued or resumed meanwhile
        // raced it for the devices it was opening); the worker looks again after.
        let _estopping = EstopUnderWay::new(self);
        let mut report = EstopReport::default();
        // The stop path's own lock, never the service's, which a request writing
        // files may hold.
        let (running, direct, park, import) = {
            let d = self.direct();
            (d.run.clone(), d.laser_off.clone(), d.park.clone(), d.import)
        };
        // 1. The laser, directly. The run is told to abort first (an atomic store), so
        //    that a `LASER ON` the latched switch refuses it reads as the abort.
        if let Some((_, control)) = &running {
            control.abort_by("estop");
        }
        let mut laser_off = false;
        if let Some(off) = &direct {
            match off.laser_off() {
                Ok(()) => {
                    laser_off = true;
                    report.laser = DIRECT_OFF.into();
                    report.laser_off_s = Some(t.elapsed().as_secs_f64());
                }
                Err(e) => report.warnings.push(format!("direct laser off failed: {e}")),
            }
        }
        // With no run holding the devices (none, or one reconstructing an imported
        // capture), the laser controller opened on its own, now, before anything below
        // waits for the service's lock (step 5 parks the arms). A running capture's
        // devices are its own until it stops (step 4). (An import's e-stop switched the
        // laser off only at step 5, after the lock and up to 2 s of waiting for the
        // import to stop, until 2026-12-06.)
        let mut controller_off = false;
        if (running.is_none() || import) && !laser_off {
            match self.laser_controller_off() {
                Ok(()) => {
                    controller_off = true;
                    laser_off = true;
                    report.laser = CONTROLLER_OFF.into();
                    report.laser_off_s = Some(t.elapsed().as_secs_f64());
                }
                Err(e) => report.warnings.push(format!("laser controller: {e}")),
            }
        }
        // 2. The run (asked above). One that had already taken a pause at its
        //    checkpoint stops paused, as it was going to: held, not aborted.
        if let Some((id, control)) = &running {
            if control.requested() == crate::pipeline::Request::Abort {
                report.aborted = Some(id.clone());
            } else {
                report.held.push(id.clone());
            }
        }
        // 3. Queued runs are held (under the lock, so no resume or worker pick races it).
        //    A run the worker took from the queue since step 1 is held through its
        //    control (it stops at its next checkpoint, paused): its pipeline alone writes
        //    its run.json, and a state written here would race the pipeline's own.
        let mut picked = None;
        {
            let mut s = self.lock();
            // A submission between its reserved place and the queue (its run already
            // `queued` on disk) is held when it arrives (`queue_admitted`).
            s.estop_holds += 1;
            if let Some((id, control)) = s.current.as_ref()
                && running.as_ref().is_none_or(|(r, _)| r != id)
            {
                control.pause_by("estop");
                report.held.push(id.clone());
                picked = Some((id.clone(), control.clone()));
            }
            let running_id = s.current.as_ref().map(|(id, _)| id.clone());
            let queued: Vec<String> = s
                .queue
                .iter()
                .filter(|q| Some(*q) != running_id.as_ref())
                .filter(|q| self.info(q).is_ok_and(|i| i.state == RunState::Queued))
                .cloned()
                .collect();
            for id in queued {
                s.held.insert(id.clone());
                if let Err(e) = self.set_state(
                    &id,
                    RunState::Paused,
                    Some("held by an emergency stop; resume it to run".into()),
                    "estop",
                ) {
                    report.warnings.push(format!(
                        "queued run {id} is held (the worker will not start it), but its run.json could not record it: {e}; resume or abort it once the disk is fixed"
                    ));
                }
                report.held.push(id);
            }
        }
        // 4. Wait (bounded) for the run to reach its checkpoint: it parks the arms and
        //    confirms the laser off on its way out.
        //    A run the worker took since step 1 is waited for the same way: it may
        //    hold the controllers' ports while it opens them, and step 5 opens them
        //    (until 2026-12-07 it did so at once, racing the run for them).
        let mut stuck = None;
        if let Some((id, control)) = running.as_ref().or(picked.as_ref()) {
            let deadline = Instant::now() + ESTOP_RUN_WAIT;
            let mut s = self.lock();
            while s.current.as_ref().is_some_and(|(c, _)| c == id) && Instant::now() < deadline {
                s = self
                    .wake
                    .wait_timeout(s, Duration::from_millis(5))
                    .unwrap_or_else(|p| p.into_inner())
                    .0;
            }
            if s.current.as_ref().is_some_and(|(c, _)| c == id) {
                stuck = Some(id.clone());
            } else {
                // Only a run that says it made the instrument safe is believed; one
                // whose make-safe failed, or that never held the devices, leaves it
                // to step 5.
                match control.made_safe() {
                    Some(Ok(())) => {
                        report.parked = true;
                        if !laser_off {
                            laser_off = true;
                            report.laser = "off: the run switched it off on its way out".into();
                            report.laser_off_s = Some(t.elapsed().as_secs_f64());
                        }
                    }
                    Some(Err(e)) => report.warnings.push(format!(
                        "run {id} could not make the instrument safe on its way out ({e}); the devices were opened directly"
                    )),
                    None => {}
                }
            }
        }
        // 5. A run stuck short of its checkpoint: each arm parked through the run's own
        //    driver, since the hardware keeps a driver's port or channels closed to
        //    anyone else while the run holds it (a serial port is opened exclusively, a
        //    started DAQ task reserves its channels). Then whatever is still not safe
        //    (no run, one that did not make the instrument safe, a park that failed):
        //    each controller opened on its own (the laser's already, above, where no
        //    run held it).
        if !report.parked {
            // Laser arm, SPAD arm.
            let mut parked = [false; 2];
            if let Some(id) = &stuck {
                // Read again: a run that was still opening its devices at step 1 has
                // handed out its direct paths since.
                let (off, park) = {
                    let d = self.direct();
                    (d.laser_off.clone(), d.park.clone().or(park))
                };
                if !laser_off
                    && let Some(off) = off
                    && off.laser_off().is_ok()
                {
                    laser_off = true;
                    report.laser = DIRECT_OFF.into();
                    report.laser_off_s = Some(t.elapsed().as_secs_f64());
                }
                let mut sent = 0;
                for (done, handle) in parked.iter_mut().zip(park.iter().flatten()) {
                    match handle.park() {
                        Ok(Parked::Done) => *done = true,
                        Ok(Parked::Sent) => {
                            sent += 1;
                            report.warnings.push(format!(
                                "{}: PARK sent on run {id}'s own link, unconfirmed (the run's thread holds the \
                                 controller's answers): check that the arm is parked",
                                handle.describe()
                            ));
                        }
                        Err(e) => report.warnings.push(format!(
                            "{} through run {id}'s own driver: {e}",
                            handle.describe()
                        )),
                    }
                }
                report.warnings.push(format!(
                    "run {id} did not reach its checkpoint within {} s; {}",
                    ESTOP_RUN_WAIT.as_secs_f64(),
                    if parked == [true, true] {
                        "both arms were parked through its own drivers"
                    } else if sent > 0 {
                        "the arms were sent to park through its own drivers, and the devices opened directly to confirm it"
                    } else {
                        "the devices were opened directly"
                    }
                ));
            }
            if !parked[0] || !laser_off {
                let controller = if controller_off {
                    Ok(())
                } else {
                    self.laser_controller_off()
                };
                match controller {
                    Ok(()) => {
                        parked[0] = true;
                        if !laser_off {
                            report.laser = CONTROLLER_OFF.into();
                            report.laser_off_s = Some(t.elapsed().as_secs_f64());
                            laser_off = true;
                        }
                    }
                    Err(e) => report.warnings.push(format!("laser controller: {e}")),
                }
            }
            if !parked[1] {
                match self.park_spad() {
                    Ok(()) => parked[1] = true,
                    Err(e) => report.warnings.push(format!("SPAD arm: {e}")),
                }
            }
            report.parked = parked == [true, true];
        }
        if !laser_off {
            report.laser = "UNCONFIRMED: no path to the laser controller answered; the controller's watchdog ends emission within its timeout, or switch the laser off at the interlock".into();
        }
        report.seconds = t.elapsed().as_secs_f64();
        {
            let mut s = self.lock();
            s.last_safe = Some(format!("{} (e-stop)", report.laser));
            // What was read before the e-stop is not the instrument after it.
            s.reading = None;
            s.refresh = true;
            self.wake.notify_all();
        }
        tracing::warn!(laser = %report.laser, parked = report.parked, seconds = report.seconds, "emergency stop");
        Ok(report)
    }

    /// Opens the laser controller alone: laser off, then park.
    pub(super) fn laser_controller_off(&self) -> Result<(), String> {
        let _devices = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let mut controller = self.backend.laser_arm().map_err(|e| e.to_string())?;
        let off = controller.laser.set_emission(false).map_err(|e| e.to_string());
        let park = controller.arm.park().map_err(|e| e.to_string());
        off?;
        park
    }

    /// Opens the SPAD arm's controller alone and parks it.
    pub(super) fn park_spad(&self) -> Result<(), String> {
        let _devices = self.devices.lock().unwrap_or_else(|p| p.into_inner());
        let mut spad = self.backend.spad_arm().map_err(|e| e.to_string())?;
        spad.park().map_err(|e| e.to_string())
    }
}

/// The report's laser line when the running run's direct path switched it off.
const DIRECT_OFF: &str = "off: out-of-band LASER OFF to the laser controller";

/// Counts an e-stop under way in [`Service::estops`] while it lives, and wakes the
/// worker when it ends.
struct EstopUnderWay<'a>(&'a Service);

impl<'a> EstopUnderWay<'a> {
    fn new(service: &'a Service) -> Self {
        service.estops.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        EstopUnderWay(service)
    }
}

impl Drop for EstopUnderWay<'_> {
    fn drop(&mut self) {
        self.0.estops.fetch_sub(1, std::sync::atomic::Ordering::SeqCst);
        // Under the lock, so the worker cannot be between its look and its wait.
        let _s = self.0.lock();
        self.0.wake.notify_all();
    }
}

/// The report's laser line when the e-stop opened the laser controller itself.
const CONTROLLER_OFF: &str = "off: LASER OFF through the laser controller, opened for the e-stop";

/// How long an e-stop waits for a running run to reach its checkpoint (and park)
/// before it opens the controllers itself.
pub(super) const ESTOP_RUN_WAIT: Duration = Duration::from_secs(2);

/// What an e-stop did.
#[derive(Debug, Default, Serialize, ToSchema)]
pub struct EstopReport {
    /// The run that was aborted, if one was running.
    pub aborted: Option<String>,
    /// What happened to the laser, and by which path.
    pub laser: String,
    /// Seconds from the request until LASER OFF was sent (`null`: not confirmed).
    pub laser_off_s: Option<f64>,
    /// Whether both arms were parked.
    pub parked: bool,
    /// Runs held as paused: the queued ones, one the worker took while the e-stop
    /// ran, and a running one that had already taken a pause at its checkpoint.
    pub held: Vec<String>,
    /// Steps that failed (each was tried regardless).
    pub warnings: Vec<String>,
    /// Seconds from the request until every step was done.
    pub seconds: f64,
}

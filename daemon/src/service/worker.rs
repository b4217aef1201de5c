//! The worker thread: it owns the instrument between runs, runs queued plans one at a
//! time, reads the devices while idle, and forwards each run's events to its stream
//! clients.
use super::*;

impl Service {
    /// Starts the worker thread that runs queued plans, one at a time.
    pub fn start_worker(self: &Arc<Self>) -> std::thread::JoinHandle<()> {
        let me = Arc::clone(self);
        std::thread::Builder::new()
            .name("instrument".into())
            .spawn(move || me.worker())
            .expect("the worker thread starts")
    }

    pub(super) fn worker(self: Arc<Self>) {
        loop {
            let (id, control) = {
                let mut s = self.lock();
                loop {
                    if s.shutdown {
                        return;
                    }
                    // A locked queue starts nothing (maintenance); the running run,
                    // if any, finishes.
                    let next = s
                        .queue
                        .iter()
                        .filter(|_| s.lock.is_none())
                        .filter(|_| self.estops.load(std::sync::atomic::Ordering::SeqCst) == 0)
                        .filter(|q| !s.held.contains(*q))
                        .find(|q| self.info(q).is_ok_and(|i| i.state == RunState::Queued))
                        .cloned();
                    let Some(id) = next else {
                        let interval = self.instrument.api.status_interval;
                        let stale = s.reading.as_ref().is_none_or(|r| r.at.elapsed() >= interval);
                        if s.refresh || stale {
                            s.refresh = false;
                            drop(s);
                            self.take_reading();
                            s = self.lock();
                        } else {
                            let wait = s
                                .reading
                                .as_ref()
                                .map_or(interval, |r| interval.saturating_sub(r.at.elapsed()));
                            s = self
                                .wake
                                .wait_timeout(s, wait.max(Duration::from_millis(10)))
                                .unwrap_or_else(|p| p.into_inner())
                                .0;
                        }
                        continue;
                    };
                    let control = Control::new();
                    self.set_current(&mut s, Some((id.clone(), control.clone())));
                    s.live = Live {
                        id: id.clone(),
                        stage: "starting".into(),
                        ..Live::default()
                    };
                    s.channels
                        .entry(id.clone())
                        .or_insert_with(|| broadcast::channel(EVENT_BUFFER).0);
                    break (id, control);
                }
            };
            tracing::info!(run = %id, "run starting");
            // The pipeline catches its own panics; this catches the rest (the worker's
            // own code), so a bug never freezes the queue or strands the e-stop.
            let result = match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                self.execute(&id, control.clone())
            })) {
                Ok(r) => r,
                Err(payload) => {
                    let e = PipelineError::Panicked {
                        stage: "worker",
                        message: pipeline::panic_message(payload.as_ref()),
                    };
                    self.direct().laser_off = None;
                    if let Err(off) = self.laser_controller_off() {
                        tracing::error!("after a panic, the laser controller could not be reached: {off}");
                    }
                    if let Err(park) = self.park_spad() {
                        tracing::error!("after a panic, the SPAD arm could not be parked: {park}");
                    }
                    let dir = self.runs_dir.join(&id);
                    if let Ok(mut info) = RunInfo::load(&dir) {
                        info.state = RunState::Failed;
                        info.error = Some(e.to_string());
                        let _ = info.save(&dir);
                    }
                    Err(e)
                }
            };
            let stale = result.as_ref().is_err_and(|e| self.record_unrecorded_end(&id, e));
            let mut s = self.lock();
            if stale {
                s.stale.insert(id.clone());
            }
            self.set_current(&mut s, None);
            // The reading from before the run says nothing of the instrument the run
            // leaves (a run that could not switch its laser off): unknown until the
            // worker reads it again, at once.
            s.reading = None;
            s.refresh = true;
            s.channels.remove(&id);
            match &result {
                Ok(()) | Err(PipelineError::Aborted(_)) => {
                    s.queue.retain(|q| q != &id);
                    match control.made_safe() {
                        Some(Ok(())) => {
                            s.last_safe = Some(format!("laser off, arms parked (end of run {id})"))
                        }
                        Some(Err(e)) => {
                            tracing::error!(run = %id, "the run could not make the instrument safe: {e}")
                        }
                        None => {}
                    }
                }
                // Paused or suspended: resumable, it keeps its place.
                Err(PipelineError::Paused(_) | PipelineError::Suspended { .. }) => {}
                Err(_) => {
                    s.queue.retain(|q| q != &id);
                }
            }
            if let Err(e) = self.persist(&s) {
                tracing::error!("{e}");
            }
            self.wake.notify_all();
            drop(s);
            self.touch(&id);
            if let Ok(info) = self.info(&id) {
                self.metrics.run_finished(state_name(info.state));
            }
            match result {
                Ok(()) => tracing::info!(run = %id, "run completed"),
                Err(e) => tracing::warn!(run = %id, "run stopped: {e}"),
            }
        }
    }

    /// After a run stopped with `e` (worker thread, the run still current so nothing
    /// else writes its run.json): if its run.json still says queued or running, the
    /// pipeline could not record its end (the store refused, or it failed before it
    /// could), so it is recorded here as failed, resumable, with the error, rather
    /// than left looking queued or running with nothing working on it. Returns
    /// whether it still reads so (the store refused this too).
    pub(super) fn record_unrecorded_end(&self, id: &str, e: &PipelineError) -> bool {
        // Another process is writing the run: its run.json is that process's to write.
        if matches!(e, PipelineError::InUse(_)) {
            return false;
        }
        let dir = self.runs_dir.join(id);
        match RunInfo::load(&dir) {
            Ok(mut info) if matches!(info.state, RunState::Queued | RunState::Running) => {
                info.state = RunState::Failed;
                info.error = Some(e.to_string());
                if let Err(io) = info.save(&dir) {
                    tracing::error!(run = %id, "could not record the run's end ({e}) in {}: {io}", dir.display());
                    return true;
                }
                false
            }
            Ok(_) => false,
            Err(io) => {
                tracing::error!(run = %id, "could not read {}: {io}", dir.display());
                false
            }
        }
    }

    pub(super) fn execute(self: &Arc<Self>, id: &str, control: Control) -> Result<(), PipelineError> {
        let dir = self.runs_dir.join(id);
        // A resumed run's pairs stored before: the live count starts from them, so the
        // pairs counter (by how far the count moves), the pair rate and the ETA count
        // only what this session measures (until 2026-12-07 each resume counted the
        // earlier sessions' pairs again).
        if let Ok(info) = RunInfo::load(&dir) {
            let mut s = self.lock();
            if s.live.id == id {
                s.live.pairs_done = info.pairs_done;
                s.live.pairs_total = info.pairs_total;
            }
        }
        let events = EventSink::open(&dir).map_err(|e| PipelineError::Storage {
            path: dir.clone(),
            source: e,
        })?;
        // The run's events reach the live state and the stream clients through a
        // forwarding thread: the capture's own thread only queues them, so it never
        // waits for the service's lock, whatever the API's readers do with it.
        // The queue is bounded (`EventQueue`): while the forwarder waits for the lock
        // (requests writing files under it), the live displays' per-pair events are
        // coalesced, so the measurement neither waits nor makes the queue grow.
        let (queue, rx) = EventQueue::new(EVENT_QUEUE);
        let tx = Arc::new(Mutex::new(Some(queue)));
        {
            let tx = Arc::clone(&tx);
            events.listen(move |ev| {
                if let Some(q) = &mut *tx.lock().unwrap_or_else(|p| p.into_inner()) {
                    q.send(ev);
                }
            });
        }
        let me = Arc::clone(self);
        let run_id = id.to_owned();
        let queue = Arc::clone(&tx);
        let forwarder = std::thread::Builder::new()
            .name("run-events".into())
            .spawn(move || {
                let mut last_sent = [Instant::now() - PAIR_EVENT_INTERVAL; 3];
                loop {
                    match rx.recv_timeout(EVENT_PUMP) {
                        Ok(ev) => me.on_event(&run_id, &ev, &mut last_sent),
                        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break,
                    }
                    // What waits in the queue's backlog and slots moves on as the
                    // channel makes room, not only when the run next emits (a run
                    // suspended for an open door emits nothing for minutes).
                    if let Some(q) = &mut *queue.lock().unwrap_or_else(|p| p.into_inner()) {
                        q.pump();
                    }
                }
            });
        // Closed on every way out, an unwinding one included: the forwarder ends only
        // once the queue's sender is gone (it polled for ever after a panic here).
        let closing = CloseQueue(Arc::clone(&tx));
        let forwarder = match forwarder {
            Ok(f) => Some(f),
            Err(e) => {
                tracing::warn!(run = %id, error = %e, "no thread for the run's events; its stream clients see none");
                None
            }
        };
        // An imported capture is read and reconstructed without the devices.
        let import = RunInfo::load(&dir).is_ok_and(|i| i.import.is_some());
        self.lock().live.import = import;
        self.direct().import = import;
        // Run::open records a run that never started (paused, aborted or failed,
        // resumable) itself.
        let result = if import {
            self.execute_import(&dir, control, events)
        } else {
            Run::open(&dir, control, Some(events), Some(self.backend.as_ref())).and_then(|run| {
                {
                    let mut d = self.direct();
                    d.laser_off = Some(run.emergency_off());
                    d.park = Some(run.emergency_park());
                }
                run.execute().map(|_| ())
            })
        };
        // Every event queued so far (and held back) reaches the clients before the
        // worker closes the run's channel.
        drop(closing);
        if let Some(f) = forwarder {
            let _ = f.join();
        }
        result
    }

    pub(super) fn on_event(&self, id: &str, ev: &RunEvent, last_sent: &mut [Instant; 3]) {
        match ev {
            RunEvent::StageStarted { .. } => self.touch(id),
            RunEvent::StageFinished { stage, seconds } => {
                self.metrics.stage_finished(stage.name(), *seconds);
                self.touch(id);
            }
            _ => {}
        }
        let mut s = self.lock();
        if s.live.id == id {
            let live = &mut s.live;
            match ev {
                RunEvent::StageStarted { stage } => {
                    live.stage = stage.name().into();
                    if stage.name() == "capture" {
                        live.capture_started = Some((Instant::now(), live.pairs_done));
                        live.counts = 0;
                    }
                }
                RunEvent::Planned { pairs, .. } => live.pairs_total = *pairs,
                RunEvent::Pair {
                    done, total, counts, ..
                } => {
                    // Pair events may come coalesced (their counts summed): the pairs
                    // are counted by how far `done` moved.
                    self.metrics
                        .pairs_measured(done.saturating_sub(live.pairs_done) as u64, *counts);
                    live.counts += counts;
                    live.pairs_done = *done;
                    live.pairs_total = *total;
                    if live.capture_started.is_none() {
                        live.capture_started = Some((Instant::now(), *done));
                    }
                }
                RunEvent::Train(t) => {
                    if let Some(loss) = train_loss(t) {
                        live.loss = Some(loss);
                    }
                }
                RunEvent::Safety {
                    emission,
                    interlock_closed,
                    diffuser_in,
                    unix_ms,
                } => {
                    let state = periscope_drivers::LaserState {
                        emission: *emission,
                        interlock_closed: *interlock_closed,
                        diffuser_in: *diffuser_in,
                    };
                    live.laser = Some((state, Instant::now(), unix_ms / 1e3));
                }
                RunEvent::Histogram {
                    pair,
                    laser_deg,
                    spad_deg,
                    dwell_us,
                    bins,
                    ..
                } => {
                    let counts: u64 = bins.iter().map(|&b| u64::from(b)).sum();
                    live.histogram = Some(LiveHistogram {
                        laser_deg: *laser_deg,
                        spad_deg: *spad_deg,
                        signal_rate: counts as f64 / (*dwell_us as f64 * 1e-6).max(1e-9),
                        pair: *pair,
                        at: Instant::now(),
                    });
                }
                _ => {}
            }
        }
        let Some(tx) = s.channels.get(id).cloned() else {
            return;
        };
        // Serialised without the service's lock (a snapshot is thousands of Gaussians).
        drop(s);
        if tx.receiver_count() == 0 {
            return;
        }
        // Per-pair and per-LOS-point progress is forwarded at a display rate (and the
        // last one always), so clients cost the capture nothing measurable.
        // Histograms likewise, on their own clock (each forwarded one is the newest).
        let progress = match ev {
            RunEvent::Pair { done, total, .. } | RunEvent::LosPoint { done, total } => {
                Some((0, done == total))
            }
            RunEvent::Histogram { .. } => Some((1, false)),
            RunEvent::Safety { .. } => Some((2, false)),
            _ => None,
        };
        if let Some((clock, last)) = progress {
            if !last && last_sent[clock].elapsed() < PAIR_EVENT_INTERVAL {
                return;
            }
            last_sent[clock] = Instant::now();
        }
        // Display-only events wait while the streams hold their budget for clients
        // that do not read (the next one goes out once they catch up or the ring
        // drops what they did not read); the rest are small and always go.
        if ev.display_only()
            && self.stream_bytes.load(Ordering::Relaxed) >= self.stream_display_budget.load(Ordering::Relaxed)
        {
            return;
        }
        let value = serde_json::to_value(ev).unwrap_or_default();
        let name = event_name(&value);
        // A send fails only when no client listens; that is fine.
        let _ = tx.send(StreamEvent {
            name,
            json: Arc::new(HeldJson::new(value.to_string(), &self.stream_bytes)),
        });
    }
}

pub(super) fn train_loss(t: &periscope_recon::gtr::TrainEvent) -> Option<f64> {
    match t {
        periscope_recon::gtr::TrainEvent::Epoch { loss, .. } => Some(*loss),
        _ => None,
    }
}

pub(super) fn event_name(v: &serde_json::Value) -> Arc<str> {
    v.get("event").and_then(|e| e.as_str()).unwrap_or("event").into()
}

/// A run's events on their way to its forwarder thread, which waits for the service's
/// lock: a bounded queue that the run's threads (the capture, the trainer) never wait
/// on. The live displays' per-pair events (pairs, LOS points, histograms, safety
/// readings) and the fit's snapshots have a slot per kind where the latest waits while
/// the queue is full, a pair's photon counts summed over those it replaced. Every
/// other event waits in a backlog, what is held in the slots going first, so the
/// forwarder sees every kind in order and the last of each. The backlog is bounded too:
/// past [`EVENT_BACKLOG`] its oldest training events are dropped from the live stream
/// (they are in `events.jsonl`); the rare others (stages, outputs, the end) are always
/// kept.
struct EventQueue {
    tx: std::sync::mpsc::SyncSender<RunEvent>,
    held: [Option<RunEvent>; 5],
    backlog: std::collections::VecDeque<RunEvent>,
    coalesced: u64,
    dropped: u64,
}

/// The most events [`EventQueue`]'s backlog holds before it drops training events.
const EVENT_BACKLOG: usize = 1024;

/// How often the forwarder moves on what waits in a run's [`EventQueue`] when no event
/// comes.
const EVENT_PUMP: std::time::Duration = std::time::Duration::from_millis(100);

impl EventQueue {
    fn new(capacity: usize) -> (EventQueue, std::sync::mpsc::Receiver<RunEvent>) {
        let (tx, rx) = std::sync::mpsc::sync_channel(capacity);
        let q = EventQueue {
            tx,
            held: Default::default(),
            backlog: std::collections::VecDeque::new(),
            coalesced: 0,
            dropped: 0,
        };
        (q, rx)
    }

    /// The slot of a live-display event's kind.
    fn slot(ev: &RunEvent) -> Option<usize> {
        match ev {
            RunEvent::Pair { .. } => Some(0),
            RunEvent::LosPoint { .. } => Some(1),
            RunEvent::Histogram { .. } => Some(2),
            RunEvent::Safety { .. } => Some(3),
            RunEvent::Train(periscope_recon::gtr::TrainEvent::Snapshot { .. }) => Some(4),
            _ => None,
        }
    }

    fn send(&mut self, ev: &RunEvent) {
        self.drain();
        let Some(i) = Self::slot(ev) else {
            // What is held goes first, so every kind stays in order.
            let held = self.held.iter_mut().filter_map(Option::take);
            self.backlog.extend(held);
            self.backlog.push_back(ev.clone());
            self.drain();
            self.bound();
            return;
        };
        let mut ev = ev.clone();
        if let Some(before) = self.held[i].take() {
            // Behind one already held: it joins it, so its kind stays in order.
            if let (RunEvent::Pair { counts, .. }, RunEvent::Pair { counts: earlier, .. }) =
                (&mut ev, &before)
            {
                *counts += earlier;
            }
        }
        if !self.backlog.is_empty() {
            self.hold(i, ev);
        } else if let Err(std::sync::mpsc::TrySendError::Full(ev)) = self.tx.try_send(ev) {
            self.hold(i, ev);
        }
    }

    fn hold(&mut self, i: usize, ev: RunEvent) {
        self.held[i] = Some(ev);
        self.coalesced += 1;
        if self.coalesced.is_power_of_two() {
            tracing::warn!(
                coalesced = self.coalesced,
                "the run's event forwarder is behind: live pair, histogram, safety and snapshot events are coalesced"
            );
        }
    }

    /// Moves on what waits, as far as the channel has room, without waiting: the
    /// backlog, then (with the backlog sent) what the slots hold. The forwarder calls
    /// it, so nothing waits for the run's next event.
    fn pump(&mut self) {
        self.drain();
        if self.backlog.is_empty() {
            for i in 0..self.held.len() {
                let Some(ev) = self.held[i].take() else { continue };
                if let Err(std::sync::mpsc::TrySendError::Full(ev)) = self.tx.try_send(ev) {
                    self.held[i] = Some(ev);
                    return;
                }
            }
        }
    }

    /// Sends what the backlog holds while there is room, without waiting.
    fn drain(&mut self) {
        while let Some(ev) = self.backlog.pop_front() {
            match self.tx.try_send(ev) {
                Ok(()) => {}
                Err(std::sync::mpsc::TrySendError::Full(ev)) => {
                    self.backlog.push_front(ev);
                    return;
                }
                // No forwarder: nobody to tell.
                Err(std::sync::mpsc::TrySendError::Disconnected(_)) => {
                    self.backlog.clear();
                    return;
                }
            }
        }
    }

    /// Past [`EVENT_BACKLOG`], drops the oldest training events from the backlog.
    fn bound(&mut self) {
        while self.backlog.len() > EVENT_BACKLOG {
            let Some(at) = self.backlog.iter().position(|e| matches!(e, RunEvent::Train(_))) else {
                return;
            };
            self.backlog.remove(at);
            self.dropped += 1;
            if self.dropped.is_power_of_two() {
                tracing::warn!(
                    dropped = self.dropped,
                    "the run's event forwarder is behind: training events are left out of the live stream (events.jsonl has them)"
                );
            }
        }
    }

    /// Sends everything, the backlog and then what is held, waiting for room: at the
    /// run's end, from the worker, with the run's threads done.
    fn flush(&mut self) {
        for ev in self.backlog.drain(..) {
            let _ = self.tx.send(ev);
        }
        for ev in self.held.iter_mut().filter_map(Option::take) {
            let _ = self.tx.send(ev);
        }
    }
}

/// Sends everything `queue` holds and closes it (the forwarder then ends). The queue
/// is taken out under the lock and flushed outside it: a guard held through the flush
/// (an `if let`'s scrutinee lives through its block, as it did until 2026-12-06) left
/// the forwarder, which pumps under the same lock between receives, waiting on it
/// while the flush waited on a full channel only the forwarder drains: the worker
/// never let the run go.
fn close_queue(queue: &Mutex<Option<EventQueue>>) {
    let taken = queue.lock().unwrap_or_else(|p| p.into_inner()).take();
    if let Some(mut q) = taken {
        q.flush();
    }
}

/// Closes the run's event queue when dropped ([`close_queue`]).
struct CloseQueue(Arc<Mutex<Option<EventQueue>>>);

impl Drop for CloseQueue {
    fn drop(&mut self) {
        close_queue(&self.0);
    }
}

impl Drop for EventQueue {
    fn drop(&mut self) {
        self.flush();
    }
}

#[cfg(test)]
mod event_queue_tests {
    use super::*;

    fn pair(done: usize, counts: u64) -> RunEvent {
        RunEvent::Pair {
            done,
            total: 100,
            counts,
            peak_bin: 0,
            flagged: false,
        }
    }

    /// With the forwarder stalled, the queue never holds more than its capacity, the
    /// pair events held back keep the latest pair and every photon, and an event that
    /// must not be lost brings what is held with it, in order.
    fn epoch(step: usize) -> RunEvent {
        RunEvent::Train(periscope_recon::gtr::TrainEvent::Epoch {
            epoch: 0,
            step,
            loss: 1.0,
            pairs: 10,
            primitives: 10,
        })
    }

    /// What waits in the backlog and the slots reaches the forwarder once the channel
    /// has room, without another event from the run (one suspended for an open door
    /// emits nothing for minutes): the forwarder pumps it.
    #[test]
    fn the_forwarder_moves_on_what_waits_without_another_event() {
        let (mut q, rx) = EventQueue::new(2);
        q.send(&pair(1, 1));
        q.send(&pair(2, 1));
        q.send(&pair(3, 1)); // held: the channel is full
        q.send(&RunEvent::StageStarted {
            stage: crate::events::Stage::Reconstruction,
        }); // the held pair and this wait in the backlog
        assert_eq!(rx.try_iter().count(), 2);
        q.pump();
        let mut seen: Vec<RunEvent> = rx.try_iter().collect();
        q.pump();
        seen.extend(rx.try_iter());
        assert!(
            matches!(seen.last(), Some(RunEvent::StageStarted { .. })),
            "{seen:?}"
        );
        assert!(matches!(seen[0], RunEvent::Pair { done: 3, .. }), "{seen:?}");
        // A safety reading held behind a full channel goes too.
        q.send(&pair(4, 1));
        q.send(&pair(5, 1));
        q.send(&RunEvent::Safety {
            emission: false,
            interlock_closed: false,
            diffuser_in: false,
            unix_ms: 0.0,
        });
        assert_eq!(rx.try_iter().count(), 2);
        q.pump();
        assert!(rx.try_iter().any(|e| matches!(e, RunEvent::Safety { .. })));
    }

    /// With the forwarder stalled, neither the capture nor the trainer waits: a flood
    /// of training events and the stage events among them return at once, the backlog
    /// stays bounded by dropping training events only, and once the forwarder reads
    /// again every stage event arrives, in order, after the pairs before it.
    #[test]
    fn a_stalled_forwarder_never_makes_the_run_wait() {
        let (mut q, rx) = EventQueue::new(4);
        let (done_tx, done) = std::sync::mpsc::channel();
        let sender = std::thread::spawn(move || {
            for k in 0..5_000 {
                q.send(&epoch(k));
                if k % 1_000 == 0 {
                    q.send(&pair(k + 1, 1));
                    q.send(&RunEvent::StageStarted {
                        stage: crate::events::Stage::Capture,
                    });
                }
            }
            done_tx.send(q.backlog.len()).unwrap();
            q
        });
        let backlog = done
            .recv_timeout(std::time::Duration::from_secs(10))
            .expect("a send waited for the stalled forwarder");
        assert!(backlog <= EVENT_BACKLOG, "{backlog}");
        let mut q = sender.join().unwrap();
        let end = std::thread::spawn(move || rx.iter().collect::<Vec<_>>());
        q.flush();
        drop(q);
        let seen = end.join().unwrap();
        let stages: Vec<usize> = seen
            .iter()
            .enumerate()
            .filter(|(_, e)| matches!(e, RunEvent::StageStarted { .. }))
            .map(|(i, _)| i)
            .collect();
        assert_eq!(stages.len(), 5, "every stage event");
        let pairs: Vec<usize> = seen
            .iter()
            .enumerate()
            .filter(|(_, e)| matches!(e, RunEvent::Pair { .. }))
            .map(|(i, _)| i)
            .collect();
        assert_eq!(pairs.len(), 5, "every pair event");
        assert!(
            pairs.iter().zip(&stages).all(|(p, s)| p < s),
            "each pair goes ahead of the stage event after it: {pairs:?} {stages:?}"
        );
        assert!(
            matches!(seen.last(), Some(RunEvent::Train(_))),
            "the last training event is kept"
        );
    }

    /// The run's end with the channel full and events waiting behind it, the
    /// forwarder pumping under the queue's lock as the worker's does: every event
    /// arrives and the close returns.
    #[test]
    fn closing_a_full_queue_does_not_wait_on_the_forwarder_it_feeds() {
        let (mut q, rx) = EventQueue::new(2);
        q.send(&pair(1, 1));
        q.send(&pair(2, 1));
        for _ in 0..3 {
            q.send(&RunEvent::StageStarted {
                stage: crate::events::Stage::Reconstruction,
            });
        }
        let queue = Arc::new(Mutex::new(Some(q)));
        let forwarder = {
            let queue = Arc::clone(&queue);
            std::thread::spawn(move || {
                let mut seen = 0;
                loop {
                    match rx.recv_timeout(std::time::Duration::from_millis(5)) {
                        Ok(_) => seen += 1,
                        Err(std::sync::mpsc::RecvTimeoutError::Timeout) => {}
                        Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => break seen,
                    }
                    if let Some(q) = &mut *queue.lock().unwrap_or_else(|p| p.into_inner()) {
                        q.pump();
                    }
                }
            })
        };
        let (done_tx, done) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            close_queue(&queue);
            let _ = done_tx.send(());
        });
        done.recv_timeout(std::time::Duration::from_secs(10))
            .expect("the close waited for good on the forwarder");
        assert_eq!(forwarder.join().unwrap(), 5, "every event");
    }

    #[test]
    fn a_full_queue_coalesces_pairs_keeping_their_counts_and_order() {
        let (mut q, rx) = EventQueue::new(4);
        for done in 1..=50 {
            q.send(&pair(done, 10));
        }
        let queued: Vec<RunEvent> = rx.try_iter().collect();
        assert_eq!(queued.len(), 4, "the bound");
        // Room again: the next pair takes the held ones' place and counts.
        q.send(&pair(51, 10));
        let mut seen: Vec<RunEvent> = queued;
        seen.extend(rx.try_iter());
        // The end, with the forwarder running again.
        let end = std::thread::spawn(move || rx.iter().collect::<Vec<_>>());
        q.send(&RunEvent::Completed);
        drop(q);
        seen.extend(end.join().unwrap());
        let (mut counts, mut last_done) = (0, 0);
        for ev in &seen {
            if let RunEvent::Pair { done, counts: c, .. } = ev {
                counts += c;
                if *done > 0 {
                    assert!(*done > last_done, "pairs out of order: {done} after {last_done}");
                    last_done = *done;
                }
            }
        }
        assert_eq!((counts, last_done), (510, 51), "every photon, and the last pair");
        assert!(
            matches!(seen.last(), Some(RunEvent::Completed)),
            "{:?}",
            seen.last()
        );
    }
}

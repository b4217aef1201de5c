//! Signals and panics. A panic hook switches every open laser off first, before the
//! panic is reported or unwound (printing a backtrace can take a tenth of a second).
//! SIGINT, SIGTERM and SIGHUP for `run`, `resume` and `serve`: the first makes the
//! instrument safe at once (the laser off through its direct path) and asks the work
//! to stop at its next checkpoint, with a deadline after which the process exits
//! anyway; a second exits at once, the laser already off. A dedicated thread waits for
//! them, so nothing depends on the async runtime or the worker being responsive.
use std::sync::atomic::{AtomicI32, Ordering};
use std::sync::{Arc, Mutex, Once};
use std::time::Duration;

/// After SIGINT, SIGTERM or SIGHUP, how long a run has to reach its checkpoint, park
/// and record its state before the process exits anyway (the laser is off from the
/// first moment): within the 2 s an operator or a service manager may expect.
pub const SIGNAL_GRACE: std::time::Duration = std::time::Duration::from_millis(1500);

use periscope_drivers::galvo::EmergencyOff;

/// The lasers of runs in this process, for the panic hook.
static LASERS: Mutex<Vec<EmergencyOff>> = Mutex::new(Vec::new());

/// Registers a run's laser with the panic hook (handles of closed drivers are dropped
/// as new ones come).
pub fn register_laser(off: EmergencyOff) {
    let mut lasers = LASERS.lock().unwrap_or_else(|p| p.into_inner());
    lasers.retain(EmergencyOff::is_open);
    lasers.push(off);
}

/// A panic the hook saw: when, in which thread, what it said and where.
#[derive(Clone, Debug)]
pub struct PanicNote {
    /// When the hook ran.
    pub at: std::time::Instant,
    /// The panicking thread's name (`unnamed` for a thread without one).
    pub thread: String,
    /// The panic's message and its source location.
    pub message: String,
}

impl std::fmt::Display for PanicNote {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "a panic in thread `{}`: {}", self.thread, self.message)
    }
}

/// The last panic in this process, for a run whose laser the hook switched off.
static PANICKED: Mutex<Option<PanicNote>> = Mutex::new(None);

/// The last panic in this process, if it came at or after `since`.
pub fn panicked_since(since: std::time::Instant) -> Option<PanicNote> {
    let last = PANICKED.lock().unwrap_or_else(|p| p.into_inner());
    last.as_ref().filter(|p| p.at >= since).cloned()
}

/// Installs the panic hook (once per process): every registered laser off, then the
/// panic noted ([`panicked_since`]), then the usual report. The binary installs it at
/// start; tests that inject panics too.
pub fn install_panic_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let report = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            // The list is locked only to add or drop a laser, briefly: wait up to 50 ms
            // for it rather than skip the lasers (a run registering its laser on another
            // thread at the moment of a panic), never for ever (a panic while it is held).
            let deadline = std::time::Instant::now() + std::time::Duration::from_millis(50);
            loop {
                match LASERS.try_lock() {
                    Ok(lasers) => {
                        for off in lasers.iter() {
                            off.try_laser_off();
                        }
                        break;
                    }
                    Err(std::sync::TryLockError::Poisoned(p)) => {
                        for off in p.into_inner().iter() {
                            off.try_laser_off();
                        }
                        break;
                    }
                    Err(std::sync::TryLockError::WouldBlock) if std::time::Instant::now() < deadline => {
                        std::thread::yield_now();
                    }
                    Err(std::sync::TryLockError::WouldBlock) => break,
                }
            }
            // Only after the lasers: formatting allocates.
            let payload = info.payload();
            let text = payload
                .downcast_ref::<&str>()
                .map(|s| (*s).to_owned())
                .or_else(|| payload.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "(no message)".into());
            let note = PanicNote {
                at: std::time::Instant::now(),
                thread: std::thread::current().name().unwrap_or("unnamed").to_owned(),
                message: match info.location() {
                    Some(l) => format!("{text} (at {}:{})", l.file(), l.line()),
                    None => text,
                },
            };
            if let Ok(mut last) = PANICKED.try_lock() {
                *last = Some(note);
            }
            report(info);
        }));
    });
}

/// The signal that asked this process to stop (0 if none), as its number.
static RECEIVED: AtomicI32 = AtomicI32::new(0);

/// The signal that asked the process to stop, if one did: its number.
pub fn received() -> Option<i32> {
    match RECEIVED.load(Ordering::SeqCst) {
        0 => None,
        n => Some(n),
    }
}

/// The conventional exit code for a process ended by signal `n`: 128 + n.
pub fn exit_code(n: i32) -> u8 {
    u8::try_from(128 + n).unwrap_or(1)
}

/// What a stop signal does.
pub trait OnSignal: Send + Sync + 'static {
    /// Makes the instrument safe now without waiting for anything: the direct laser
    /// off. Called on every signal and before a forced exit; must be quick.
    fn laser_off(&self);
    /// Asks the work to wind down (pause the run, shut the server down). Called once,
    /// after [`OnSignal::laser_off`].
    fn stop(&self, signal: &'static str);
    /// Parks the arms through the work's own drivers, without waiting for the work
    /// (its [`periscope_drivers::EmergencyPark`] handles): called before a forced exit,
    /// when the run has not reached its checkpoint to park them itself.
    fn park_now(&self);
}

/// How long a forced exit waits for the arms' direct parks ([`park_within`]).
pub const PARK_WAIT: Duration = Duration::from_millis(300);

/// Parks each arm through its handle on a thread of its own, waiting at most
/// [`PARK_WAIT`] for them all (a DAQ park waits for a write of the stuck run's to
/// return, up to its library's timeout): a forced exit is not held up longer.
pub fn park_within(handles: Option<[periscope_drivers::EmergencyPark; 2]>) {
    let Some(handles) = handles else { return };
    let (tx, rx) = std::sync::mpsc::channel();
    for handle in handles {
        let tx = tx.clone();
        let spawned = std::thread::Builder::new().name("park".into()).spawn(move || {
            if let Err(e) = handle.park() {
                eprintln!("direct park of {} failed: {e}", handle.describe());
            }
            let _ = tx.send(());
        });
        if let Err(e) = spawned {
            eprintln!("no thread to park an arm on ({e})");
        }
    }
    drop(tx);
    let deadline = std::time::Instant::now() + PARK_WAIT;
    while let Some(left) = deadline.checked_duration_since(std::time::Instant::now()) {
        if rx.recv_timeout(left).is_err() {
            return;
        }
    }
}

/// The signals that stop Periscope and their numbers.
#[cfg(unix)]
const SIGNALS: [(&str, i32); 3] = [("SIGINT", 2), ("SIGTERM", 15), ("SIGHUP", 1)];

/// Starts the signal thread. After the first signal the process has `grace` to finish
/// on its own (the run reaching its checkpoint, parking the arms, writing its state)
/// before it is ended with the laser off.
pub fn install(handler: Arc<dyn OnSignal>, grace: Duration) {
    let spawned = std::thread::Builder::new().name("signals".into()).spawn(move || {
        let Ok(rt) = tokio::runtime::Builder::new_current_thread().enable_all().build() else {
            tracing::warn!("no signal handling: the laser relies on the controller's watchdog");
            return;
        };
        rt.block_on(async move {
            // Listened for once, so a second signal sent while the first is handled is
            // not missed between two registrations.
            let mut signals = Signals::listen();
            let Some((name, n)) = signals.next().await else { return };
            RECEIVED.store(n, Ordering::SeqCst);
            handler.laser_off();
            eprintln!(
                "\n{name}: laser off; stopping at the next checkpoint (arms parked, data kept). \
                 Again to exit at once."
            );
            // Winding down may wait for a lock another thread holds over a stalled
            // disk (the service's, for a run's state): on a thread of its own, so the
            // grace and a second signal are answered whatever it waits for.
            let stopper = Arc::clone(&handler);
            if let Err(e) = std::thread::Builder::new()
                .name("signals-stop".into())
                .spawn(move || stopper.stop(name))
            {
                tracing::warn!("no thread to wind down on ({e}); winding down on the signal thread");
                handler.stop(name);
            }
            tokio::select! {
                _ = tokio::time::sleep(grace) => {
                    handler.laser_off();
                    handler.park_now();
                    eprintln!("still busy {} s after {name}: exiting with the laser off", grace.as_secs_f64());
                }
                again = signals.next() => {
                    handler.laser_off();
                    handler.park_now();
                    if let Some((name, _)) = again {
                        eprintln!("{name} again: exiting now with the laser off");
                    }
                }
            }
            std::process::exit(i32::from(exit_code(n)));
        });
    });
    if let Err(e) = spawned {
        tracing::warn!("no signal handling ({e}): the laser relies on the controller's watchdog");
    }
}

/// The stop signals, listened for from when they are made.
struct Signals {
    #[cfg(unix)]
    streams: Vec<(&'static str, i32, tokio::signal::unix::Signal)>,
}

impl Signals {
    #[cfg(unix)]
    fn listen() -> Signals {
        use tokio::signal::unix::{SignalKind, signal};
        let mut streams = Vec::new();
        for (name, n) in SIGNALS {
            match signal(SignalKind::from_raw(n)) {
                Ok(s) => streams.push((name, n, s)),
                Err(e) => tracing::warn!("cannot listen for {name}: {e}"),
            }
        }
        Signals { streams }
    }

    #[cfg(not(unix))]
    fn listen() -> Signals {
        Signals {}
    }

    /// The next stop signal; `None` when none can be listened for.
    #[cfg(unix)]
    async fn next(&mut self) -> Option<(&'static str, i32)> {
        let [(a, an, sa), (b, bn, sb), (c, cn, sc)] = &mut self.streams[..] else {
            // Fewer than three: wait on the first.
            let (name, n, s) = self.streams.first_mut()?;
            s.recv().await;
            return Some((name, *n));
        };
        tokio::select! {
            _ = sa.recv() => Some((*a, *an)),
            _ = sb.recv() => Some((*b, *bn)),
            _ = sc.recv() => Some((*c, *cn)),
        }
    }

    #[cfg(not(unix))]
    async fn next(&mut self) -> Option<(&'static str, i32)> {
        tokio::signal::ctrl_c().await.ok().map(|()| ("Ctrl-C", 2))
    }
}

/// The text of a panic payload.
pub fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_owned())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "a panic without a message".into())
}

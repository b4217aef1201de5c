//! Thread priorities: under load the capture comes first. The HTTP API's threads (its
//! async workers and its blocking pool) run at a lower scheduling priority (a higher
//! nice value) than the instrument's worker, so a flood of requests, however much CPU
//! it asks for, takes only what the capture leaves: the kernel's fair scheduler weighs
//! a thread at nice 10 about a tenth of one at nice 0. The API still gets the CPU
//! whenever the instrument does not need it, so an e-stop or a status read is answered
//! at once on an idle machine.
//!
//! This is the one module of the daemon with `unsafe`: two plain system calls through
//! `libc`, each with its reason beside it. Linux only (the nice value is per thread
//! there); elsewhere it does nothing.
#![allow(unsafe_code)]

/// The nice value of the API's threads (the instrument's stay at the process's own).
pub const API_NICE: i32 = 10;

/// Lowers the calling thread's scheduling priority to nice `nice` (never raises it:
/// an unprivileged process may not). Returns why it could not.
#[cfg(target_os = "linux")]
pub fn lower_current_thread(nice: i32) -> std::io::Result<()> {
    // SAFETY: gettid(2) takes no arguments, cannot fail and touches no memory.
    let tid = unsafe { libc::gettid() };
    let id = libc::id_t::try_from(tid).map_err(|_| std::io::Error::other("negative thread id"))?;
    // SAFETY: setpriority(2) takes three integers and touches no memory; with
    // PRIO_PROCESS and a thread id, Linux sets that one thread's nice value.
    let r = unsafe { libc::setpriority(libc::PRIO_PROCESS, id, nice) };
    if r == -1 {
        return Err(std::io::Error::last_os_error());
    }
    Ok(())
}

/// Elsewhere: nothing to do.
#[cfg(not(target_os = "linux"))]
pub fn lower_current_thread(_nice: i32) -> std::io::Result<()> {
    Ok(())
}

/// The calling thread's nice value (Linux; 0 elsewhere), for tests and logs.
pub fn current_nice() -> i32 {
    #[cfg(target_os = "linux")]
    {
        // /proc/thread-self/stat field 19 is the nice value; the command name (field
        // 2, in parentheses) may hold spaces, so count from its closing parenthesis.
        let stat = std::fs::read_to_string("/proc/thread-self/stat").unwrap_or_default();
        stat.rsplit_once(')')
            .and_then(|(_, rest)| rest.split_whitespace().nth(16))
            .and_then(|n| n.parse().ok())
            .unwrap_or(0)
    }
    #[cfg(not(target_os = "linux"))]
    0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_thread_lowers_its_own_priority_and_no_other() {
        if !cfg!(target_os = "linux") {
            return;
        }
        let before = current_nice();
        let lowered = std::thread::spawn(|| {
            lower_current_thread(current_nice() + 5).unwrap();
            current_nice()
        })
        .join()
        .unwrap();
        assert_eq!(lowered, before + 5);
        assert_eq!(current_nice(), before, "another thread's priority changed");
    }
}

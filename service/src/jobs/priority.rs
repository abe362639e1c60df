//! A job's threads run at a lower OS priority than serving's. Both want every core (libtorch's
//! OpenMP team, the solver's rayon pool); measured in `reports/service.md`, a job at the same
//! priority made serving's p99 about 11× its idle value. With a higher nice value the kernel
//! gives the cores to requests first and to the job whatever they leave, so an idle server
//! still adapts at full speed.

/// Raises the calling thread's nice value by `nice` (capped at 19; 0 leaves it). Threads it
/// starts later inherit the value; that includes the OpenMP team libtorch starts the first time
/// this thread runs a parallel operator (libgomp keeps one team per calling thread), so a job's
/// convolutions run at its priority too. Returns the new nice value, `None` where it could not
/// be changed (logged: the job then runs at serving's priority, which is slower, not wrong).
pub fn lower_this_thread(nice: i32) -> Option<i32> {
    if nice <= 0 {
        return None;
    }
    imp::lower(nice)
}

#[cfg(target_os = "linux")]
mod imp {
    /// Linux keeps a nice value per thread: PRIO_PROCESS with a thread id changes that thread
    /// only (POSIX's per-process rule does not hold there).
    pub fn lower(nice: i32) -> Option<i32> {
        // SAFETY: plain system calls on this thread's own id; errno is read right after.
        unsafe {
            let tid = libc::gettid() as libc::id_t;
            *libc::__errno_location() = 0;
            let current = libc::getpriority(libc::PRIO_PROCESS, tid);
            if current == -1 && *libc::__errno_location() != 0 {
                tracing::warn!("cannot read the job thread's priority: {}", std::io::Error::last_os_error());
                return None;
            }
            let target = (current + nice).min(19);
            if libc::setpriority(libc::PRIO_PROCESS, tid, target) != 0 {
                tracing::warn!("cannot lower the job thread's priority: {}", std::io::Error::last_os_error());
                return None;
            }
            Some(target)
        }
    }

    #[cfg(test)]
    pub fn current() -> i32 {
        // SAFETY: as above.
        unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) }
    }
}

#[cfg(not(target_os = "linux"))]
mod imp {
    pub fn lower(_nice: i32) -> Option<i32> {
        tracing::warn!("per-thread priorities are only set on Linux: the job runs at serving's priority");
        None
    }
}

#[cfg(all(test, target_os = "linux"))]
mod tests {
    use super::*;

    #[test]
    fn lowers_only_this_thread_and_what_it_starts_later() {
        let main = imp::current();
        let (mine, child) = std::thread::spawn(|| {
            let before = imp::current();
            let after = lower_this_thread(5).expect("raising one's own nice value needs no privilege");
            assert_eq!(after, (before + 5).min(19));
            assert_eq!(imp::current(), after);
            let child = std::thread::spawn(imp::current).join().unwrap();
            (after, child)
        })
        .join()
        .unwrap();
        assert_eq!(child, mine, "a thread started afterwards inherits the job's priority");
        assert_eq!(imp::current(), main, "other threads keep theirs");
        assert_eq!(lower_this_thread(0), None);
    }
}

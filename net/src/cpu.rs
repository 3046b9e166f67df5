//! This process's CPU time (user + system, every thread) and a token naming the process,
//! so that CPU seconds reported by several actors of one process (the embedded mode's
//! workers, a coordinator beside them) are counted once per process, not once per actor.

use std::sync::OnceLock;

/// CPU seconds this process has used so far (`CLOCK_PROCESS_CPUTIME_ID`: user + system
/// time of all its threads).
pub fn process_cpu_seconds() -> f64 {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ProcessCPUTime);
    t.tv_sec as f64 + t.tv_nsec as f64 * 1e-9
}

/// CPU nanoseconds the calling thread has used so far (`CLOCK_THREAD_CPUTIME_ID`): what
/// a step of work computed, not counting time its thread waited for a core.
pub fn thread_cpu_nanos() -> u64 {
    let t = rustix::time::clock_gettime(rustix::time::ClockId::ThreadCPUTime);
    t.tv_sec as u64 * 1_000_000_000 + t.tv_nsec as u64
}

/// A random token for this process, the same for every actor in it: two reports with
/// the same token measured the same clock.
pub fn process_token() -> u64 {
    static TOKEN: OnceLock<u64> = OnceLock::new();
    *TOKEN.get_or_init(|| {
        let mut b = [0u8; 8];
        // Falls back to the process id, unique on one host, if the OS has no randomness.
        match getrandom::fill(&mut b) {
            Ok(()) => u64::from_le_bytes(b),
            Err(_) => u64::from(std::process::id()),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_grows_with_work_and_the_token_is_stable() {
        let before = process_cpu_seconds();
        let thread_before = thread_cpu_nanos();
        let mut x = 0u64;
        // Spin until the clock moves (its resolution is far below this loop's cost).
        while process_cpu_seconds() <= before {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
        }
        std::hint::black_box(x);
        assert!(process_cpu_seconds() > before);
        assert!(
            thread_cpu_nanos() > thread_before,
            "this thread did the work"
        );
        assert_eq!(process_token(), process_token());
    }
}

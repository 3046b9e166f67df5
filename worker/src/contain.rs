//! Panic containment for tracing work and domain loads.
//!
//! A tracing thread that panics would die silently: its job would wait for credit that
//! never comes (until the coordinator's stall timeout), and every later job would have
//! one thread fewer. A load that panicked also left its domain marked "loading" for
//! ever, so every other thread skipped the domain as busy and the job hung
//! (docs/security.md "Hardening, second round", item 3: `dray render --translate 1e25,0,0`
//! with worker actors). Instead, a panic
//! while tracing a batch or a tile, or while loading a domain (reading it, building its
//! BVH, on this thread or on rayon's pool, which carries the panic back), fails that job
//! with the panic's message, and the thread goes on to the next piece of work. The
//! worker's shared state is behind locks that tolerate poisoning, and the work item's
//! own outputs are dropped with the failed job. Whatever else panics on a tracing
//! thread is caught by the thread's loop ([`crate::work::tracer_thread`]), which logs it
//! and goes on.

use std::panic::{AssertUnwindSafe, catch_unwind};

/// Run `f`; a panic inside it becomes `Err` with the panic's message.
pub(crate) fn contained<T>(f: impl FnOnce() -> T) -> Result<T, String> {
    contained_while("tracing", f)
}

/// Run `f`, which does `what` ("tracing", "loading a domain"); a panic inside it
/// becomes `Err` with the panic's message.
pub(crate) fn contained_while<T>(what: &str, f: impl FnOnce() -> T) -> Result<T, String> {
    catch_unwind(AssertUnwindSafe(f)).map_err(|payload| {
        // Bounded: the message goes to the coordinator and into GetJob.
        let message = dray_net::contain::panic_message(payload.as_ref());
        format!("internal error (a panic while {what}, contained): {message}")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_becomes_an_error_with_its_message_and_values_pass_through() {
        assert_eq!(contained(|| 7), Ok(7));
        let e = contained(|| -> u32 { panic!("index {} out of range", 9) }).unwrap_err();
        assert!(e.contains("index 9 out of range"), "{e}");
        let e = contained(|| -> u32 { std::panic::panic_any(5u8) }).unwrap_err();
        assert!(e.contains("without a message"), "{e}");
        let long = "x".repeat(10_000);
        let e = contained(|| -> u32 { panic!("{long}") }).unwrap_err();
        assert!(e.len() < 400, "{}", e.len());
    }
}

//! Stopping a load (or a package being cut) part-way.
//!
//! A coordinator loads a job's scene on a blocking thread while the job is PREPARING. A
//! job cancelled then (or a coordinator stopping) must not go on parsing or generating
//! for minutes and holding the memory it grows: [`load_cancellable`] loads with a flag
//! the loaders look at between pieces of work (every primitive, every 64 Ki elements of
//! a PLY, every slab of an isosurface, every glTF image), and a set flag ends the load
//! with [`SceneError::Cancelled`], dropping what was made.
//!
//! The flag is per thread, set for the duration of the call, so the many loader
//! functions need no extra parameter; every loader runs on the calling thread (none
//! spawns threads), so they all see it.

use std::cell::RefCell;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use dray_core::scene::Scene;

use crate::error::{Result, SceneError};

thread_local! {
    static FLAG: RefCell<Option<Arc<AtomicBool>>> = const { RefCell::new(None) };
}

/// How many elements a loop handles between two looks at the flag.
pub(crate) const CHECK_EVERY: usize = 1 << 16;

/// [`crate::load`], ended early with [`SceneError::Cancelled`] once `cancel` is set.
pub fn load_cancellable(spec: &str, cancel: &Arc<AtomicBool>) -> Result<Scene> {
    with_cancel(cancel, || crate::load(spec))
}

/// Run `f` (a load, or a package being cut into domains) so that the loaders and the
/// partitioner inside it stop with [`SceneError::Cancelled`] once `cancel` is set.
pub fn with_cancel<R>(cancel: &Arc<AtomicBool>, f: impl FnOnce() -> R) -> R {
    /// Puts back the caller's flag (a nested call, or none) however `f` ends.
    struct Restore(Option<Arc<AtomicBool>>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let previous = self.0.take();
            FLAG.with(|f| *f.borrow_mut() = previous);
        }
    }
    let previous = FLAG.with(|f| f.borrow_mut().replace(cancel.clone()));
    let _restore = Restore(previous);
    // No look before `f` starts: the loaders' own looks are what the tests reach.
    f()
}

#[cfg(test)]
thread_local! {
    /// Looks at the flag made on this thread, so tests can see that a loop looks.
    static CHECKS: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// How many times this thread has looked at its flag (tests only).
#[cfg(test)]
pub(crate) fn checks_made() -> usize {
    CHECKS.with(std::cell::Cell::get)
}

/// `Err(Cancelled)` when the load running on this thread was cancelled.
pub(crate) fn check() -> Result<()> {
    #[cfg(test)]
    CHECKS.with(|c| c.set(c.get() + 1));
    let cancelled = FLAG.with(|f| {
        f.borrow()
            .as_ref()
            .is_some_and(|flag| flag.load(Ordering::Relaxed))
    });
    if cancelled {
        Err(SceneError::Cancelled)
    } else {
        Ok(())
    }
}

/// [`check`] every [`CHECK_EVERY`] elements of a loop over `i`.
pub(crate) fn check_at(i: usize) -> Result<()> {
    if i.is_multiple_of(CHECK_EVERY) {
        check()
    } else {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_set_flag_ends_a_load_and_the_thread_forgets_it_afterwards() {
        let flag = Arc::new(AtomicBool::new(true));
        let err = load_cancellable("cornell", &flag).unwrap_err();
        assert!(matches!(err, SceneError::Cancelled), "{err}");
        // Outside the call nothing is cancelled.
        assert!(check().is_ok());
        flag.store(false, Ordering::Relaxed);
        assert!(load_cancellable("cornell", &flag).is_ok());
        assert!(crate::load("cornell").is_ok());
    }

    #[test]
    fn files_stop_too() {
        // Already set: the vertex loop sees it at its first row.
        let dir = std::env::temp_dir().join(format!("dray-cancel-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let ply = dir.join("tri.ply");
        std::fs::write(
            &ply,
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n\
             property float z\nelement face 1\nproperty list uchar int vertex_indices\n\
             end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n",
        )
        .unwrap();
        let spec = ply.to_str().unwrap();
        let flag = Arc::new(AtomicBool::new(false));
        assert!(load_cancellable(spec, &flag).is_ok());
        flag.store(true, Ordering::Relaxed);
        let err = load_cancellable(spec, &flag).unwrap_err();
        assert!(matches!(err, SceneError::Cancelled), "{err}");
        let _ = std::fs::remove_dir_all(&dir);
    }
}

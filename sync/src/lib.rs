//! Poison-tolerant locking, defined once for every dray crate.
//!
//! A `std::sync` lock is *poisoned* when a thread panics while holding it, and every
//! later `lock()` returns an error. dray's locks guard maps, queues, logs and counters
//! whose every update is one statement or leaves them consistent at each step, so the
//! data a panicking holder leaves behind is still valid; taking the guard anyway keeps
//! one failed request (already reported by its panic) from failing every later one on
//! the same lock. These helpers say that once instead of
//! `.lock().unwrap_or_else(|p| p.into_inner())` at every call.
//!
//! The crate has no dependencies, so the lowest crates (`dray-core`, `dray-net`, which
//! share no other) can both use it.

use std::sync::{Mutex, MutexGuard, RwLock, RwLockReadGuard, RwLockWriteGuard};

/// `m`'s guard, poisoned or not.
pub fn lock<T: ?Sized>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// A read guard of `l`, poisoned or not.
pub fn read<T: ?Sized>(l: &RwLock<T>) -> RwLockReadGuard<'_, T> {
    l.read().unwrap_or_else(|p| p.into_inner())
}

/// The write guard of `l`, poisoned or not.
pub fn write<T: ?Sized>(l: &RwLock<T>) -> RwLockWriteGuard<'_, T> {
    l.write().unwrap_or_else(|p| p.into_inner())
}

/// The value inside `m`, poisoned or not.
pub fn into_inner<T>(m: Mutex<T>) -> T {
    m.into_inner().unwrap_or_else(|p| p.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    /// Poisons `m` by panicking in a thread that holds its guard.
    fn poison(m: &Arc<Mutex<Vec<u32>>>) {
        let m2 = Arc::clone(m);
        let joined = std::thread::spawn(move || {
            let mut g = m2.lock().expect("not yet poisoned");
            g.push(2);
            panic!("poisoning on purpose");
        })
        .join();
        assert!(joined.is_err(), "the thread panicked");
        assert!(m.is_poisoned());
    }

    #[test]
    fn a_poisoned_mutex_still_gives_its_guard_and_value() {
        let m = Arc::new(Mutex::new(vec![1]));
        poison(&m);
        assert!(m.lock().is_err(), "std refuses a poisoned mutex");
        lock(&m).push(3);
        assert_eq!(*lock(&m), [1, 2, 3]);
        let m = Arc::try_unwrap(m).expect("the thread is gone");
        assert_eq!(into_inner(m), [1, 2, 3]);
    }

    #[test]
    fn a_poisoned_rwlock_still_reads_and_writes() {
        let l = Arc::new(RwLock::new(1u32));
        let l2 = Arc::clone(&l);
        let joined = std::thread::spawn(move || {
            let mut g = l2.write().expect("not yet poisoned");
            *g = 2;
            panic!("poisoning on purpose");
        })
        .join();
        assert!(joined.is_err() && l.is_poisoned());
        assert!(l.read().is_err(), "std refuses a poisoned lock");
        *write(&l) += 1;
        assert_eq!(*read(&l), 3);
    }
}

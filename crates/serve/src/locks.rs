//! The one way this crate takes a `std::sync::Mutex`.

use std::sync::{Mutex, MutexGuard};

/// Locks `m`, taking the data over from a holder that panicked (every critical section in
/// this crate leaves its data consistent at each step, so a panic elsewhere never makes it
/// unusable, and one failed request must not take the server down with it).
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

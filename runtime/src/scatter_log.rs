//! Scatter logs: the additions one chunk of a parallel launch made into one target while it
//! could not write directly, applied later in thread-id order (`crate::chunk_order`,
//! `crate::split`), and the pool of log buffers reused from one launch to the next.

use std::any::Any;
use std::sync::{Mutex, PoisonError};

use crate::array::{Array, Element};

/// The scatters one chunk made into one target, applied in thread-id order after the chunks ran.
pub struct ScatterLog(pub(crate) Option<Box<dyn ApplyLog>>);

impl ScatterLog {
    /// The log of `entries` (index, value) into `target`, in the order they were made.
    pub(crate) fn of<T: Element>(target: Array<T>, entries: Vec<(u32, T)>) -> Self {
        ScatterLog(Some(Box::new(TypedLog { target, entries })))
    }
}

pub(crate) trait ApplyLog: Send + Sync {
    /// Applies every entry, in log order.
    ///
    /// # Safety
    /// No other thread may write the target concurrently.
    unsafe fn apply(&self);
}

struct TypedLog<T: Element> {
    target: Array<T>,
    entries: Vec<(u32, T)>,
}

impl<T: Element> Drop for TypedLog<T> {
    fn drop(&mut self) {
        give_log(std::mem::take(&mut self.entries));
    }
}

/// Log buffers kept from one launch to the next. Fresh buffers would be faulted in from the
/// kernel at every launch, which made parallel launches about 3x slower
/// (docs/performance.md, "Deterministic scatter").
static LOG_POOL: Mutex<Vec<Box<dyn Any + Send>>> = Mutex::new(Vec::new());
/// At most this many buffers are kept (each at most a chunk's worth of entries).
const LOG_POOL_MAX: usize = 128;

pub(crate) fn take_log<T: Element>() -> Vec<(u32, T)> {
    let mut pool = LOG_POOL.lock().unwrap_or_else(PoisonError::into_inner);
    match pool.iter().rposition(|b| b.is::<Vec<(u32, T)>>()) {
        Some(k) => *pool.swap_remove(k).downcast().expect("checked by `is`"),
        None => Vec::new(),
    }
}

pub(crate) fn give_log<T: Element>(mut log: Vec<(u32, T)>) {
    if log.capacity() == 0 {
        return;
    }
    log.clear();
    let mut pool = LOG_POOL.lock().unwrap_or_else(PoisonError::into_inner);
    if pool.len() < LOG_POOL_MAX {
        pool.push(Box::new(log));
    }
}

impl<T: Element> ApplyLog for TypedLog<T> {
    unsafe fn apply(&self) {
        let p = self.target.data_ptr();
        for &(i, v) in &self.entries {
            (*p.add(i as usize)).acc(v);
        }
    }
}

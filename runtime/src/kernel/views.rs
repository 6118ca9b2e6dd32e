//! The views through which generated code reads and stores: [`Reader`], [`OptReader`],
//! [`Writer`], and the functions that make them over a launch's [`Exec`].

use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};

use super::exec::Exec;
use super::place::{checked, Place, Site, ToIndex};
use crate::array::{Array, Element};

/// Reads an array inside a kernel (`a[i]`).
pub struct Reader<T> {
    ptr: *const T,
    len: usize,
    place: Place,
}

impl<T: Element> Reader<T> {
    /// Element `i`, bounds-checked with the kernel's and parameter's names.
    #[inline(always)]
    pub fn get<I: ToIndex>(&self, i: I) -> T {
        let i = checked(i, self.len, &self.place);
        // SAFETY: in bounds; the launch holds the array's access lock and no thread of this
        // launch writes an array that the kernel reads (checked by the macro).
        unsafe { *self.ptr.add(i) }
    }
}

/// Reads an optional buffer (gradient or tangent); absent buffers read as zero.
pub struct OptReader<T> {
    ptr: Option<*const T>,
    len: usize,
    place: Place,
    /// Keeps the buffer alive even if the array drops it meanwhile.
    _buf: Option<Array<T>>,
}

impl<T: Element> OptReader<T> {
    /// Element `i` or zero.
    #[inline(always)]
    pub fn get<I: ToIndex>(&self, i: I) -> T {
        let i = checked(i, self.len, &self.place);
        match self.ptr {
            // SAFETY: in bounds, buffer held by the owned args for the launch.
            Some(p) => unsafe { *p.add(i) },
            None => T::zeroed(),
        }
    }
}

/// The claims of one launch on an array it stores into at indices the macro could not prove
/// distinct per thread (anything but `a[tid()] = v`): the first thread to store an element
/// claims it for the launch, and a store to it from another thread is refused with a panic
/// naming the kernel, the array, the index and both threads. So two threads never write one
/// element (which would be a data race, and a result that depends on scheduling), and the
/// adjoint, which hands each stored element's gradient to exactly one store, stays right.
#[derive(Clone, Copy)]
struct Claims {
    table: *const AtomicU64,
    epoch: u32,
}

impl Claims {
    #[inline(always)]
    fn claim(&self, i: usize, tid: usize, place: &Place) {
        // `tid + 1`, so that an entry's low half 0 means unclaimed in any epoch.
        if tid >= u32::MAX as usize {
            claim_overflow(place, tid);
        }
        let me = (u64::from(self.epoch) << 32) | (tid as u64 + 1);
        // SAFETY: `i` is in bounds (checked by the caller); the table has one entry per
        // element and lives as long as the array the view holds.
        let e = unsafe { &*self.table.add(i) };
        let cur = e.load(Ordering::Acquire);
        if cur == me {
            return;
        }
        if (cur >> 32) as u32 == self.epoch && cur as u32 != 0 {
            store_conflict(place, i, cur as u32 as usize - 1, tid);
        }
        if let Err(now) = e.compare_exchange(cur, me, Ordering::AcqRel, Ordering::Acquire) {
            if now != me {
                store_conflict(place, i, (now as u32 as usize).saturating_sub(1), tid);
            }
        }
    }
}

#[cold]
#[inline(never)]
fn store_conflict(place: &Place, i: usize, a: usize, b: usize) -> ! {
    let (a, b) = (a.min(b), a.max(b));
    let array = match place.name() {
        Some(n) => format!("array `{n}` (parameter `{}`)", place.site.param),
        None => format!("parameter `{}`", place.site.param),
    };
    panic!(
        "kernel `{}`: threads {a} and {b} both store to {array} at index {i}; the result would \
         depend on which runs last, and only one store can receive the gradient. Store at \
         `tid()` (or an index only this thread writes), or accumulate with `atomic_add`",
        place.site.kernel
    )
}

#[cold]
#[inline(never)]
fn not_own_index(place: &Place, i: usize, tid: usize) -> ! {
    panic!(
        "kernel `{}`: thread {tid} stores to parameter `{}` at index {i} through a view for \
         stores at the thread's own index",
        place.site.kernel, place.site.param
    )
}

#[cold]
#[inline(never)]
fn claim_overflow(place: &Place, tid: usize) -> ! {
    panic!(
        "kernel `{}`: thread {tid} stores to parameter `{}` at an index the macro cannot prove \
         is the thread's own, and such stores are checked only for launches of up to 2^32 \
         threads; store at `tid()` or split the launch",
        place.site.kernel, place.site.param
    )
}

/// Stores into an array inside a kernel (`a[i] = v`), or takes the gradient of a stored
/// element in the adjoint; absent buffers ignore stores and read as zero.
pub struct Writer<T> {
    ptr: Option<*mut T>,
    len: usize,
    place: Place,
    claims: Option<Claims>,
    /// The chunk's thread ids (see [`Exec`]).
    range: Range<usize>,
    /// Keeps the buffer (and its claim table) alive even if the array drops it meanwhile.
    _buf: Option<Array<T>>,
}

impl<T: Element> Writer<T> {
    fn new(
        of: &Array<T>,
        buf: Option<Array<T>>,
        site: &'static Site,
        distinct: bool,
        range: Range<usize>,
    ) -> Self {
        let claims = match (&buf, distinct) {
            (Some(b), false) => {
                let (table, epoch) = b.claims();
                Some(Claims {
                    table: table.as_ptr(),
                    epoch,
                })
            }
            _ => None,
        };
        Writer {
            ptr: buf.as_ref().map(|b| b.data_ptr()),
            len: of.len(),
            place: Place::of(of, site),
            claims,
            range,
            _buf: buf,
        }
    }

    #[inline(always)]
    fn slot<I: ToIndex>(&self, tid: usize, i: I) -> Option<*mut T> {
        let i = checked(i, self.len, &self.place);
        let p = self.ptr?;
        if !self.range.contains(&tid) {
            not_own_index(&self.place, i, tid);
        }
        match &self.claims {
            Some(c) => c.claim(i, tid, &self.place),
            // The macro proved the index is the thread id; this makes it so for any caller.
            None if i != tid => not_own_index(&self.place, i, tid),
            None => {}
        }
        // SAFETY: in bounds.
        Some(unsafe { p.add(i) })
    }

    /// `a[i] = v` by thread `tid`.
    #[inline(always)]
    pub fn store<I: ToIndex>(&self, tid: usize, i: I, v: T) {
        if let Some(p) = self.slot(tid, i) {
            // SAFETY: only this thread writes element `i` in this launch: the macro proved
            // the index is the thread id, or the claim above made it this thread's.
            unsafe { *p = v }
        }
    }

    /// The adjoint of `a[i] = v` by thread `tid`: returns the gradient of element `i` and
    /// zeroes it, so that an earlier store to the same element (overwritten by this one)
    /// receives nothing.
    #[inline(always)]
    pub fn take<I: ToIndex>(&self, tid: usize, i: I) -> T {
        match self.slot(tid, i) {
            // SAFETY: as in `store`.
            Some(p) => unsafe { std::mem::replace(&mut *p, T::zeroed()) },
            None => T::zeroed(),
        }
    }
}

// SAFETY: the raw pointers in views point into arrays kept alive by the launch's owned
// arguments; the launch contract (above) rules out conflicting access.
unsafe impl<T: Send> Send for Reader<T> {}
unsafe impl<T: Element> Send for OptReader<T> {}
unsafe impl<T: Element> Send for Writer<T> {}

fn opt_reader<T: Element>(
    of: &Array<T>,
    buf: Option<Array<T>>,
    exec: &Exec,
    site: &'static Site,
) -> OptReader<T> {
    exec.check(buf.as_ref(), false, site);
    OptReader {
        ptr: buf.as_ref().map(|b| b.data_ptr() as *const T),
        len: of.len(),
        place: Place::of(of, site),
        _buf: buf,
    }
}

fn writer_of<T: Element>(
    of: &Array<T>,
    buf: Option<Array<T>>,
    exec: &Exec,
    site: &'static Site,
    distinct: bool,
) -> Writer<T> {
    exec.check(buf.as_ref(), true, site);
    Writer::new(of, buf, site, distinct, exec.range.clone())
}

/// A reader of `a`.
#[inline]
pub fn reader<T: Element>(a: &Array<T>, exec: &Exec, site: &'static Site) -> Reader<T> {
    exec.check(Some(a), false, site);
    Reader {
        ptr: a.data_ptr(),
        len: a.len(),
        place: Place::of(a, site),
    }
}

/// A writer of `a`. `distinct`: the macro proved that every store indexes with the thread
/// id, so threads never store to one element (checked: a store elsewhere panics); otherwise
/// stores are claimed (see [`Writer`]).
#[inline]
pub fn writer<T: Element>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
    distinct: bool,
) -> Writer<T> {
    writer_of(a, Some(a.clone()), exec, site, distinct)
}

/// The adjoint view of a stored array: takes (reads and zeroes) the gradient of each stored
/// element (a no-op reading zeros if it has no gradient).
#[inline]
pub fn grad_taker<T: Element>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
    distinct: bool,
) -> Writer<T> {
    writer_of(a, a.grad_buffer(), exec, site, distinct)
}

/// A reader of `a`'s gradient (zeros if it has none).
#[inline]
pub fn grad_reader<T: Element>(a: &Array<T>, exec: &Exec, site: &'static Site) -> OptReader<T> {
    opt_reader(a, a.grad_buffer(), exec, site)
}

/// A reader of `a`'s tangent (zeros if it has none).
#[inline]
pub fn tangent_reader<T: Element>(a: &Array<T>, exec: &Exec, site: &'static Site) -> OptReader<T> {
    opt_reader(a, a.tangent_buffer(), exec, site)
}

/// A writer of `a`'s tangent (ignores stores if it has none).
#[inline]
pub fn tangent_writer<T: Element>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
    distinct: bool,
) -> Writer<T> {
    writer_of(a, a.tangent_buffer(), exec, site, distinct)
}

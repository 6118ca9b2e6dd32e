//! The interface between `#[diff_kernel]`'s output and the runtime: kernel traits, the
//! per-chunk views of arrays that generated code reads and writes through, and the
//! deterministic scatter logs behind `atomic_add`.
//!
//! Users do not implement these traits by hand; the macro does.

use std::any::Any;
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use crate::array::{AnyArray, Array, Element};
use crate::chunk_order::ChunkOrder;

/// How a kernel uses one of its parameters (decided by the macro from the source).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Access {
    /// A value parameter (scalar, vector, index): not an array.
    Value,
    /// An array the kernel reads.
    Read,
    /// An array the kernel stores to (`a[i] = v`).
    Store,
    /// An array the kernel accumulates into (`a.atomic_add(i, v)`).
    Atomic,
    /// An array passed but not used.
    Unused,
}

impl Access {
    /// Whether the kernel writes the array.
    pub fn writes(self) -> bool {
        matches!(self, Access::Store | Access::Atomic)
    }
}

/// One kernel parameter: its name in the source and how the kernel uses it.
#[derive(Debug, Clone, Copy)]
pub struct ParamInfo {
    /// Name in the source.
    pub name: &'static str,
    /// How the kernel uses it.
    pub access: Access,
}

/// Which of the three generated kernels to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Mode {
    /// The kernel as written.
    Forward,
    /// Reverse mode: reads adjoints of outputs from their gradient buffers, accumulates adjoints
    /// of inputs into theirs.
    Adjoint,
    /// Forward mode: reads tangents of inputs from their tangent buffers, writes tangents of
    /// outputs into theirs.
    Tangent,
}

/// A `#[diff_kernel]` that can be launched with the borrowed argument tuple `Args`
/// (e.g. `(&Array<Vec3>, f32, &Array<Vec3>)`).
#[diagnostic::on_unimplemented(
    message = "kernel `{Self}` cannot be launched with arguments `{Args}`",
    label = "these arguments do not match the kernel's parameters",
    note = "pass a tuple with one element per kernel parameter, in order: `&array` for each \
            `&Array<T>` parameter (with the same element type) and a value for each value parameter"
)]
pub trait Kernel<Args>: Copy + Send + Sync + 'static {
    /// The arguments with every `&Array` replaced by a handle (what a tape keeps).
    type Owned: Send + Sync + 'static;
    /// Takes handles of the arrays in `args`.
    fn to_owned(args: &Args) -> Self::Owned;
}

/// The body of a kernel over its owned arguments: what a launch or a tape runs.
pub trait KernelBody<Owned>: Copy + Send + Sync + 'static {
    /// The kernel's name (its fn name).
    const NAME: &'static str;
    /// Its parameters in order.
    const PARAMS: &'static [ParamInfo];
    /// The array passed for each parameter (`None` for value parameters).
    fn arrays(args: &Owned) -> Vec<Option<&dyn AnyArray>>;
    /// Runs thread ids `range` in `mode`; returns the scatter logs to apply (empty when `exec`
    /// writes directly).
    fn run(&self, mode: Mode, args: &Owned, range: Range<usize>, exec: &Exec) -> Vec<ScatterLog>;
    /// The scatters of `mode` (other than those at the thread id), if the indices of every
    /// one are static: computed at the top of the body from the thread id, constants and
    /// reads of arrays, so a launch can know them before it runs (see `crate::split`).
    fn static_scatters(mode: Mode) -> Option<StaticScatters> {
        let _ = mode;
        None
    }
    /// Calls `sink(slot, tid, index)` for every static scatter of `mode` of each thread id in
    /// `range`, in order: `slot` is the scattered parameter's place in
    /// [`StaticScatters::targets`]. A thread reports each scatter it may make, whatever
    /// branch it takes later.
    fn scatter_indices(
        &self,
        mode: Mode,
        args: &Owned,
        range: Range<usize>,
        exec: &Exec,
        sink: &mut dyn FnMut(usize, usize, i128),
    ) {
        let _ = (mode, args, range, exec, sink);
    }
}

/// The static scatters of a kernel in one mode (see [`KernelBody::static_scatters`]).
#[derive(Clone, Copy, Debug)]
pub struct StaticScatters {
    /// The parameters scattered into (in the adjoint: whose gradients are).
    pub targets: &'static [usize],
    /// The array parameters the indices read (index arrays such as a mesh's elements).
    pub deps: &'static [usize],
}

/// Converts one launch argument into what the tape keeps.
pub trait LaunchArg {
    /// The owned form.
    type Owned: Send + Sync + 'static;
    /// Takes a handle or copies the value.
    fn to_owned_arg(&self) -> Self::Owned;
}

impl<T: Element> LaunchArg for &Array<T> {
    type Owned = Array<T>;
    #[inline]
    fn to_owned_arg(&self) -> Array<T> {
        (*self).clone()
    }
}

impl<T: crate::Value> LaunchArg for T {
    type Owned = T;
    #[inline]
    fn to_owned_arg(&self) -> T {
        *self
    }
}

/// Where a kernel reads and writes an array: named in bounds errors.
#[derive(Debug)]
pub struct Site {
    /// The kernel.
    pub kernel: &'static str,
    /// The parameter.
    pub param: &'static str,
}

#[cold]
#[inline(never)]
fn out_of_bounds(site: &Site, name: &Option<Arc<str>>, index: i128, len: usize) -> ! {
    match name {
        Some(n) => panic!(
            "kernel `{}`: index {index} out of bounds for array `{n}` (parameter `{}`) of length {len}",
            site.kernel, site.param
        ),
        None => panic!(
            "kernel `{}`: index {index} out of bounds for parameter `{}` (an array of length {len})",
            site.kernel, site.param
        ),
    }
}

/// An index into an array: `usize`, `u32`, `i32`, ... (negative indices are out of bounds).
pub trait ToIndex: Copy {
    /// The index as a wide signed integer (to report it as written).
    fn to_i128(self) -> i128;
}
macro_rules! to_index {
    ($($t:ty),*) => {$( impl ToIndex for $t { #[inline(always)] fn to_i128(self) -> i128 { self as i128 } } )*};
}
to_index!(u8, u16, u32, u64, usize, i8, i16, i32, i64, isize);

/// Where a view reads or writes: the kernel, the parameter and the array's name, for errors.
#[derive(Clone)]
struct Place {
    site: &'static Site,
    name: Option<Arc<str>>,
}

impl Place {
    fn of<T: Element>(a: &Array<T>, site: &'static Site) -> Self {
        Place {
            site,
            name: a.name(),
        }
    }
}

#[inline(always)]
fn checked<I: ToIndex>(i: I, len: usize, place: &Place) -> usize {
    let w = i.to_i128();
    if w < 0 || w >= len as i128 {
        out_of_bounds(place.site, &place.name, w, len)
    }
    w as usize
}

/// `i` as an index of a scatter whose indices must lie in `lo..hi` (`0..len`, or the chunk's
/// own thread ids for a scatter at the thread id writing directly before its turn): one
/// comparison, as for `0..len`.
#[inline(always)]
fn checked_in<I: ToIndex>(i: I, lo: usize, hi: usize, len: usize, place: &Place) -> usize {
    let w = i.to_i128();
    if (w.wrapping_sub(lo as i128) as u128) >= (hi - lo) as u128 {
        outside_range(place, w, lo..hi, len)
    }
    w as usize
}

#[cold]
#[inline(never)]
fn outside_range(place: &Place, index: i128, own: Range<usize>, len: usize) -> ! {
    if index < 0 || index >= len as i128 {
        out_of_bounds(place.site, &place.name, index, len)
    }
    panic!(
        "kernel `{}`: a scatter into parameter `{}` at index {index}, outside the thread ids \
         {own:?} of its chunk, through a view for scatters at the thread's own index",
        place.site.kernel, place.site.param
    )
}

/// How a chunk of a launch runs: writing scatters directly (one chunk in thread-id order) or
/// into logs that the launch applies afterwards in thread-id order; and what the launch
/// locked.
///
/// Only a launch makes one (there is no public constructor), and every view of an array
/// needs one: so views exist only inside a launch, over buffers it holds locked (for
/// reading to read, for writing to write), and safe code cannot race through them.
#[derive(Debug)]
pub struct Exec<'a> {
    pub(crate) direct: bool,
    /// (buffer id, locked for writing) of every buffer the launch holds.
    locked: &'a [(u64, bool)],
    /// The thread ids of this chunk: a store claims only for these (chunks are disjoint).
    range: Range<usize>,
    /// A logged chunk: the launch's chunk order and this chunk's place in it (to flush a
    /// large log early, once every earlier chunk is applied).
    order: Option<(&'a ChunkOrder, usize)>,
    /// Buffers that two parameters of the launch scatter into (an array passed twice, read by
    /// both, in the adjoint): such a launch runs serially, and no scatter into them writes
    /// directly before its chunk's turn, even one at the thread's own index.
    shared_scatters: &'a [u64],
    /// The head of a range of a split launch (see `crate::split`): its scatters log only
    /// what an earlier range also adds to.
    halo: Option<Halo<'a>>,
}

/// The head of a range of a split launch: per scattered array (by id), the first thread id
/// that adds to each element, and the range's first thread id. An element first touched at
/// or after it belongs to this range alone until later ranges' logs are applied.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Halo<'a> {
    pub(crate) firsts: &'a [(u64, Arc<[u32]>)],
    pub(crate) bound: u32,
}

impl<'a> Exec<'a> {
    pub(crate) fn new(
        direct: bool,
        locked: &'a [(u64, bool)],
        shared_scatters: &'a [u64],
        range: Range<usize>,
    ) -> Self {
        Exec {
            direct,
            locked,
            range,
            order: None,
            shared_scatters,
            halo: None,
        }
    }

    /// The head `range` of a range of a split launch (see [`Halo`]).
    pub(crate) fn halo(
        locked: &'a [(u64, bool)],
        shared_scatters: &'a [u64],
        range: Range<usize>,
        halo: Halo<'a>,
    ) -> Self {
        Exec {
            direct: false,
            locked,
            range,
            order: None,
            shared_scatters,
            halo: Some(halo),
        }
    }

    /// A logged chunk `k` of a launch whose chunks are applied in `order`.
    pub(crate) fn ordered(
        locked: &'a [(u64, bool)],
        shared_scatters: &'a [u64],
        range: Range<usize>,
        order: &'a ChunkOrder,
        k: usize,
    ) -> Self {
        Exec {
            direct: false,
            locked,
            range,
            order: Some((order, k)),
            shared_scatters,
            halo: None,
        }
    }

    /// Panics unless the launch holds `buf` locked for writing (`write`) or for reading.
    fn check<T: Element>(&self, buf: Option<&Array<T>>, write: bool, site: &Site) {
        let Some(b) = buf else { return };
        if !self.locked.contains(&(b.id(), write)) {
            unlocked_view(site, &b.label(), write);
        }
    }
}

#[cold]
#[inline(never)]
fn unlocked_view(site: &Site, label: &str, write: bool) -> ! {
    panic!(
        "kernel `{}`, parameter `{}`: a view {} `{label}`, which the launch does not hold \
         locked {}; views are made only by generated code, over the launch's own arguments",
        site.kernel,
        site.param,
        if write { "writing" } else { "reading" },
        if write { "for writing" } else { "for reading" },
    )
}

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
    let array = match &place.name {
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

/// Accumulates into an array (`a.atomic_add(i, v)`), deterministically.
///
/// The log lives in its own heap box (`None` in direct mode): a `Vec` inline in the view would
/// let its out-of-line growth take the view's address, and the compiler would then keep every
/// field in memory and reload it after each add (the direct path ran at 1.4x to 2x a
/// hand-written loop; docs/performance.md).
pub struct Scatter<T: Element, const AT_TID: bool = false> {
    target: Option<Array<T>>,
    /// The target's data while this view writes directly, null while it logs (or has no
    /// target): one test in `add` picks the path, the direct one first.
    ptr: *mut T,
    /// The target's data (null without a target), for applying the log.
    dst: *mut T,
    len: usize,
    /// The indices it may add at, with `AT_TID`: the chunk's thread ids (see `new`).
    lo: usize,
    hi: usize,
    // Boxed on purpose (see the type's docs): the view's own fields stay in registers.
    #[allow(clippy::box_collection)]
    log: Option<Box<Vec<(u32, T)>>>,
    place: Place,
    /// The launch's chunk order and this chunk's index (logged chunks).
    order: Option<(*const ChunkOrder, usize)>,
    /// In the head of a split launch's range: the first thread id adding to each element
    /// (null otherwise), and the range's first thread id; an element first touched at or
    /// after it is written directly, the others logged.
    first: *const u32,
    bound: u32,
}

impl<T: Element, const AT_TID: bool> Scatter<T, AT_TID> {
    /// `AT_TID`: the macro proved that every scatter into this parameter indexes with the
    /// thread id. Then only this chunk's threads add to the elements at this chunk's thread
    /// ids, each its own, so the view writes directly from the start even in a logged chunk
    /// (the additions to an element are one thread's, in its order: the same bits), unless
    /// another parameter of the launch scatters into the same buffer. Its indices are then
    /// checked to be the chunk's thread ids.
    fn new(target: Option<Array<T>>, of: u64, exec: &Exec, place: Place, len: usize) -> Self {
        let dst = target
            .as_ref()
            .map_or(std::ptr::null_mut(), |a| a.data_ptr());
        let own = AT_TID
            && target
                .as_ref()
                .is_some_and(|t| !exec.shared_scatters.contains(&t.id()));
        // A logged chunk whose turn it already is (every earlier chunk applied) writes directly.
        let logged = !own && !exec.direct && !exec.order.is_some_and(|(o, k)| o.is_turn(k));
        let (lo, hi) = match own {
            true => {
                let hi = exec.range.end.min(len);
                (exec.range.start.min(hi), hi)
            }
            false => (0, len),
        };
        let first = match (&exec.halo, logged && target.is_some()) {
            (Some(h), true) => match h.firsts.iter().find(|(id, _)| *id == of) {
                Some((_, m)) if m.len() == len => m.as_ptr(),
                // The plan covers every scatter that is not at the thread id: logging all
                // of a head would apply it after the tail's direct additions.
                _ => panic!(
                    "kernel `{}`, parameter `{}`: a split launch without the first-touch map \
                     of this scatter (an internal error of adflex; please report it)",
                    place.site.kernel, place.site.param
                ),
            },
            _ => std::ptr::null(),
        };
        Scatter {
            first,
            bound: exec.halo.map_or(0, |h| h.bound),
            log: (logged && target.is_some()).then(|| Box::new(take_log())),
            target,
            ptr: if logged { std::ptr::null_mut() } else { dst },
            dst,
            len,
            lo,
            hi,
            place,
            order: exec.order.map(|(o, k)| (o as *const ChunkOrder, k)),
        }
    }

    /// `a[i] += v`.
    #[inline(always)]
    pub fn add<I: ToIndex>(&mut self, i: I, v: T) {
        // Without `AT_TID` the plain bounds check: `lo`, `hi` cost registers in the adjoints'
        // many scatters (the range check on every view made the cloth's backward 1-3% slower).
        let i = match AT_TID {
            true => checked_in(i, self.lo, self.hi, self.len, &self.place),
            false => checked(i, self.len, &self.place),
        };
        if !self.ptr.is_null() {
            // SAFETY: direct mode runs a single chunk in thread-id order on one thread (or
            // this chunk is the first unapplied one, see `checkpoint`, or the indices are
            // this chunk's own thread ids, see `new`); in bounds.
            unsafe { (*self.ptr.add(i)).acc(v) }
        } else if let Some(log) = &mut self.log {
            // SAFETY: `i < len`, the map's length (see `new`).
            if !self.first.is_null() && unsafe { *self.first.add(i) } >= self.bound {
                // SAFETY: no earlier range adds to this element, later ones log theirs.
                unsafe { (*self.dst.add(i)).acc(v) };
                return;
            }
            log.push((i as u32, v));
            if log.len() % TURN_CHECK == 0 {
                self.checkpoint();
            }
        }
    }

    /// Every [`TURN_CHECK`] logged entries: once every earlier chunk of the launch is applied,
    /// this chunk is the first unapplied one and no later chunk applies anything before it
    /// finishes, so it applies its log and goes on writing directly (with two workers, about
    /// half the contributions are then never logged). A log too large to keep waits for that
    /// turn, so a launch's memory does not grow with its contributions. Either way the order
    /// of the additions (thread-id order) is unchanged.
    #[inline(never)]
    fn checkpoint(&mut self) {
        let Some((order, k)) = self.order else { return };
        // SAFETY: the order outlives the launch's chunks, which own the views.
        let order = unsafe { &*order };
        if order.is_turn(k) {
            self.apply_and_go_direct();
        } else if self.log.as_ref().is_some_and(|l| l.len() >= LOG_FLUSH) {
            if order.wait_turn(k) {
                self.apply_and_go_direct();
            } else if let Some(log) = &mut self.log {
                // The launch is failing with another chunk's panic: apply nothing.
                log.clear();
            }
        }
    }

    /// Applies the log (this chunk's turn) and switches to direct writes.
    fn apply_and_go_direct(&mut self) {
        if let Some(log) = self.log.take() {
            for &(i, v) in log.iter() {
                // SAFETY: in bounds (checked when logged); this chunk's turn: no other
                // thread writes the target.
                unsafe { (*self.dst.add(i as usize)).acc(v) }
            }
            give_log(*log);
            self.ptr = self.dst;
        }
    }

    /// `a[i] -= v`.
    #[inline(always)]
    pub fn sub<I: ToIndex>(&mut self, i: I, v: T) {
        // `-0.0 - v` is `-v` exactly (`0.0 - v` is not, at `v = 0`): the compiler makes
        // `a[i] + (-v)` the single subtraction `a[i] - v`, the same bits.
        let mut neg = T::neg_zeroed();
        neg.acc_neg(v);
        self.add(i, neg)
    }

    /// This scatter as one that writes directly for the rest of the chunk, or `None` while
    /// it logs. Generated kernels run a chunk's remaining threads in a loop over these views
    /// once every scatter of the chunk writes directly: that loop has no log path, which
    /// otherwise costs a hand-written loop's speed (springs' adjoint 1.3x -> 1.05x of it).
    #[inline(always)]
    pub fn direct(&mut self) -> Option<DirectScatter<'_, T, AT_TID>> {
        (!self.ptr.is_null() || self.log.is_none()).then_some(DirectScatter {
            ptr: self.ptr,
            len: self.len,
            lo: self.lo,
            hi: self.hi,
            place: &self.place,
        })
    }

    /// The log of this chunk (empty in direct mode).
    pub fn finish(self) -> ScatterLog {
        match (self.target, self.log) {
            (Some(t), Some(log)) if !log.is_empty() => ScatterLog(Some(Box::new(TypedLog {
                target: t,
                entries: *log,
            }))),
            (_, Some(log)) => {
                give_log(*log);
                ScatterLog(None)
            }
            _ => ScatterLog(None),
        }
    }
}

/// A [`Scatter`] that writes directly (or has no target, and then ignores its adds): see
/// [`Scatter::direct`]. Same methods, same bits.
pub struct DirectScatter<'s, T: Element, const AT_TID: bool = false> {
    /// Null without a target.
    ptr: *mut T,
    len: usize,
    lo: usize,
    hi: usize,
    place: &'s Place,
}

impl<T: Element, const AT_TID: bool> DirectScatter<'_, T, AT_TID> {
    /// `a[i] += v`.
    #[inline(always)]
    pub fn add<I: ToIndex>(&mut self, i: I, v: T) {
        let i = match AT_TID {
            true => checked_in(i, self.lo, self.hi, self.len, self.place),
            false => checked(i, self.len, self.place),
        };
        if !self.ptr.is_null() {
            // SAFETY: as in `Scatter::add`'s direct path (this view borrows that scatter,
            // which was writing directly); in bounds.
            unsafe { (*self.ptr.add(i)).acc(v) }
        }
    }

    /// `a[i] -= v` (see [`Scatter::sub`]).
    #[inline(always)]
    pub fn sub<I: ToIndex>(&mut self, i: I, v: T) {
        let mut neg = T::neg_zeroed();
        neg.acc_neg(v);
        self.add(i, neg)
    }
}

/// Entries a chunk's log may hold before it waits for its turn to apply them
/// ([`Scatter::checkpoint`]): 1 MB of `Vec3<f32>` entries per target and chunk.
const LOG_FLUSH: usize = 1 << 16;
/// A logged scatter looks whether its chunk's turn has come every this many entries (a power
/// of two, so the test is a mask in the hot loop).
const TURN_CHECK: usize = 256;

/// The scatters one chunk made into one target, applied in thread-id order after the chunks ran.
pub struct ScatterLog(pub(crate) Option<Box<dyn ApplyLog>>);

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

fn take_log<T: Element>() -> Vec<(u32, T)> {
    let mut pool = LOG_POOL.lock().unwrap_or_else(PoisonError::into_inner);
    match pool.iter().rposition(|b| b.is::<Vec<(u32, T)>>()) {
        Some(k) => *pool.swap_remove(k).downcast().expect("checked by `is`"),
        None => Vec::new(),
    }
}

fn give_log<T: Element>(mut log: Vec<(u32, T)>) {
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

// SAFETY: the raw pointers in views point into arrays kept alive by the launch's owned
// arguments; the launch contract (above) rules out conflicting access.
unsafe impl<T: Send> Send for Reader<T> {}
unsafe impl<T: Element> Send for OptReader<T> {}
unsafe impl<T: Element> Send for Writer<T> {}
unsafe impl<T: Element, const AT_TID: bool> Send for Scatter<T, AT_TID> {}

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

fn scatter_of<T: Element, const AT_TID: bool>(
    of: &Array<T>,
    buf: Option<Array<T>>,
    exec: &Exec,
    site: &'static Site,
) -> Scatter<T, AT_TID> {
    exec.check(buf.as_ref(), true, site);
    Scatter::new(buf, of.id(), exec, Place::of(of, site), of.len())
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

/// A scatter into `a`. `AT_TID`: the macro proved that every scatter into it indexes with
/// the thread id (then it may write directly in any chunk, its indices checked to be the
/// chunk's thread ids; see [`Scatter`]).
#[inline]
pub fn scatter<T: Element, const AT_TID: bool>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
) -> Scatter<T, AT_TID> {
    scatter_of(a, Some(a.clone()), exec, site)
}

/// A reader of `a`'s gradient (zeros if it has none).
#[inline]
pub fn grad_reader<T: Element>(a: &Array<T>, exec: &Exec, site: &'static Site) -> OptReader<T> {
    opt_reader(a, a.grad_buffer(), exec, site)
}

/// A scatter into `a`'s gradient (a no-op if it has none); `AT_TID` as for [`scatter`].
#[inline]
pub fn grad_scatter<T: Element, const AT_TID: bool>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
) -> Scatter<T, AT_TID> {
    scatter_of(a, a.grad_buffer(), exec, site)
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

/// A scatter into `a`'s tangent (a no-op if it has none); `AT_TID` as for [`scatter`].
#[inline]
pub fn tangent_scatter<T: Element, const AT_TID: bool>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
) -> Scatter<T, AT_TID> {
    scatter_of(a, a.tangent_buffer(), exec, site)
}

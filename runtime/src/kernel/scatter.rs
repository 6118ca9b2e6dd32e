//! Deterministic accumulation (`atomic_add`): [`Scatter`], which writes directly when it may
//! and otherwise logs (`crate::scatter_log`) for the launch to apply in thread-id order.

use super::exec::Exec;
use super::place::{checked, checked_in, Place, Site, ToIndex};
use crate::array::{Array, Element};
use crate::chunk_order::ChunkOrder;
use crate::scatter_log::{give_log, take_log, ScatterLog};

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
        // Logs hold 32-bit indices: checked for every view that may log (not only those that
        // do, which depends on the timing of the chunks), so the error does not either.
        if !own && !exec.direct && target.is_some() && len as u64 > MAX_LOGGED_LEN {
            too_long_to_log(&place, len)
        }
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
            (Some(t), Some(log)) if !log.is_empty() => ScatterLog::of(t, *log),
            (_, Some(log)) => {
                give_log(*log);
                ScatterLog(None)
            }
            _ => ScatterLog(None),
        }
    }
}

/// The longest target a logging scatter takes: its log holds indices as `u32`.
const MAX_LOGGED_LEN: u64 = 1 << 32;

#[cold]
#[inline(never)]
fn too_long_to_log(place: &Place, len: usize) -> ! {
    let array = match place.name() {
        Some(n) => format!("array `{n}` (parameter `{}`)", place.site.param),
        None => format!("parameter `{}`", place.site.param),
    };
    panic!(
        "kernel `{}`: scatters into {array} of {len} elements in a parallel launch, whose \
         scatter logs hold 32-bit indices (at most 2^32 elements); run it with \
         `launch_serial`, on one thread, or scatter into smaller arrays",
        place.site.kernel
    )
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

// SAFETY: the raw pointers in views point into arrays kept alive by the launch's owned
// arguments; the launch contract (above) rules out conflicting access.
unsafe impl<T: Element, const AT_TID: bool> Send for Scatter<T, AT_TID> {}

fn scatter_of<T: Element, const AT_TID: bool>(
    of: &Array<T>,
    buf: Option<Array<T>>,
    exec: &Exec,
    site: &'static Site,
) -> Scatter<T, AT_TID> {
    exec.check(buf.as_ref(), true, site);
    Scatter::new(buf, of.id(), exec, Place::of(of, site), of.len())
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

/// A scatter into `a`'s gradient (a no-op if it has none); `AT_TID` as for [`scatter`].
#[inline]
pub fn grad_scatter<T: Element, const AT_TID: bool>(
    a: &Array<T>,
    exec: &Exec,
    site: &'static Site,
) -> Scatter<T, AT_TID> {
    scatter_of(a, a.grad_buffer(), exec, site)
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

#[cfg(test)]
mod tests {
    use super::*;

    static SITE: Site = Site {
        kernel: "big",
        param: "f",
    };

    /// A view of a logged chunk over `a`, told the target has `len` elements (no test can
    /// allocate 2^32 of them; the view takes the length from its caller).
    fn logged_view(a: &Array<f32>, len: usize) -> Scatter<f32> {
        let exec = Exec::new(false, &[], &[], 0..1);
        Scatter::new(Some(a.clone()), a.id(), &exec, Place::of(a, &SITE), len)
    }

    #[test]
    fn a_logging_scatter_takes_targets_of_up_to_2_pow_32_elements() {
        let a = Array::<f32>::zeros(1).named("forces");
        let v = logged_view(&a, 1 << 32);
        assert!(v.log.is_some(), "the view logs");
        assert!(v.finish().0.is_none(), "nothing was logged");
    }

    #[test]
    #[should_panic(
        expected = "kernel `big`: scatters into array `forces` (parameter `f`) of 4294967297 \
                    elements in a parallel launch"
    )]
    fn a_longer_target_is_refused_naming_kernel_and_array() {
        let a = Array::<f32>::zeros(1).named("forces");
        let _ = logged_view(&a, (1 << 32) + 1);
    }

    #[test]
    fn a_direct_view_takes_longer_targets() {
        let a = Array::<f32>::zeros(1);
        let exec = Exec::new(true, &[], &[], 0..1);
        let v = Scatter::<f32>::new(
            Some(a.clone()),
            a.id(),
            &exec,
            Place::of(&a, &SITE),
            (1 << 32) + 1,
        );
        assert!(v.log.is_none());
    }
}

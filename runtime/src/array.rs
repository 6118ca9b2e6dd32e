//! `Array<T>`: a cheap shared handle over kernel data, with an optional gradient (adjoint)
//! buffer, an optional tangent buffer and a version counter that every write bumps.

use std::cell::{RefCell, UnsafeCell};
use std::fmt;
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{
    Arc, Mutex, MutexGuard, OnceLock, PoisonError, RwLock, RwLockReadGuard, RwLockWriteGuard,
};

use crate::error::Error;
use crate::Value;

/// What an array can hold: any kernel value (scalars, vectors, matrices, indices).
pub trait Element: Value + fmt::Debug {}
impl<T: Value + fmt::Debug> Element for T {}

static NEXT_ID: AtomicU64 = AtomicU64::new(1);

struct Inner<T> {
    id: u64,
    name: Mutex<Option<Arc<str>>>,
    /// Host reads hold `access` for reading, host writes for writing. A launch holds it for
    /// writing on the arrays it writes and for reading on those it reads, and goes through
    /// raw pointers.
    data: UnsafeCell<Vec<T>>,
    len: usize,
    access: RwLock<()>,
    version: AtomicU64,
    requires_grad: AtomicBool,
    grad: Mutex<Option<Array<T>>>,
    tangent: Mutex<Option<Array<T>>>,
    /// Which thread of the current launch stored to each element, for stores the macro could
    /// not prove distinct (see [`Claims`]); allocated on first use.
    claims: OnceLock<Box<[AtomicU64]>>,
    /// Bumped by every launch that stores into the array: claims of older launches are void.
    epoch: AtomicU32,
}

mod sealed {
    /// Proof that the caller is the runtime: what launches alone may do to an array (lock it
    /// for a launch, bump its version, start a store-claim epoch) takes one, and code outside
    /// the crate cannot name this type. So no user code can bump a version behind a tape.
    #[derive(Clone, Copy)]
    pub struct Token(pub(crate) ());
}
pub(crate) use sealed::Token;

/// A mutex that a panic elsewhere does not poison for good: the data it guards (a name, a
/// buffer handle) is always consistent.
fn relock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Where an array's name is: held by a launch's views, which live inside the launch while its
/// arguments keep the array alive.
#[derive(Clone, Copy)]
pub(crate) struct NameRef(*const Mutex<Option<Arc<str>>>);

// SAFETY: a pointer to a `Mutex` (which is `Sync`), read only while the array is alive.
unsafe impl Send for NameRef {}
unsafe impl Sync for NameRef {}

impl NameRef {
    /// The name now.
    pub(crate) fn get(&self) -> Option<Arc<str>> {
        // SAFETY: a view holding this lives inside the launch, whose arguments hold the array.
        relock(unsafe { &*self.0 }).clone()
    }
}

thread_local! {
    /// The arrays whose access lock this thread holds: (id, for writing).
    static HELD: RefCell<Vec<(u64, bool)>> = const { RefCell::new(Vec::new()) };
}

/// Refuses an access that would deadlock on this thread's own lock (a host read inside
/// `modify` of the same array, a launch inside it, ...), naming the array.
fn check_not_held(id: u64, label: impl FnOnce() -> String, write: bool, what: &str) {
    let held = HELD.with(|h| h.borrow().iter().find(|(i, _)| *i == id).map(|&(_, w)| w));
    if let Some(held_write) = held {
        if write || held_write {
            panic!(
                "{what} array `{}` while this thread already holds it{} (inside `modify`, or a \
                 launch): that would deadlock. Read what you need before `modify` (or use the \
                 slice `modify` gives you), and launch outside it",
                label(),
                if held_write {
                    " for writing"
                } else {
                    " for reading"
                }
            );
        }
    }
}

// SAFETY: `data` is only touched under `access` (host) or by launches that hold `access` for
// reading and write disjoint indices (the documented kernel contract: a store to the same index
// from two threads is a race; scatters go through the deterministic scatter logs).
unsafe impl<T: Send + Sync> Send for Inner<T> {}
unsafe impl<T: Send + Sync> Sync for Inner<T> {}

/// A 1-D array of kernel values, shared by handle: cloning an `Array` clones the handle, not
/// the data (use [`Array::deep_clone`] for a copy).
///
/// ```
/// use adflex_runtime::{Array, Vec3};
/// let x = Array::from_vec(vec![Vec3::new(1.0, 2.0, 3.0); 4]).requires_grad().named("x");
/// assert_eq!(x.len(), 4);
/// assert_eq!(x.grad().unwrap().to_vec(), vec![Vec3::zeros(); 4]);
/// let y: adflex_runtime::Array<f32> = adflex_runtime::Array::zeros(3);
/// assert!(y.grad().is_err()); // no silent None: gradients must be asked for
/// ```
pub struct Array<T> {
    inner: Arc<Inner<T>>,
}

impl<T> Clone for Array<T> {
    fn clone(&self) -> Self {
        Array {
            inner: self.inner.clone(),
        }
    }
}

impl<T: Element> fmt::Debug for Array<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Array")
            .field("name", &self.name())
            .field("len", &self.len())
            .field("version", &self.version())
            .field("requires_grad", &self.is_requires_grad())
            .finish()
    }
}

impl<T: Element> Array<T> {
    /// An array holding `data`.
    pub fn from_vec(data: Vec<T>) -> Self {
        Array {
            inner: Arc::new(Inner {
                id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
                name: Mutex::new(None),
                len: data.len(),
                data: UnsafeCell::new(data),
                access: RwLock::new(()),
                version: AtomicU64::new(0),
                requires_grad: AtomicBool::new(false),
                grad: Mutex::new(None),
                tangent: Mutex::new(None),
                claims: OnceLock::new(),
                epoch: AtomicU32::new(0),
            }),
        }
    }

    /// `len` zeros. Large arrays of reals, vectors and matrices come zeroed from the allocator,
    /// and only one element per memory page is written here.
    pub fn zeros(len: usize) -> Self {
        let mut v = T::zeroed_vec(len);
        // Fresh pages from the kernel are mapped on first touch. Touched first by a read (a
        // scatter's or a gradient's `+=`), a page maps the shared zero page and faults again
        // on the write, which also flushes the TLB of every core running the process: a
        // backward faulted twice per page of its new gradients. Mapping each page for writing
        // here faults it once (docs/performance.md): in one system call where the kernel
        // offers it, else by one write per page.
        let bytes = len * std::mem::size_of::<T>();
        if populate_for_writing(v.as_mut_ptr().cast(), bytes) {
            // The pages wholly inside were mapped; those at either end, by a write.
            // SAFETY: `len > 0` (at least 4 pages), initialized elements.
            unsafe {
                std::ptr::write_volatile(v.as_mut_ptr(), T::zeroed());
                std::ptr::write_volatile(v.as_mut_ptr().add(len - 1), T::zeroed());
            }
            return Self::from_vec(v);
        }
        let step = (4096 / std::mem::size_of::<T>().max(1)).max(1);
        for k in (0..len).step_by(step) {
            // SAFETY: `k < len`, an initialized element. Volatile: the compiler knows the
            // memory is zero and would drop a plain store of zero.
            unsafe { std::ptr::write_volatile(v.as_mut_ptr().add(k), T::zeroed()) };
        }
        Self::from_vec(v)
    }

    /// Zeros shaped like `self` (same length), without gradient.
    pub fn zeros_like(&self) -> Self {
        Self::zeros(self.len())
    }

    /// A copy of the data in a new array (new id, no gradient, same name).
    pub fn deep_clone(&self) -> Self {
        let a = Self::from_vec(self.to_vec());
        *relock(&a.inner.name) = relock(&self.inner.name).clone();
        a
    }

    /// Gives the array a name used in error messages, DOT graphs and reports.
    pub fn named(self, name: impl Into<String>) -> Self {
        *relock(&self.inner.name) = Some(Arc::from(name.into()));
        self
    }

    /// The name given by [`Array::named`], if any.
    pub fn name(&self) -> Option<Arc<str>> {
        relock(&self.inner.name).clone()
    }

    /// Where the name is, for a view to read it only when an error names the array.
    pub(crate) fn name_ref(&self) -> NameRef {
        NameRef(&self.inner.name)
    }

    /// Marks the array as a gradient target and allocates its (zeroed) gradient buffer.
    pub fn requires_grad(self) -> Self {
        self.inner.requires_grad.store(true, Ordering::Relaxed);
        self.ensure_grad();
        self
    }

    /// Whether [`Array::requires_grad`] was called.
    pub fn is_requires_grad(&self) -> bool {
        self.inner.requires_grad.load(Ordering::Relaxed)
    }

    /// The gradient buffer (a handle sharing it). An error if this array neither requires grad
    /// nor received a gradient buffer from a tape.
    pub fn grad(&self) -> Result<Array<T>, Error> {
        self.grad_buffer().ok_or_else(|| Error::NoGrad {
            array: self.label(),
        })
    }

    /// The gradient buffer if one exists.
    pub fn grad_buffer(&self) -> Option<Array<T>> {
        relock(&self.inner.grad).clone()
    }

    /// Allocates a zeroed gradient buffer if there is none; returns it.
    pub fn ensure_grad(&self) -> Array<T> {
        let mut g = relock(&self.inner.grad);
        g.get_or_insert_with(|| Array::zeros(self.len())).clone()
    }

    /// Makes the gradient buffer zero: allocates a zeroed one if there is none (without a
    /// second pass over it), zeroes the existing one otherwise.
    pub(crate) fn reset_grad(&self) {
        let mut g = relock(&self.inner.grad);
        match &*g {
            Some(b) => b.fill(T::zeroed()),
            None => *g = Some(Array::zeros(self.len())),
        }
    }

    /// Sets the gradient buffer to zero (no-op without one).
    pub fn zero_grad(&self) {
        if let Some(g) = self.grad_buffer() {
            g.fill(T::zeroed());
        }
    }

    /// The tangent buffer (forward mode) if one exists.
    pub fn tangent_buffer(&self) -> Option<Array<T>> {
        relock(&self.inner.tangent).clone()
    }

    /// Attaches `tangent` (same length) as this array's tangent buffer for forward-mode launches.
    pub fn set_tangent(&self, tangent: Option<Array<T>>) {
        if let Some(t) = &tangent {
            assert_eq!(
                t.len(),
                self.len(),
                "tangent of `{}` has the wrong length",
                self.label()
            );
        }
        *relock(&self.inner.tangent) = tangent;
    }

    /// Allocates a zeroed tangent buffer if there is none; returns it.
    pub fn ensure_tangent(&self) -> Array<T> {
        let mut g = relock(&self.inner.tangent);
        g.get_or_insert_with(|| Array::zeros(self.len())).clone()
    }

    /// Number of elements.
    pub fn len(&self) -> usize {
        self.inner.len
    }

    /// Whether the array has no elements.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// A copy of the data.
    pub fn to_vec(&self) -> Vec<T> {
        let _g = self.host_lock(false);
        // SAFETY: under the read lock nobody writes (writers hold the write lock).
        unsafe { std::slice::from_raw_parts(self.data_ptr(), self.len()) }.to_vec()
    }

    /// Element `i` (panics with the array's name if out of bounds).
    pub fn get(&self, i: usize) -> T {
        let _g = self.host_lock(false);
        let len = self.len();
        if i >= len {
            panic!(
                "index {i} out of bounds for array `{}` of length {len}",
                self.label()
            );
        }
        // SAFETY: in bounds, under the read lock.
        unsafe { *self.data_ptr().add(i) }
    }

    /// Runs `f` on the data for writing, then bumps the version.
    ///
    /// Accessing the same array inside `f` (`y.modify(|d| d[0] = y.get(1))`) panics with a
    /// message naming the array: it would deadlock.
    pub fn modify<U>(&self, f: impl FnOnce(&mut [T]) -> U) -> U {
        let _g = self.host_lock(true);
        // SAFETY: exclusive under the write lock.
        let out = f(unsafe { std::slice::from_raw_parts_mut(self.data_ptr(), self.len()) });
        self.bump_version();
        out
    }

    /// Sets element `i`.
    pub fn set(&self, i: usize, v: T) {
        let label = self.label();
        self.modify(|d| {
            let len = d.len();
            *d.get_mut(i).unwrap_or_else(|| {
                panic!("index {i} out of bounds for array `{label}` of length {len}")
            }) = v
        })
    }

    /// Copies `src` (same length) into the array.
    pub fn assign(&self, src: &[T]) {
        let label = self.label();
        self.modify(|d| {
            assert_eq!(d.len(), src.len(), "assign to `{label}`: length mismatch");
            d.copy_from_slice(src)
        })
    }

    /// Sets every element to `v`.
    pub fn fill(&self, v: T) {
        self.modify(|d| d.fill(v))
    }

    /// Unique id of the underlying buffer (shared by clones of the handle).
    pub fn id(&self) -> u64 {
        self.inner.id
    }

    /// The write counter: bumped by every host write and every launch that writes the array.
    pub fn version(&self) -> u64 {
        self.inner.version.load(Ordering::Acquire)
    }

    fn host_lock(&self, write: bool) -> ArrayLock<'_> {
        let what = if write { "writing" } else { "reading" };
        self.inner.acquire(write, || self.label(), what)
    }

    /// Starts a launch that stores into this array at indices the macro could not prove
    /// distinct per thread: voids the claims of earlier launches.
    pub(crate) fn new_claim_epoch(&self) {
        if self.inner.epoch.fetch_add(1, Ordering::AcqRel) == u32::MAX {
            // Wrapped around: clear so that no stale claim can match a new epoch.
            if let Some(c) = self.inner.claims.get() {
                c.iter().for_each(|e| e.store(0, Ordering::Relaxed));
            }
        }
    }

    /// The claim table and the current launch's epoch (see [`crate::kernel`]'s stores).
    pub(crate) fn claims(&self) -> (&[AtomicU64], u32) {
        let table = self
            .inner
            .claims
            .get_or_init(|| (0..self.len()).map(|_| AtomicU64::new(0)).collect());
        (table, self.inner.epoch.load(Ordering::Acquire))
    }

    pub(crate) fn bump_version(&self) {
        self.inner.version.fetch_add(1, Ordering::AcqRel);
    }

    /// The name if set, otherwise `array#<id>`.
    pub fn label(&self) -> String {
        match self.name() {
            Some(n) => n.to_string(),
            None => format!("array#{}", self.inner.id),
        }
    }

    pub(crate) fn data_ptr(&self) -> *mut T {
        // SAFETY: only the pointer is taken; callers uphold the launch contract.
        unsafe { (*self.inner.data.get()).as_mut_ptr() }
    }
}

enum Guard<'a> {
    Read(#[allow(dead_code)] RwLockReadGuard<'a, ()>),
    Write(#[allow(dead_code)] RwLockWriteGuard<'a, ()>),
}

/// An array's access lock, held by a host access or a launch. Registered with the thread so
/// that re-entrant access is refused instead of deadlocking. A panic while it is held for
/// writing (a kernel's out-of-bounds index, caught with `catch_unwind`) leaves the data
/// partly written: the version is bumped so that a tape which recorded a read of it refuses
/// to differentiate through it, and the lock stays usable (no poisoning).
pub struct ArrayLock<'a> {
    id: u64,
    version: &'a AtomicU64,
    guard: Guard<'a>,
    /// Registered in [`HELD`] alone (a host access), not by a [`HeldGroup`].
    tracked: bool,
}

impl<T> Inner<T> {
    fn acquire(&self, write: bool, label: impl FnOnce() -> String, what: &str) -> ArrayLock<'_> {
        check_not_held(self.id, label, write, what);
        HELD.with(|h| h.borrow_mut().push((self.id, write)));
        self.acquire_in_group(write, true)
    }

    /// The lock alone; `tracked`: the lock removes its own entry from [`HELD`] when dropped
    /// (a launch's locks are registered and removed together, see [`HeldGroup`]).
    fn acquire_in_group(&self, write: bool, tracked: bool) -> ArrayLock<'_> {
        let guard = if write {
            Guard::Write(self.access.write().unwrap_or_else(PoisonError::into_inner))
        } else {
            Guard::Read(self.access.read().unwrap_or_else(PoisonError::into_inner))
        };
        ArrayLock {
            id: self.id,
            version: &self.version,
            guard,
            tracked,
        }
    }
}

impl Drop for ArrayLock<'_> {
    fn drop(&mut self) {
        if matches!(self.guard, Guard::Write(_)) && std::thread::panicking() {
            self.version.fetch_add(1, Ordering::AcqRel);
        }
        if !self.tracked {
            return;
        }
        HELD.with(|h| {
            let mut h = h.borrow_mut();
            if let Some(k) = h.iter().rposition(|&(i, _)| i == self.id) {
                h.remove(k);
            }
        });
    }
}

/// A launch's distinct arrays registered with the thread at once (checked against what it
/// already holds in one pass, removed together on drop): a kernel has tens of parameters, and
/// registering each lock alone cost a search of the others.
pub(crate) struct HeldGroup {
    /// [`HELD`]'s length before the group.
    base: usize,
}

impl HeldGroup {
    /// Registers `targets` (distinct arrays: id, for writing, the array), refusing (as a host
    /// access does) an array this thread already holds in a way that would deadlock.
    pub(crate) fn enter<'a, 'b>(
        targets: impl Iterator<Item = (u64, bool, &'b (dyn AnyArray + 'a))> + Clone,
        what: &str,
    ) -> HeldGroup
    where
        'a: 'b,
    {
        let base = HELD.with(|h| h.borrow().len());
        if base > 0 {
            for (id, w, a) in targets.clone() {
                check_not_held(id, || a.label(), w, what);
            }
        }
        HELD.with(|h| h.borrow_mut().extend(targets.map(|(id, w, _)| (id, w))));
        HeldGroup { base }
    }
}

impl Drop for HeldGroup {
    fn drop(&mut self) {
        HELD.with(|h| h.borrow_mut().truncate(self.base));
    }
}

/// An array with its element type erased: what tapes and checks hold.
pub trait AnyArray: Send + Sync {
    /// See [`Array::id`].
    fn id(&self) -> u64;
    /// See [`Array::label`].
    fn label(&self) -> String;
    /// See [`Array::version`].
    fn version(&self) -> u64;
    /// See [`Array::len`].
    fn len(&self) -> usize;
    /// Whether it has no elements.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// See [`Array::is_requires_grad`].
    fn is_requires_grad(&self) -> bool;
    /// Whether a gradient buffer exists.
    fn has_grad(&self) -> bool;
    /// Allocates the gradient buffer if missing.
    fn ensure_grad(&self);
    /// Zeroes the gradient buffer if present.
    fn zero_grad(&self);
    /// Allocates a zeroed gradient buffer, or zeroes the existing one.
    fn reset_grad(&self);
    /// Number of differentiable scalars per element (0 for index arrays).
    fn element_dim(&self) -> usize;
    /// The relative rounding of the scalars ([`crate::Value::EPSILON`]: `f32`'s or `f64`'s).
    fn scalar_epsilon(&self) -> f64;
    /// A clone of the handle, boxed.
    fn boxed(&self) -> Box<dyn AnyArray>;
    /// The gradient buffer, boxed, if present.
    fn grad_any(&self) -> Option<Box<dyn AnyArray>>;
    /// Number of differentiable scalars in the whole array, `len * element_dim`: the length
    /// of the flat vectors that [`AnyArray::scalar`], `Tape::jvp` and the optimizers read.
    fn n_scalars(&self) -> usize {
        self.len() * self.element_dim()
    }
    /// Scalar component `k` of the whole array, `k < len * element_dim`.
    fn scalar(&self, k: usize) -> f64;
    /// Sets scalar component `k` (bumps the version).
    fn set_scalar(&self, k: usize, x: f64);
    /// Whether the elements are made of [`Dual`](crate::Dual) numbers.
    fn is_dual(&self) -> bool;
    /// The derivative part of scalar component `k` (0 unless [`AnyArray::is_dual`]).
    fn eps_scalar(&self, k: usize) -> f64;
    /// Sets the derivative part of scalar component `k` (bumps the version; nothing changes
    /// unless [`AnyArray::is_dual`]).
    fn set_eps_scalar(&self, k: usize, x: f64);
    /// First index whose element has a NaN or infinite component.
    fn first_non_finite(&self) -> Option<usize>;
    /// Holds the access lock while a launch runs: for writing if the launch writes the array.
    /// (Only the runtime can call it: `Token` cannot be named outside.) The launch registers
    /// its locks with the thread as one `HeldGroup` first.
    fn lock(&self, write: bool, _: Token) -> ArrayLock<'_>;
    /// Bumps the version (after a launch wrote the array).
    fn mark_written(&self, _: Token);
    /// Voids the store claims of earlier launches (a launch that stores is starting).
    fn new_claim_epoch(&self, _: Token);
    /// The handle as [`std::any::Any`], to downcast to its `Array<T>`.
    fn as_any(&self) -> &dyn std::any::Any;
    /// Adds `src` (an array of the same element type and length) into this array element by
    /// element (bumps the version). Panics on a type or length mismatch.
    fn add_from(&self, src: &dyn AnyArray);
    /// The tangent buffer, boxed, if present.
    fn tangent_any(&self) -> Option<Box<dyn AnyArray>>;
    /// A copy of the data in a new array (see [`Array::deep_clone`]), boxed.
    fn deep_clone_any(&self) -> Box<dyn AnyArray>;
    /// Copies `src` (an array of the same element type and length) into this array (bumps
    /// the version). Panics on a type or length mismatch.
    fn copy_from(&self, src: &dyn AnyArray);
    /// Allocates a zeroed tangent buffer, or zeroes the existing one.
    fn reset_tangent(&self);
    /// Drops the tangent buffer: the array counts as constant in forward mode.
    fn clear_tangent(&self);
}

impl<T: Element> AnyArray for Array<T> {
    fn id(&self) -> u64 {
        Array::id(self)
    }
    fn label(&self) -> String {
        Array::label(self)
    }
    fn version(&self) -> u64 {
        Array::version(self)
    }
    fn len(&self) -> usize {
        Array::len(self)
    }
    fn is_requires_grad(&self) -> bool {
        Array::is_requires_grad(self)
    }
    fn has_grad(&self) -> bool {
        self.grad_buffer().is_some()
    }
    fn ensure_grad(&self) {
        Array::ensure_grad(self);
    }
    fn zero_grad(&self) {
        Array::zero_grad(self)
    }
    fn reset_grad(&self) {
        Array::reset_grad(self)
    }
    fn element_dim(&self) -> usize {
        T::DIM
    }
    fn scalar_epsilon(&self) -> f64 {
        T::EPSILON
    }
    fn boxed(&self) -> Box<dyn AnyArray> {
        Box::new(self.clone())
    }
    fn grad_any(&self) -> Option<Box<dyn AnyArray>> {
        self.grad_buffer().map(|g| Box::new(g) as Box<dyn AnyArray>)
    }
    fn scalar(&self, k: usize) -> f64 {
        self.get(k / T::DIM).component(k % T::DIM)
    }
    fn set_scalar(&self, k: usize, x: f64) {
        self.modify(|d| d[k / T::DIM].set_component(k % T::DIM, x))
    }
    fn is_dual(&self) -> bool {
        T::DUAL
    }
    fn eps_scalar(&self, k: usize) -> f64 {
        self.get(k / T::DIM).eps_component(k % T::DIM)
    }
    fn set_eps_scalar(&self, k: usize, x: f64) {
        self.modify(|d| d[k / T::DIM].set_eps_component(k % T::DIM, x))
    }
    fn first_non_finite(&self) -> Option<usize> {
        if T::DIM == 0 {
            return None;
        }
        let _g = self.host_lock(false);
        // SAFETY: under the read lock nobody writes (writers hold the write lock).
        let data = unsafe { std::slice::from_raw_parts(self.data_ptr(), self.len()) };
        if T::DUAL {
            // The derivative parts too: a NaN there is a wrong second-order product.
            let bad = |v: &T, k| !v.component(k).is_finite() || !v.eps_component(k).is_finite();
            return data.iter().position(|v| (0..T::DIM).any(|k| bad(v, k)));
        }
        // One pass without branches first, in the element's own arithmetic (integrators check
        // every new state): a sum is finite only if every term is (a finite sum that
        // overflows just takes the slow pass).
        let mut sum = T::zeroed();
        for v in data {
            sum.acc(*v);
        }
        if (0..T::DIM).all(|k| sum.component(k).is_finite()) {
            return None;
        }
        data.iter()
            .position(|v| (0..T::DIM).any(|k| !v.component(k).is_finite()))
    }
    fn lock(&self, write: bool, _: Token) -> ArrayLock<'_> {
        self.inner.acquire_in_group(write, false)
    }
    fn mark_written(&self, _: Token) {
        self.bump_version()
    }
    fn new_claim_epoch(&self, _: Token) {
        Array::new_claim_epoch(self)
    }
    fn as_any(&self) -> &dyn std::any::Any {
        self
    }
    fn add_from(&self, src: &dyn AnyArray) {
        let src = src
            .as_any()
            .downcast_ref::<Array<T>>()
            .unwrap_or_else(|| {
                panic!(
                    "add `{}` into `{}`: element types differ",
                    src.label(),
                    self.label()
                )
            })
            .to_vec();
        let label = self.label();
        self.modify(|d| {
            assert_eq!(d.len(), src.len(), "add into `{label}`: length mismatch");
            for (a, b) in d.iter_mut().zip(src) {
                a.acc(b);
            }
        })
    }
    fn tangent_any(&self) -> Option<Box<dyn AnyArray>> {
        self.tangent_buffer()
            .map(|t| Box::new(t) as Box<dyn AnyArray>)
    }
    fn reset_tangent(&self) {
        self.ensure_tangent().fill(T::zeroed())
    }
    fn clear_tangent(&self) {
        self.set_tangent(None)
    }
    fn deep_clone_any(&self) -> Box<dyn AnyArray> {
        Box::new(self.deep_clone())
    }
    fn copy_from(&self, src: &dyn AnyArray) {
        let src = src
            .as_any()
            .downcast_ref::<Array<T>>()
            .unwrap_or_else(|| {
                panic!(
                    "copy `{}` into `{}`: element types differ",
                    src.label(),
                    self.label()
                )
            })
            .to_vec();
        self.assign(&src)
    }
}

/// Maps for writing the pages wholly inside the `bytes` bytes at `start`, in one call
/// (`madvise(MADV_POPULATE_WRITE)`, Linux 5.14 and later): from 4 pages on, a third cheaper
/// than faulting page by page (1.1 against 1.8 us a page at 54 pages, docs/performance.md).
/// False where the call is not offered or the buffer is too small to gain: the caller then
/// touches the pages itself.
#[cfg(target_os = "linux")]
fn populate_for_writing(start: *mut u8, bytes: usize) -> bool {
    const PAGE: usize = 4096;
    if bytes < 4 * PAGE {
        return false;
    }
    let first = (start as usize).next_multiple_of(PAGE);
    let end = (start as usize + bytes) & !(PAGE - 1);
    // SAFETY: `first..end` lies inside the caller's buffer; populating maps pages and leaves
    // their contents as they are.
    unsafe {
        libc::madvise(
            first as *mut libc::c_void,
            end - first,
            libc::MADV_POPULATE_WRITE,
        ) == 0
    }
}

#[cfg(not(target_os = "linux"))]
fn populate_for_writing(_: *mut u8, _: usize) -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::real::Vec3;

    /// Zeros of every size class (under the page-population threshold, over it, lengths that
    /// end inside a page, an element size that does not divide a page) read zero everywhere
    /// and keep what is written, also in memory freed by an earlier array.
    #[test]
    fn zeros_are_zero_and_writable_at_every_size() {
        for round in 0..2 {
            for len in [0, 1, 100, 682, 683, 700, 10_001, 100_003] {
                let a = Array::<Vec3<f64>>::zeros(len);
                let v = a.to_vec();
                assert_eq!(v.len(), len);
                assert!(
                    v.iter().all(|x| *x == Vec3::zeros()),
                    "round {round}, {len} elements"
                );
                let filled: Vec<_> = (0..len).map(|k| Vec3::new(k as f64, 1.0, -1.0)).collect();
                a.assign(&filled);
                assert_eq!(a.to_vec(), filled);
            }
        }
    }
}

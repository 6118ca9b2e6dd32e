//! Where a view reads or writes (the kernel, the parameter, the array's name) and the index
//! checks that name them when they fail.

use std::ops::Range;
use std::sync::Arc;

use crate::array::{Array, Element, NameRef};

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
pub(super) fn out_of_bounds(place: &Place, index: i128, len: usize) -> ! {
    let site = place.site;
    match place.name() {
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

/// Where a view reads or writes: the kernel, the parameter and the array, for errors.
#[derive(Clone)]
pub(super) struct Place {
    pub(super) site: &'static Site,
    /// The array's name, read only when an error names it: reading it as each view is made
    /// took a mutex per parameter per launch.
    name: NameRef,
}

impl Place {
    pub(super) fn of<T: Element>(a: &Array<T>, site: &'static Site) -> Self {
        Place {
            site,
            name: a.name_ref(),
        }
    }

    /// The array's name (see [`Array::named`]).
    pub(super) fn name(&self) -> Option<Arc<str>> {
        self.name.get()
    }
}

#[inline(always)]
pub(super) fn checked<I: ToIndex>(i: I, len: usize, place: &Place) -> usize {
    let w = i.to_i128();
    if w < 0 || w >= len as i128 {
        out_of_bounds(place, w, len)
    }
    w as usize
}

/// `i` as an index of a scatter whose indices must lie in `lo..hi` (`0..len`, or the chunk's
/// own thread ids for a scatter at the thread id writing directly before its turn): one
/// comparison, as for `0..len`.
#[inline(always)]
pub(super) fn checked_in<I: ToIndex>(
    i: I,
    lo: usize,
    hi: usize,
    len: usize,
    place: &Place,
) -> usize {
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
        out_of_bounds(place, index, len)
    }
    panic!(
        "kernel `{}`: a scatter into parameter `{}` at index {index}, outside the thread ids \
         {own:?} of its chunk, through a view for scatters at the thread's own index",
        place.site.kernel, place.site.param
    )
}

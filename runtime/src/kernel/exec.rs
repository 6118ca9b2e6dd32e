//! What a launch hands the chunks it runs: [`Exec`].

use std::ops::Range;
use std::sync::Arc;

use super::place::Site;
use crate::array::{Array, Element};
use crate::chunk_order::ChunkOrder;

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
    pub(super) locked: &'a [(u64, bool)],
    /// The thread ids of this chunk: a store claims only for these (chunks are disjoint).
    pub(super) range: Range<usize>,
    /// A logged chunk: the launch's chunk order and this chunk's place in it (to flush a
    /// large log early, once every earlier chunk is applied).
    pub(super) order: Option<(&'a ChunkOrder, usize)>,
    /// Buffers that two parameters of the launch scatter into (an array passed twice, read by
    /// both, in the adjoint): such a launch runs serially, and no scatter into them writes
    /// directly before its chunk's turn, even one at the thread's own index.
    pub(super) shared_scatters: &'a [u64],
    /// The head of a range of a split launch (see `crate::split`): its scatters log only
    /// what an earlier range also adds to.
    pub(super) halo: Option<Halo<'a>>,
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
    pub(super) fn check<T: Element>(&self, buf: Option<&Array<T>>, write: bool, site: &Site) {
        let Some(b) = buf else { return };
        // A scan without early exit: for the tens of buffers a launch holds it vectorizes and
        // beats a binary search's unpredictable branches.
        let id = b.id();
        let held = self
            .locked
            .iter()
            .fold(false, |found, &(i, w)| found | ((i == id) & (w == write)));
        if !held {
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

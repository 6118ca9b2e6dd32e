//! Static splits of a parallel launch whose scatter indices are known ahead.
//!
//! When every scatter of a kernel (other than those at the thread id) indexes through index
//! arrays alone (`let [i, j] = springs[t]; f.atomic_add(i, ..)`), the launch can compute, once
//! per version of those arrays, the first thread id that adds to each element. It then splits
//! `0..dim` into one contiguous range per worker. A range writes directly every element that
//! no earlier range touches; it logs only the additions to elements an earlier range also
//! touches, and those happen in its *head*, the ids up to its last such addition. The rest of
//! the range, its tail, runs the plain direct loop. After the ranges ran, the heads' logs are
//! applied in range order: every element receives its additions in thread-id order, the bits
//! of a serial launch. On a mesh in mesh order the heads are a few rows of elements, so nearly
//! nothing is logged and no worker waits for another.

use std::any::TypeId;
use std::collections::HashMap;
use std::ops::Range;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};

use crate::kernel::{Exec, Halo, KernelBody, Mode, ScatterLog};
use crate::region::Region;

/// A split of one launch: each range with the end of its head, and the first-touch maps.
pub(crate) struct Plan {
    /// `(range, head_end)`: ids `range.start..head_end` run logging what earlier ranges touch.
    ranges: Vec<(Range<usize>, usize)>,
    /// Per scattered parameter (in the order of `StaticScatters::targets`): the first
    /// thread id adding to each element (`u32::MAX` if none).
    firsts: Vec<Arc<[u32]>>,
}

impl Plan {
    /// Whether the heads are small enough for the split to pay: at most a quarter of the
    /// ids (a mesh in random order has heads spanning most of each range).
    fn pays(&self, dim: usize) -> bool {
        let head: usize = self.ranges.iter().map(|(r, h)| h - r.start).sum();
        4 * head <= dim
    }
}

type Key = (TypeId, Mode, usize, usize, Vec<(u64, u64)>, Vec<usize>);

/// Plans by kernel, mode, size, parts, index arrays' (id, version) and targets' lengths (not
/// their ids: a simulation scatters into new force arrays every step).
/// `None`: the heads were too large.
static PLANS: Mutex<Option<HashMap<Key, Option<Arc<Plan>>>>> = Mutex::new(None);
/// Plans kept at most (a program relaunching with ever new index arrays starts over).
const KEEP: usize = 256;

/// The split of `kernel`'s launch over `0..dim` in `mode` into `parts` ranges, if its scatters
/// are static and the split pays. `locked`, `shared`: the launch's locked buffers; `built`
/// is set if the plan was made now.
#[allow(clippy::too_many_arguments)]
pub(crate) fn plan<K: KernelBody<O>, O>(
    kernel: &K,
    args: &O,
    mode: Mode,
    dim: usize,
    parts: usize,
    locked: &[(u64, bool)],
    shared: &[u64],
    built: &mut bool,
) -> Option<Arc<Plan>> {
    let statics = K::static_scatters(mode)?;
    let arrays = K::arrays(args);
    let array = |p: usize| arrays.get(p).copied().flatten();
    let deps: Vec<(u64, u64)> = statics
        .deps
        .iter()
        .map(|&p| array(p).map_or((0, 0), |a| (a.id(), a.version())))
        .collect();
    let targets: Vec<usize> = statics
        .targets
        .iter()
        .map(|&p| array(p).map_or(0, |a| a.len()))
        .collect();
    let key: Key = (TypeId::of::<K>(), mode, dim, parts, deps, targets);
    if let Some(p) = with_plans(|m| m.get(&key).cloned()) {
        return p;
    }
    *built = true;
    let plan = build(kernel, args, mode, dim, parts, &key.5, locked, shared);
    let plan = plan.pays(dim).then(|| Arc::new(plan));
    with_plans(|m| {
        if m.len() >= KEEP {
            m.clear();
        }
        m.insert(key, plan.clone());
    });
    plan
}

fn with_plans<R>(f: impl FnOnce(&mut HashMap<Key, Option<Arc<Plan>>>) -> R) -> R {
    let mut g = PLANS.lock().unwrap_or_else(PoisonError::into_inner);
    f(g.get_or_insert_with(HashMap::new))
}

/// The ranges of `0..dim` in `parts` parts, as equal as can be.
fn ranges(dim: usize, parts: usize) -> Vec<Range<usize>> {
    (0..parts)
        .map(|r| r * dim / parts..(r + 1) * dim / parts)
        .collect()
}

#[allow(clippy::too_many_arguments)]
fn build<K: KernelBody<O>, O>(
    kernel: &K,
    args: &O,
    mode: Mode,
    dim: usize,
    parts: usize,
    targets: &[usize],
    locked: &[(u64, bool)],
    shared: &[u64],
) -> Plan {
    let ranges = ranges(dim, parts);
    let mut firsts: Vec<Vec<u32>> = targets.iter().map(|&n| vec![u32::MAX; n]).collect();
    let mut head_end: Vec<usize> = ranges.iter().map(|r| r.start).collect();
    let mut part = 0;
    // Thread ids come in order, so an element's first toucher is set at its first visit, and
    // when a later id visits it, every id before that one has been seen.
    let mut sink = |slot: usize, tid: usize, index: i128| {
        let map = &mut firsts[slot];
        // An index out of bounds is the kernel's own error when it runs.
        let Ok(i) = usize::try_from(index) else {
            return;
        };
        let Some(first) = map.get_mut(i) else { return };
        while tid >= ranges[part].end {
            part += 1;
        }
        if *first == u32::MAX {
            *first = tid as u32;
        } else if (*first as usize) < ranges[part].start {
            head_end[part] = tid + 1;
        }
    };
    let exec = Exec::new(true, locked, shared, 0..dim);
    kernel.scatter_indices(mode, args, 0..dim, &exec, &mut sink);
    Plan {
        ranges: ranges.into_iter().zip(head_end).collect(),
        firsts: firsts.into_iter().map(Arc::from).collect(),
    }
}

/// Launches run split so far (for tests that check a launch took this path).
static LAUNCHES: AtomicU64 = AtomicU64::new(0);

/// How many launches so far ran as a static split (see `docs/performance.md`, "How a parallel
/// launch scatters"): for tests that a launch took that path.
pub(crate) fn launches() -> u64 {
    LAUNCHES.load(Ordering::Relaxed)
}

/// Runs `kernel` over the plan's ranges in parallel (shares of `region`), then applies the
/// heads' logs in order on the calling thread.
pub(crate) fn run<K: KernelBody<O>, O: Sync>(
    kernel: &K,
    args: &O,
    mode: Mode,
    plan: &Plan,
    locked: &[(u64, bool)],
    shared: &[u64],
    region: &Region,
) {
    LAUNCHES.fetch_add(1, Ordering::Relaxed);
    // The maps by the ids of this launch's arrays (scatters find theirs by array id).
    let arrays = K::arrays(args);
    let statics = K::static_scatters(mode).expect("a split launch has static scatters");
    let firsts: Vec<(u64, Arc<[u32]>)> = statics
        .targets
        .iter()
        .zip(&plan.firsts)
        .filter_map(|(&p, m)| Some((arrays.get(p).copied().flatten()?.id(), m.clone())))
        .collect();
    let logs: Vec<Vec<ScatterLog>> = region.shares(plan.ranges.len(), |r| {
        let (range, head_end) = &plan.ranges[r];
        let head = range.start..*head_end;
        let logs = match head.is_empty() {
            true => Vec::new(),
            false => {
                let halo = Halo {
                    firsts: &firsts,
                    bound: range.start as u32,
                };
                kernel.run(
                    mode,
                    args,
                    head.clone(),
                    &Exec::halo(locked, shared, head, halo),
                )
            }
        };
        let tail = *head_end..range.end;
        if !tail.is_empty() {
            let direct = kernel.run(
                mode,
                args,
                tail.clone(),
                &Exec::new(true, locked, shared, tail),
            );
            debug_assert!(direct.iter().all(|l| l.0.is_none()));
        }
        logs
    });
    for log in logs.iter().flatten().filter_map(|l| l.0.as_deref()) {
        // SAFETY: every range has finished; logs go in range order, each in thread-id order.
        unsafe { log.apply() }
    }
}

#[cfg(test)]
mod tests {
    use super::ranges;

    #[test]
    fn ranges_cover_every_id_once() {
        for (dim, parts) in [(10, 3), (4096, 2), (7, 7), (5000, 4)] {
            let r = ranges(dim, parts);
            assert_eq!(r.len(), parts);
            assert_eq!(r[0].start, 0);
            assert_eq!(r[parts - 1].end, dim);
            assert!(r.windows(2).all(|w| w[0].end == w[1].start));
        }
    }
}

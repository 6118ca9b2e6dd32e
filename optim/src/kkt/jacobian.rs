//! The sparse Jacobian of a tape's outputs in its inputs, from tangent passes.
//!
//! The first time, the sparsity pattern is found by probing (group testing: random groups of
//! the input elements seeded at once; an output element a probe leaves at zero is not touched
//! by any element of the group), which takes a few rounds of [`GROUPS`] passes where one pass
//! per column would take thousands; a small Jacobian, or one the probes find dense, is taken
//! one pass per column instead (a unit seed). After that the columns are coloured so that no
//! two of one colour share a row (Curtis, Powell and Reid's compression), and one pass per colour, seeded on all of its
//! columns, gives every column of that colour at once: a cloth's stiffness takes a few dozen
//! passes instead of three per particle. The pattern is the values' at the point it was found
//! (a contact may start touching later), so each compressed Jacobian is checked by two more
//! passes along random directions; if it disagrees, the columns are taken one by one again and
//! the pattern grows.

use adflex_runtime::Error;

use crate::newton::Apply;

/// A matrix in compressed columns.
pub(super) struct Sparse {
    pub rows: usize,
    /// Column `j` holds the entries `ptr[j]..ptr[j + 1]` of `idx` (rows, ascending) and `val`.
    pub ptr: Vec<usize>,
    pub idx: Vec<usize>,
    pub val: Vec<f64>,
}

impl Sparse {
    pub fn cols(&self) -> usize {
        self.ptr.len() - 1
    }

    /// Rows and values of column `j`.
    pub fn col(&self, j: usize) -> (&[usize], &[f64]) {
        let r = self.ptr[j]..self.ptr[j + 1];
        (&self.idx[r.clone()], &self.val[r])
    }

    /// `A v`.
    pub fn mul(&self, v: &[f64]) -> Vec<f64> {
        self.sum_by_row(v, |x| x)
    }

    /// The sum over each row of `|A_ij v_j|`: the size of `A v`'s rounding.
    fn abs_mul(&self, v: &[f64]) -> Vec<f64> {
        self.sum_by_row(v, f64::abs)
    }

    /// `sum_j f(A_ij v_j)` for each row `i`.
    fn sum_by_row(&self, v: &[f64], f: impl Fn(f64) -> f64) -> Vec<f64> {
        let mut out = vec![0.0; self.rows];
        for (j, vj) in v.iter().enumerate() {
            let (rows, vals) = self.col(j);
            for (i, a) in rows.iter().zip(vals) {
                out[*i] += f(a * vj);
            }
        }
        out
    }
}

/// Where a Jacobian's entries may be nonzero, and the columns' colours.
pub(super) struct Pattern {
    rows: usize,
    ptr: Vec<usize>,
    idx: Vec<usize>,
    colour: Vec<usize>,
    colours: usize,
    /// Checks made with this pattern (each takes new random directions).
    probes: std::cell::Cell<u64>,
    /// Rows that read so many columns (more than [`DENSE`] and an eighth of them) that
    /// colouring them would give each column its own colour: left out of the colouring and
    /// taken by one reverse (adjoint) pass each.
    dense: Vec<usize>,
}

/// Columns a row reads at most and still takes part in the colouring (see [`Pattern::dense`]).
pub(super) const DENSE: usize = 64;

/// The elements of the arrays behind the columns and the rows: `starts[e]..starts[e + 1]`
/// are element `e`'s scalars (a `Vec3` is three).
pub(super) struct Elements<'a> {
    pub cols: &'a [usize],
    pub rows: &'a [usize],
}

impl Pattern {
    /// The pattern of `a`'s nonzeros, closed over elements (if one scalar of an input element
    /// moves one scalar of an output element, every scalar of the one may move every scalar of
    /// the other: a spring along an axis has exact zeros in its stiffness that are not zero
    /// once it turns) and joined with `old`'s entries (a contact that let go may touch again),
    /// coloured greedily in column order.
    fn of(a: &Sparse, old: Option<&Pattern>, elements: &Elements<'_>) -> Self {
        let (rows, cols) = (a.rows, a.cols());
        let mut row_element = vec![0; rows];
        for (e, w) in elements.rows.windows(2).enumerate() {
            row_element[w[0]..w[1]].iter_mut().for_each(|r| *r = e);
        }
        let mut ptr = vec![0];
        let mut idx = Vec::new();
        let mut mark = vec![usize::MAX; elements.rows.len()];
        for (e, w) in elements.cols.windows(2).enumerate() {
            // The output elements this input element moves.
            let mut touched = Vec::new();
            for j in w[0]..w[1] {
                let (r, v) = a.col(j);
                let nonzero = r.iter().zip(v).filter(|(_, v)| **v != 0.0).map(|(i, _)| *i);
                let kept = old.map(|o| &o.idx[o.ptr[j]..o.ptr[j + 1]]).unwrap_or(&[]);
                for i in nonzero.chain(kept.iter().copied()) {
                    let out = row_element[i];
                    if mark[out] != e {
                        mark[out] = e;
                        touched.push(out);
                    }
                }
            }
            touched.sort_unstable();
            for _ in w[0]..w[1] {
                for &out in &touched {
                    idx.extend(elements.rows[out]..elements.rows[out + 1]);
                }
                ptr.push(idx.len());
            }
        }
        // Rows to columns, to find each column's neighbours (columns sharing a row); a dense
        // row has none (it is taken by a reverse pass).
        let mut count = vec![0usize; rows];
        for &i in &idx {
            count[i] += 1;
        }
        let limit = DENSE.max(cols / 8);
        let dense: Vec<usize> = (0..rows).filter(|&i| count[i] > limit).collect();
        let mut row_ptr = vec![0usize; rows + 1];
        for &i in &idx {
            if count[i] <= limit {
                row_ptr[i + 1] += 1;
            }
        }
        for i in 0..rows {
            row_ptr[i + 1] += row_ptr[i];
        }
        let mut fill = row_ptr.clone();
        let mut row_cols = vec![0usize; idx.len()];
        for j in 0..cols {
            for &i in idx[ptr[j]..ptr[j + 1]]
                .iter()
                .filter(|i| count[**i] <= limit)
            {
                row_cols[fill[i]] = j;
                fill[i] += 1;
            }
        }
        let mut colour = vec![usize::MAX; cols];
        let mut taken = Vec::<usize>::new(); // taken[c] == j: colour c is a neighbour's of j
        let mut colours = 0;
        for j in 0..cols {
            for &i in &idx[ptr[j]..ptr[j + 1]] {
                for &n in &row_cols[row_ptr[i]..row_ptr[i + 1]] {
                    if colour[n] != usize::MAX {
                        taken[colour[n]] = j;
                    }
                }
            }
            let c = (0..colours).find(|&c| taken[c] != j).unwrap_or(colours);
            if c == colours {
                colours += 1;
                taken.push(usize::MAX);
            }
            colour[j] = c;
        }
        Pattern {
            rows,
            ptr,
            idx,
            colour,
            colours,
            probes: std::cell::Cell::new(0),
            dense,
        }
    }

    /// Passes a compressed Jacobian takes.
    #[cfg(test)]
    pub fn colours(&self) -> usize {
        self.colours
    }
}

/// The Jacobian of `forward`, a tangent pass (its rows and columns in `elements`; `reverse`
/// the adjoint pass, for the dense rows). With a pattern from an earlier call, one pass per
/// colour (and per dense row) and a check along two random directions (relative `tol` per
/// row); without one, the pattern found by probing, then the same; for a small Jacobian, or
/// if the check fails, one pass per column, and `pattern` becomes (or grows to) that
/// Jacobian's. `passes` counts the passes.
pub(super) fn jacobian(
    forward: &mut Apply<'_>,
    reverse: &mut Apply<'_>,
    elements: &Elements<'_>,
    pattern: &mut Option<Pattern>,
    tol: f64,
    passes: &mut usize,
) -> Result<Sparse, Error> {
    let last = |starts: &[usize]| starts[starts.len() - 1];
    let (rows, cols) = (last(elements.rows), last(elements.cols));
    if let Some(p) = pattern
        .as_ref()
        .filter(|p| p.rows == rows && p.ptr.len() == cols + 1)
    {
        let a = compressed(forward, reverse, p, passes)?;
        if agrees(forward, &a, p, tol, passes)? {
            return Ok(a);
        }
    }
    let old = pattern
        .take()
        .filter(|p| p.rows == rows && p.ptr.len() == cols + 1);
    if old.is_none() {
        // The first time: the pattern by probing, then the values by colours, checked.
        if let Some(probed) = probe(forward, elements, passes)? {
            let p = Pattern::of(&probed, None, elements);
            let a = compressed(forward, reverse, &p, passes)?;
            if agrees(forward, &a, &p, tol, passes)? {
                *pattern = Some(p);
                return Ok(a);
            }
        }
    }
    let a = by_columns(forward, rows, cols, passes)?;
    // An old pattern of other sizes (the residuals changed in number) is dropped.
    *pattern = Some(Pattern::of(&a, old.as_ref(), elements));
    Ok(a)
}

/// The next state of a xorshift64 generator (the probes' and the checks' fixed sequences).
fn xorshift(state: &mut u64) -> u64 {
    *state ^= *state >> 12;
    *state ^= *state << 25;
    *state ^= *state >> 27;
    *state
}

/// A weight in `±[0.5, 1.5)` from the high 24 bits of `bits` (exact in `f32`), negative if
/// `negative`.
fn weight(bits: u64, negative: bool) -> f64 {
    let u = (bits >> 40) as f64 / (1u64 << 24) as f64;
    (0.5 + u) * if negative { -1.0 } else { 1.0 }
}

/// xorshift64*'s multiplier.
const STAR: u64 = 0x2545_f491_4f6c_dd1d;

/// Groups of input elements per round of probing (more when a probe moves too many rows).
pub(super) const GROUPS: usize = 32;

/// The candidate lists' entries at most (64 MB of indices): past it, more groups.
const CANDIDATES: usize = 8 << 20;

/// The pattern of the Jacobian at the level of elements, by probing (`None`: too few input
/// elements for probing to save passes, a pattern too dense, or probes that would cost as
/// many passes as the columns). Each round partitions the input elements at random into
/// groups and seeds each group's scalars with random weights (exact in `f32`, from a fixed
/// sequence: runs repeat exactly) in one pass; an input element's candidates are the output
/// elements every probe of it moved. An output element moved by `k` other input elements
/// stays a false candidate with probability `1 - (1 - 1/groups)^k` per round, so rounds go
/// on until one removes no candidate; a false candidate left costs only colours, and a missed
/// entry (weights that cancel exactly) above the check's tolerance is caught by the check
/// that follows. The first round starts with [`GROUPS`] groups and takes four times as many
/// while its candidate lists would hold more than [`CANDIDATES`] entries or half of all
/// pairs (a probe that moves most rows tells little). Returns a matrix with a nonzero at every
/// candidate's scalars.
fn probe(
    forward: &mut Apply<'_>,
    elements: &Elements<'_>,
    passes: &mut usize,
) -> Result<Option<Sparse>, Error> {
    let (col_el, row_el) = (elements.cols.len() - 1, elements.rows.len() - 1);
    let cols = elements.cols[col_el];
    let rows = elements.rows[row_el];
    // Probing takes a few rounds of groups (about 200 to 550 sweeps on a cloth): below 16
    // rounds' worth of columns, one pass per column is as cheap.
    if col_el < 4 * GROUPS || cols < 16 * GROUPS {
        return Ok(None);
    }
    // Probing that would take three quarters of the columns' passes gives up (then the
    // columns are taken one by one: at most 1.75 times their passes in all).
    let over = |passes: usize, groups: usize| 4 * (passes + groups) > 3 * cols;
    let mut row_element = vec![0; rows];
    for (e, w) in elements.rows.windows(2).enumerate() {
        row_element[w[0]..w[1]].iter_mut().for_each(|r| *r = e);
    }
    let mut state = STAR;
    // xorshift64*
    let mut random = move || xorshift(&mut state).wrapping_mul(STAR);
    let mut mark = vec![usize::MAX; row_el];
    let mut seed = vec![0.0; cols];
    let mut probes = 0usize;
    // One round: each group's probe, the output elements it moved (a NaN moves one too).
    let mut round = |groups: usize, passes: &mut usize| -> Result<_, Error> {
        let group: Vec<usize> = (0..col_el)
            .map(|_| (random() % groups as u64) as usize)
            .collect();
        let mut members = vec![Vec::new(); groups];
        for (e, g) in group.iter().enumerate() {
            members[*g].push(e);
        }
        let mut moved = vec![Vec::new(); groups];
        for (g, members) in members.iter().enumerate().filter(|(_, m)| !m.is_empty()) {
            for &e in members {
                for s in &mut seed[elements.cols[e]..elements.cols[e + 1]] {
                    let r = random();
                    *s = weight(r, r & 1 == 1);
                }
            }
            let t = forward(&seed)?;
            *passes += 1;
            seed.iter_mut().for_each(|s| *s = 0.0);
            probes += 1;
            for (i, v) in t.iter().enumerate() {
                let o = row_element[i];
                if *v != 0.0 && mark[o] != probes {
                    mark[o] = probes;
                    moved[g].push(o);
                }
            }
            moved[g].sort_unstable();
        }
        Ok((members, moved))
    };
    let mut groups = GROUPS;
    let (members, moved) = loop {
        let (members, moved) = round(groups, passes)?;
        let size: usize = members
            .iter()
            .zip(&moved)
            .map(|(m, o)| m.len() * o.len())
            .sum();
        if size <= CANDIDATES && 2 * size <= col_el * row_el {
            break (members, moved);
        }
        groups *= 4;
        if 4 * groups > col_el || over(*passes, groups) {
            return Ok(None);
        }
    };
    // Each input element's candidates (sorted).
    let mut candidates: Vec<Vec<usize>> = vec![Vec::new(); col_el];
    for (m, o) in members.iter().zip(&moved) {
        for &e in m {
            candidates[e] = o.clone();
        }
    }
    loop {
        if over(*passes, groups) {
            return Ok(None);
        }
        let (members, moved) = round(groups, passes)?;
        let mut removed = 0usize;
        for (m, o) in members.iter().zip(&moved) {
            for &e in m {
                let before = candidates[e].len();
                candidates[e].retain(|x| o.binary_search(x).is_ok());
                removed += before - candidates[e].len();
            }
        }
        if removed == 0 {
            break;
        }
    }
    let mut a = Sparse {
        rows,
        ptr: vec![0],
        idx: Vec::new(),
        val: Vec::new(),
    };
    for (e, c) in candidates.iter().enumerate() {
        for _ in elements.cols[e]..elements.cols[e + 1] {
            for &o in c {
                a.idx.extend(elements.rows[o]..elements.rows[o + 1]);
            }
            a.ptr.push(a.idx.len());
        }
    }
    a.val = vec![1.0; a.idx.len()];
    Ok(Some(a))
}

/// One pass per column; the exact zeros are left out.
fn by_columns(
    forward: &mut Apply<'_>,
    rows: usize,
    cols: usize,
    passes: &mut usize,
) -> Result<Sparse, Error> {
    let mut a = Sparse {
        rows,
        ptr: vec![0],
        idx: Vec::new(),
        val: Vec::new(),
    };
    let mut e = vec![0.0; cols];
    for j in 0..cols {
        e[j] = 1.0;
        let t = forward(&e)?;
        e[j] = 0.0;
        *passes += 1;
        for (i, v) in t.into_iter().enumerate() {
            // A NaN is kept: the caller names its column.
            if v != 0.0 {
                a.idx.push(i);
                a.val.push(v);
            }
        }
        a.ptr.push(a.idx.len());
    }
    Ok(a)
}

/// One pass per colour, seeded with 1 on the colour's columns: row `i` of the result is the
/// entry `(i, j)` of the one column `j` of that colour whose pattern has row `i`; and one
/// reverse pass per dense row, seeded with 1 on it: the row's entries.
fn compressed(
    forward: &mut Apply<'_>,
    reverse: &mut Apply<'_>,
    p: &Pattern,
    passes: &mut usize,
) -> Result<Sparse, Error> {
    let cols = p.ptr.len() - 1;
    let mut val = vec![0.0; p.idx.len()];
    let mut dense_at = vec![usize::MAX; p.rows];
    let mut dense_rows = Vec::with_capacity(p.dense.len());
    let mut w = vec![0.0; p.rows];
    for (k, &i) in p.dense.iter().enumerate() {
        dense_at[i] = k;
        w[i] = 1.0;
        dense_rows.push(reverse(&w)?);
        w[i] = 0.0;
        *passes += 1;
    }
    let mut by_colour = vec![Vec::new(); p.colours];
    for j in 0..cols {
        by_colour[p.colour[j]].push(j);
    }
    let mut seed = vec![0.0; cols];
    for members in &by_colour {
        for &j in members {
            seed[j] = 1.0;
        }
        let t = forward(&seed)?;
        *passes += 1;
        for &j in members {
            seed[j] = 0.0;
            let span = p.ptr[j]..p.ptr[j + 1];
            for (v, &i) in val[span.clone()].iter_mut().zip(&p.idx[span]) {
                *v = match dense_at[i] {
                    usize::MAX => t[i],
                    d => dense_rows[d][j],
                };
            }
        }
    }
    Ok(Sparse {
        rows: p.rows,
        ptr: p.ptr.clone(),
        idx: p.idx.clone(),
        val,
    })
}

/// Whether `a v` matches a tangent pass along `v` for two random directions: one scaled by
/// each column's largest entry (every column weighs alike whatever its units), one not (an
/// entry missing from a row of small entries, beside a column of large ones, shows there).
/// Each row must agree to `tol` of its `Σ |a_ij v_j|` (NaN disagrees). The directions'
/// entries are exact in `f32`, so an `f32` input takes them unrounded; they change from call
/// to call (`p.probes`), from a fixed sequence, so runs repeat exactly.
fn agrees(
    forward: &mut Apply<'_>,
    a: &Sparse,
    p: &Pattern,
    tol: f64,
    passes: &mut usize,
) -> Result<bool, Error> {
    let probes = p.probes.get();
    p.probes.set(probes + 1);
    let mut state = 0x9e37_79b9_7f4a_7c15u64 ^ probes.wrapping_mul(0xbf58_476d_1ce4_e5b9);
    let mut random = || {
        let s = xorshift(&mut state);
        weight(s.wrapping_mul(STAR), s & 1 == 1)
    };
    for scaled in [true, false] {
        let v: Vec<f64> = (0..a.cols())
            .map(|j| {
                let largest = a.col(j).1.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                let size = match scaled && largest > 0.0 {
                    // A power of two: the entry stays exact in f32.
                    true => (1.0 / largest).log2().round().exp2(),
                    false => 1.0,
                };
                random() * size
            })
            .collect();
        let t = forward(&v)?;
        *passes += 1;
        let (av, bound) = (a.mul(&v), a.abs_mul(&v));
        let agree = t
            .iter()
            .zip(av.iter().zip(&bound))
            .all(|(t, (av, b))| (t - av).abs() <= tol * (b + t.abs()));
        if !agree {
            return Ok(false);
        }
    }
    Ok(true)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::newton::dot;

    /// [`jacobian`] of `f`, its reverse pass `Jᵀ w` from `f`'s columns.
    fn jac(
        f: &dyn Fn(&[f64]) -> Vec<f64>,
        elements: &Elements<'_>,
        pattern: &mut Option<Pattern>,
        passes: &mut usize,
    ) -> Sparse {
        let cols = elements.cols[elements.cols.len() - 1];
        let mut forward = |v: &[f64]| Ok(f(v));
        let mut reverse = |w: &[f64]| {
            Ok((0..cols)
                .map(|j| {
                    let e: Vec<f64> = (0..cols).map(|k| (k == j) as u8 as f64).collect();
                    dot(&f(&e), w)
                })
                .collect())
        };
        jacobian(&mut forward, &mut reverse, elements, pattern, 1e-12, passes).unwrap()
    }

    /// A tridiagonal Jacobian with a dense last column: three colours for the band, one more
    /// for the dense column.
    fn band(n: usize, extra: Option<(usize, usize)>) -> impl Fn(&[f64]) -> Vec<f64> {
        move |v: &[f64]| {
            let mut out: Vec<f64> = (0..n)
                .map(|i| {
                    let band = i.saturating_sub(1)..(i + 2).min(n);
                    let entry = |j: usize| (1.0 + i as f64 + 0.5 * j as f64) * v[j];
                    band.map(entry).sum::<f64>() + 0.25 * v[n]
                })
                .collect();
            if let Some((i, j)) = extra {
                out[i] += 3.0 * v[j];
            }
            out
        }
    }

    #[test]
    fn coloured_passes_give_the_columns_and_a_new_entry_is_found() {
        let n = 30;
        let f = band(n, None);
        let (cols, rows): (Vec<usize>, Vec<usize>) = ((0..=n + 1).collect(), (0..=n).collect());
        let scalars = Elements {
            cols: &cols,
            rows: &rows,
        };
        let (mut pattern, mut passes) = (None, 0);
        let first = jac(&f, &scalars, &mut pattern, &mut passes);
        assert_eq!(passes, n + 1);
        assert_eq!(pattern.as_ref().unwrap().colours(), 4);
        passes = 0;
        let again = jac(&f, &scalars, &mut pattern, &mut passes);
        assert_eq!(passes, 6, "four colours and the check's two passes");
        assert_eq!((&first.idx, &first.val), (&again.idx, &again.val));
        // An entry outside the pattern: the check fails, the columns are taken one by one,
        // and the pattern grows.
        let g = band(n, Some((0, 10)));
        passes = 0;
        let grown = jac(&g, &scalars, &mut pattern, &mut passes);
        assert_eq!(passes, 4 + 1 + n + 1, "the check fails at its first pass");
        let e10: Vec<f64> = (0..=n).map(|j| (j == 10) as u8 as f64).collect();
        assert_eq!(grown.mul(&e10), g(&e10));
        assert_eq!(pattern.as_ref().unwrap().colours(), 5);
    }
    /// A large Jacobian's pattern is found by probing: the band and the dense column exactly
    /// (four colours), the values those of unit seeds, in a few rounds of passes instead of
    /// one per column; a probe's entry outside the band is found too, and a dense Jacobian
    /// falls back to one pass per column after two rounds.
    #[test]
    fn a_large_pattern_is_found_by_probing() {
        let n = 2000;
        for extra in [None, Some((3, 1500))] {
            let f = band(n, extra);
            let (cols, rows): (Vec<usize>, Vec<usize>) = ((0..=n + 1).collect(), (0..=n).collect());
            let scalars = Elements {
                cols: &cols,
                rows: &rows,
            };
            let (mut pattern, mut passes) = (None, 0);
            let a = jac(&f, &scalars, &mut pattern, &mut passes);
            let colours = pattern.as_ref().unwrap().colours();
            println!(
                "{extra:?}: {passes} passes for {} columns, {colours} colours",
                n + 1
            );
            assert!(passes <= 16 * GROUPS, "{passes} passes");
            assert_eq!(colours, if extra.is_some() { 5 } else { 4 });
            for j in [0, 1, 2, 999, 1500, n - 1, n] {
                let e: Vec<f64> = (0..=n).map(|k| (k == j) as u8 as f64).collect();
                assert_eq!(a.mul(&e), f(&e), "column {j}");
                // Only the true entries: no false candidate left.
                assert!(a.col(j).0.len() <= if j == n { n } else { 4 }, "column {j}");
            }
        }
        // Dense: every row reads every column.
        let m = 800;
        let dense = |v: &[f64]| -> Vec<f64> {
            let s: f64 = v.iter().sum();
            (0..m).map(|i| s + i as f64 * v[i]).collect()
        };
        let (cols, rows): (Vec<usize>, Vec<usize>) = ((0..=m).collect(), (0..=m).collect());
        let scalars = Elements {
            cols: &cols,
            rows: &rows,
        };
        let (mut pattern, mut passes) = (None, 0);
        jac(&dense, &scalars, &mut pattern, &mut passes);
        assert_eq!(
            passes,
            GROUPS + 4 * GROUPS + m,
            "a round, one with four times the groups, then one pass per column"
        );
    }

    /// A row that reads every column (a residual on a sum) is left out of the colouring and
    /// taken by one reverse pass: four colours for the rest, not one per column; the values
    /// are the columns' to the bit, at the first step and the next.
    #[test]
    fn a_dense_row_is_taken_by_a_reverse_pass() {
        let n = 2000;
        let f = band(n, None);
        let g = |v: &[f64]| {
            let mut out = f(v);
            out[0] += v
                .iter()
                .enumerate()
                .map(|(j, x)| (1.0 + j as f64) * x)
                .sum::<f64>();
            out
        };
        let (cols, rows): (Vec<usize>, Vec<usize>) = ((0..=n + 1).collect(), (0..=n).collect());
        let scalars = Elements {
            cols: &cols,
            rows: &rows,
        };
        let mut pattern = None;
        for step in 0..2 {
            let mut passes = 0;
            let a = jac(&g, &scalars, &mut pattern, &mut passes);
            let p = pattern.as_ref().unwrap();
            assert_eq!((p.colours(), &p.dense[..]), (4, &[0][..]), "step {step}");
            if step == 1 {
                assert_eq!(passes, 4 + 1 + 2, "colours, the dense row, the check");
            }
            for j in [0, 1, 2, 999, n - 1, n] {
                let e: Vec<f64> = (0..=n).map(|k| (k == j) as u8 as f64).collect();
                assert_eq!(a.mul(&e), g(&e), "step {step}, column {j}");
            }
        }
    }

    /// An element's scalars share their pattern: a coupling that is exactly zero where the
    /// pattern is found (a spring along an axis) is in it, and no pass is taken again when it
    /// is not zero.
    #[test]
    fn the_pattern_covers_whole_elements() {
        let s = std::cell::Cell::new(0.0);
        // Two 3-scalar input elements, one output element: out = (I + s 1) x[0..3].
        let f = |v: &[f64]| -> Vec<f64> {
            let sum: f64 = v[..3].iter().sum();
            (0..3).map(|i| v[i] + s.get() * sum).collect()
        };
        let elements = Elements {
            cols: &[0, 3, 6],
            rows: &[0, 3],
        };
        let (mut pattern, mut passes) = (None, 0);
        jac(&f, &elements, &mut pattern, &mut passes);
        assert_eq!(passes, 6);
        assert_eq!(pattern.as_ref().unwrap().colours(), 3);
        s.set(0.5);
        passes = 0;
        let a = jac(&f, &elements, &mut pattern, &mut passes);
        assert_eq!(passes, 5, "three colours and the check, no pass per column");
        for j in 0..6 {
            let e: Vec<f64> = (0..6).map(|k| (k == j) as u8 as f64).collect();
            assert_eq!(a.mul(&e), f(&e), "column {j}");
        }
    }
    /// A Jacobian of other sizes than the pattern's (residuals that change in number) is
    /// taken column by column, and its pattern replaces the old one.
    #[test]
    fn other_sizes_drop_the_pattern() {
        let mut pattern = None;
        for n in [4usize, 6, 3] {
            let f = band(n, None);
            let (cols, rows): (Vec<usize>, Vec<usize>) = ((0..=n + 1).collect(), (0..=n).collect());
            let elements = Elements {
                cols: &cols,
                rows: &rows,
            };
            let mut passes = 0;
            let a = jac(&f, &elements, &mut pattern, &mut passes);
            assert_eq!(passes, n + 1, "n = {n}");
            let ones = vec![1.0; n + 1];
            assert_eq!(a.mul(&ones), f(&ones), "n = {n}");
        }
    }
}

//! The cloth topology of `docs/scenes.md`, in the order of
//! `bench/peers/warp_cloth_scene.py` (particles, springs, bending elements, inverse masses).

use std::collections::HashMap;

use adflex_runtime::{Real, Vec3};

/// Particles, springs and bending elements of an `n x n` cloth.
pub struct ClothTopo<R: Real> {
    /// Particles per side.
    pub n: usize,
    /// Initial positions `(i h, 0.03, j h)`.
    pub x0: Vec<Vec3<R>>,
    /// Spring index pairs.
    pub springs: Vec<[u32; 2]>,
    /// Spring rest lengths (initial distances, computed in f32 like the peers).
    pub rest: Vec<R>,
    /// Bending elements `(o1, o2, e0, e1)`.
    pub bends: Vec<[u32; 4]>,
    /// Inverse masses (100, and 0 at the two pinned corners).
    pub inv_mass: Vec<R>,
}

/// Builds the `n x n` cloth.
pub fn cloth<R: Real>(n: usize) -> ClothTopo<R> {
    let h = 1.0f32 / (n - 1) as f32;
    let p32: Vec<[f32; 3]> = (0..n)
        .flat_map(|i| (0..n).map(move |j| [i as f32 * h, 0.03, j as f32 * h]))
        .collect();
    let pid = |i: usize, j: usize| (i * n + j) as u32;
    let mut springs = Vec::new();
    for i in 0..n {
        for j in 0..n {
            if i + 1 < n {
                springs.push([pid(i, j), pid(i + 1, j)]);
            }
            if j + 1 < n {
                springs.push([pid(i, j), pid(i, j + 1)]);
            }
            if i + 1 < n && j + 1 < n {
                springs.push([pid(i, j), pid(i + 1, j + 1)]);
                springs.push([pid(i + 1, j), pid(i, j + 1)]);
            }
        }
    }
    // numpy: norm of the f32 difference, computed in f32 (accumulated in f32, sqrt in f32)
    let rest: Vec<R> = springs
        .iter()
        .map(|&[a, b]| {
            let (p, q) = (p32[a as usize], p32[b as usize]);
            let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
            R::lit((d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() as f64)
        })
        .collect();
    let mut tris = Vec::new();
    for i in 0..n - 1 {
        for j in 0..n - 1 {
            let (a, b, c, d) = (pid(i, j), pid(i + 1, j), pid(i + 1, j + 1), pid(i, j + 1));
            tris.push([a, b, c]);
            tris.push([a, c, d]);
        }
    }
    let mut order: Vec<(u32, u32)> = Vec::new();
    let mut edges: HashMap<(u32, u32), Vec<[u32; 3]>> = HashMap::new();
    for t in &tris {
        for e in 0..3 {
            let (u, w, o) = (t[e], t[(e + 1) % 3], t[(e + 2) % 3]);
            let key = (u.min(w), u.max(w));
            let list = edges.entry(key).or_default();
            if list.is_empty() {
                order.push(key);
            }
            list.push([o, u, w]);
        }
    }
    let bends = order
        .iter()
        .filter_map(|k| {
            let l = &edges[k];
            (l.len() == 2).then(|| [l[0][0], l[1][0], l[0][1], l[0][2]])
        })
        .collect();
    let mut inv_mass = vec![R::lit(100.0); n * n];
    inv_mass[pid(0, 0) as usize] = R::lit(0.0);
    inv_mass[pid(n - 1, 0) as usize] = R::lit(0.0);
    ClothTopo {
        n,
        x0: p32
            .iter()
            .map(|p| {
                Vec3::new(
                    R::lit(p[0] as f64),
                    R::lit(p[1] as f64),
                    R::lit(p[2] as f64),
                )
            })
            .collect(),
        springs,
        rest,
        bends,
        inv_mass,
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn counts_match_warp() {
        // from peers-results.jsonl: N=32: 3906 springs, 2821 bends; N=64: 16002, 11781
        let t = super::cloth::<f32>(32);
        assert_eq!((t.springs.len(), t.bends.len()), (3906, 2821));
        let t = super::cloth::<f32>(64);
        assert_eq!((t.springs.len(), t.bends.len()), (16002, 11781));
        // the first bending elements and springs of the python builder
        assert_eq!(
            &t.bends[..3],
            &[[0, 129, 64, 65], [64, 1, 65, 0], [0, 66, 65, 1]]
        );
        assert_eq!(&t.springs[..3], &[[0, 64], [0, 1], [0, 65]]);
        assert_eq!(t.rest[2], f32::from_bits(0x3cb7e486)); // 0x1.6fc90cp-6 from numpy
    }
}

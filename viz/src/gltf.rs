//! A rollout as one binary glTF 2.0 file (`.glb`), animated, for Blender (File > Import > glTF
//! 2.0), any web viewer (three.js, Babylon.js, `<model-viewer>`) and game engines.
//!
//! What the file holds (one scene, one animation named `rollout`):
//! - node `particles`: one mesh over the particle positions of the first state, with the model's
//!   faces (triangles and tetrahedron boundaries) as a triangle primitive, its springs and
//!   distance constraints as a line primitive, or the bare points as a point primitive; every
//!   later state is a **morph target** (its displacement from the first), and the animation
//!   steps the target weights so that state `k` shows at time `k / fps` s (linear in between);
//! - node `body_<i>` per rigid body, its translation and rotation animated, with a child mesh
//!   of its contact points and the edges between them (in body frame, as in [`crate::export`]).
//!
//! Files are checked with the Khronos glTF validator in the tests. A glTF file holds finite
//! numbers only: a non-finite position is an [`Error::Invalid`] naming the state and particle.
//! Size: about `12 n (T + 1) + 4 T^2` bytes for `n` particles and `T + 1` states (the morph
//! targets and their weights), so for long rollouts pass every few states.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_kernels::scenes::cloth;
//! use adflex_runtime::Tape;
//! let scene = cloth::build::<f64>(4);
//! let mut states = vec![scene.initial.clone()];
//! for _ in 0..10 {
//!     let s = SemiImplicitEuler
//!         .step(&scene.model, &mut Tape::new(), states.last().unwrap(), None, 1e-2)
//!         .unwrap();
//!     states.push(s);
//! }
//! let path = std::env::temp_dir().join(format!("adflex-viz-doc-{}.glb", std::process::id()));
//! adflex_viz::gltf::write_glb(&path, &scene.model, &states, 30.0).unwrap();
//! assert_eq!(&std::fs::read(&path).unwrap()[..4], b"glTF");
//! # std::fs::remove_file(&path).ok();
//! ```

use std::path::Path;

use adflex_kernels::model::{Model, State};
use adflex_runtime::{Real, Vec3};
use serde_json::{json, Value};

use crate::scene::Frame;
use crate::{Error, Result};

const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;
const POINTS: u32 = 0;
const LINES: u32 = 1;
const TRIANGLES: u32 = 4;

/// The binary chunk and the JSON arrays that describe it.
#[derive(Default)]
struct Builder {
    bin: Vec<u8>,
    views: Vec<Value>,
    accessors: Vec<Value>,
}

impl Builder {
    /// Appends `bytes` as a buffer view (for `target`, if any); returns its index.
    fn view(&mut self, bytes: &[u8], target: Option<u32>) -> usize {
        let offset = self.bin.len();
        self.bin.extend_from_slice(bytes);
        self.bin.resize(self.bin.len().next_multiple_of(4), 0);
        let mut v = json!({ "buffer": 0, "byteOffset": offset, "byteLength": bytes.len() });
        if let Some(t) = target {
            v["target"] = json!(t);
        }
        self.views.push(v);
        self.views.len() - 1
    }

    /// `VEC3` float accessor with its min and max (which glTF requires for positions).
    fn vec3(&mut self, pts: &[[f32; 3]], target: Option<u32>) -> usize {
        let bytes: Vec<u8> = pts.iter().flatten().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&bytes, target);
        let (mut lo, mut hi) = ([f32::MAX; 3], [f32::MIN; 3]);
        for p in pts {
            for c in 0..3 {
                lo[c] = lo[c].min(p[c]);
                hi[c] = hi[c].max(p[c]);
            }
        }
        self.accessor(json!({
            "bufferView": view, "componentType": FLOAT, "count": pts.len(), "type": "VEC3",
            "min": lo, "max": hi,
        }))
    }

    /// Float accessor of `kind` (`SCALAR`, `VEC3`, `VEC4`, `width` floats per element),
    /// animation data (no buffer target); `with_bounds` adds min and max (animation inputs).
    fn floats(&mut self, data: &[f32], kind: &str, width: usize, with_bounds: bool) -> usize {
        let bytes: Vec<u8> = data.iter().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&bytes, None);
        let mut a = json!({
            "bufferView": view, "componentType": FLOAT, "count": data.len() / width, "type": kind,
        });
        if with_bounds {
            let lo = data.iter().copied().fold(f32::MAX, f32::min);
            let hi = data.iter().copied().fold(f32::MIN, f32::max);
            a["min"] = json!([lo]);
            a["max"] = json!([hi]);
        }
        self.accessor(a)
    }

    /// Index accessor (`u32`).
    fn indices(&mut self, idx: &[u32]) -> usize {
        let bytes: Vec<u8> = idx.iter().flat_map(|c| c.to_le_bytes()).collect();
        let view = self.view(&bytes, Some(ELEMENT_ARRAY_BUFFER));
        self.accessor(json!({
            "bufferView": view, "componentType": UNSIGNED_INT, "count": idx.len(), "type": "SCALAR",
        }))
    }

    fn accessor(&mut self, a: Value) -> usize {
        self.accessors.push(a);
        self.accessors.len() - 1
    }
}

/// The positions as `f32`, or an error naming the first non-finite one.
fn finite(pts: &[Vec3<f64>], what: &dyn Fn(usize) -> String) -> Result<Vec<[f32; 3]>> {
    pts.iter()
        .enumerate()
        .map(|(i, p)| {
            let q = [p.x as f32, p.y as f32, p.z as f32];
            if q.iter().all(|c| c.is_finite()) {
                Ok(q)
            } else {
                Err(Error::Invalid(format!(
                    "{} is not finite ({p:?}): glTF holds finite numbers only",
                    what(i)
                )))
            }
        })
        .collect()
}

/// Writes `states` as an animated binary glTF 2.0 file (see the [module docs](self)): state
/// `k` at time `k / fps` s.
///
/// Errors: [`Error::Empty`] for no states, [`Error::Invalid`] for a bad `fps`, a state that
/// does not fit the model or a non-finite position, [`Error::Io`] naming `path`.
pub fn write_glb<R: Real>(
    path: impl AsRef<Path>,
    model: &Model<R>,
    states: &[State<R>],
    fps: f64,
) -> Result<()> {
    let path = path.as_ref();
    let (topo, frames) = crate::export::rollout(path, model, states, fps)?;
    if topo.particles == 0 && topo.body_points.is_empty() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            what: "the model has no particles and no rigid bodies",
        });
    }
    let n = topo.particles;
    let mut b = Builder::default();
    let (mut nodes, mut meshes, mut roots) = (Vec::new(), Vec::new(), Vec::new());
    let (mut channels, mut samplers) = (Vec::new(), Vec::new());
    let times: Vec<f32> = (0..frames.len()).map(|k| (k as f64 / fps) as f32).collect();
    let animated = frames.len() > 1;
    let time = animated.then(|| b.floats(&times, "SCALAR", 1, true));

    if n > 0 {
        let at = |k: usize| move |i: usize| format!("particle {i} of state {k}");
        let base = finite(&frames[0].x[..n], &at(0))?;
        let position = b.vec3(&base, Some(ARRAY_BUFFER));
        let mut targets = Vec::new();
        for (k, f) in frames.iter().enumerate().skip(1) {
            let x = finite(&f.x[..n], &at(k))?;
            let d: Vec<[f32; 3]> = x
                .iter()
                .zip(&base)
                .map(|(p, q)| [p[0] - q[0], p[1] - q[1], p[2] - q[2]])
                .collect();
            targets.push(json!({ "POSITION": b.vec3(&d, Some(ARRAY_BUFFER)) }));
        }
        let mut primitive = |mode: u32, idx: Option<Vec<u32>>| {
            let mut p = json!({ "attributes": { "POSITION": position }, "mode": mode });
            if let Some(idx) = idx {
                p["indices"] = json!(b.indices(&idx));
            }
            if !targets.is_empty() {
                p["targets"] = json!(targets);
            }
            p
        };
        let mut prims = Vec::new();
        if !topo.faces.is_empty() {
            prims.push(primitive(TRIANGLES, Some(topo.faces.concat())));
        }
        if !topo.edges.is_empty() {
            prims.push(primitive(LINES, Some(topo.edges.concat())));
        }
        if prims.is_empty() {
            prims.push(primitive(POINTS, None));
        }
        let mut mesh = json!({ "name": "particles", "primitives": prims });
        if animated {
            let t = frames.len() - 1;
            mesh["weights"] = json!(vec![0.0; t]);
            // At state k, target k - 1 has weight 1 and the others 0.
            let mut w = vec![0f32; frames.len() * t];
            for k in 1..frames.len() {
                w[k * t + (k - 1)] = 1.0;
            }
            let output = b.floats(&w, "SCALAR", 1, false);
            samplers.push(json!({ "input": time, "output": output, "interpolation": "LINEAR" }));
            channels.push(json!({
                "sampler": samplers.len() - 1,
                "target": { "node": nodes.len(), "path": "weights" },
            }));
        }
        meshes.push(mesh);
        roots.push(nodes.len());
        nodes.push(json!({ "name": "particles", "mesh": meshes.len() - 1 }));
    }

    for (bi, pts) in topo.body_points.iter().enumerate() {
        let pose = |f: &Frame| {
            f.bodies
                .get(bi)
                .copied()
                .unwrap_or((Vec3::zeros(), [1.0, 0.0, 0.0, 0.0]))
        };
        let body = nodes.len();
        roots.push(body);
        let (c0, q0) = pose(&frames[0]);
        let what = |k: usize| move |_: usize| format!("the centre of body {bi} in state {k}");
        let mut node = json!({
            "name": format!("body_{bi}"),
            "translation": finite(&[c0], &what(0))?[0],
            "rotation": [q0[1] as f32, q0[2] as f32, q0[3] as f32, q0[0] as f32],
        });
        if !pts.is_empty() {
            let local = finite(pts, &|i| format!("contact point {i} of body {bi}"))?;
            let position = b.vec3(&local, Some(ARRAY_BUFFER));
            let mut prims = vec![json!({ "attributes": { "POSITION": position }, "mode": POINTS })];
            let edges = topo.body_edges_of(bi);
            if !edges.is_empty() {
                let idx = b.indices(&edges.concat());
                prims.push(json!({
                    "attributes": { "POSITION": position }, "indices": idx, "mode": LINES,
                }));
            }
            meshes.push(json!({ "name": format!("body_{bi}_points"), "primitives": prims }));
            node["children"] = json!([nodes.len() + 1]);
        }
        if animated {
            let mut tr = Vec::with_capacity(3 * frames.len());
            let mut rot = Vec::with_capacity(4 * frames.len());
            for (k, f) in frames.iter().enumerate() {
                let (c, q) = pose(f);
                tr.extend(finite(&[c], &what(k))?[0]);
                rot.extend([q[1], q[2], q[3], q[0]].map(|c| c as f32));
            }
            for (data, kind, width, target) in
                [(tr, "VEC3", 3, "translation"), (rot, "VEC4", 4, "rotation")]
            {
                let output = b.floats(&data, kind, width, false);
                samplers
                    .push(json!({ "input": time, "output": output, "interpolation": "LINEAR" }));
                channels.push(json!({
                    "sampler": samplers.len() - 1,
                    "target": { "node": body, "path": target },
                }));
            }
        }
        nodes.push(node);
        if !pts.is_empty() {
            nodes.push(json!({ "name": format!("body_{bi}_points"), "mesh": meshes.len() - 1 }));
        }
    }

    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "adflex-viz" },
        "scene": 0,
        "scenes": [{ "name": "rollout", "nodes": roots }],
        "nodes": nodes,
    });
    // glTF wants no empty arrays and no empty buffer (bodies without points, one state).
    if !b.bin.is_empty() {
        doc["buffers"] = json!([{ "byteLength": b.bin.len() }]);
        doc["bufferViews"] = json!(b.views);
        doc["accessors"] = json!(b.accessors);
    }
    if !meshes.is_empty() {
        doc["meshes"] = json!(meshes);
    }
    if !channels.is_empty() {
        doc["animations"] =
            json!([{ "name": "rollout", "channels": channels, "samplers": samplers }]);
    }
    write_container(path, &doc, &b.bin)
}

/// The GLB container: header, JSON chunk (padded with spaces), binary chunk (with zeros).
fn write_container(path: &Path, doc: &Value, bin: &[u8]) -> Result<()> {
    let mut json = serde_json::to_vec(doc).expect("a JSON value serializes");
    json.resize(json.len().next_multiple_of(4), b' ');
    // The binary chunk only if there is data.
    let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
    let too_big = |_| Error::Invalid(format!("{} would exceed 4 GiB", path.display()));
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(b"glTF");
    out.extend_from_slice(&2u32.to_le_bytes());
    out.extend_from_slice(&u32::try_from(total).map_err(too_big)?.to_le_bytes());
    out.extend_from_slice(&(json.len() as u32).to_le_bytes());
    out.extend_from_slice(b"JSON");
    out.extend_from_slice(&json);
    if !bin.is_empty() {
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
    }
    std::fs::write(path, out).map_err(|e| Error::io(path, e))
}

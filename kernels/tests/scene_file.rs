//! Scene files: JSON and TOML scenes build the same models as the builder; malformed files give
//! errors that name the field and the line, and never panic.

use adflex_kernels::prelude::*;
use adflex_kernels::scene_file::SceneError;
use adflex_kernels::scenes::cloth;
use adflex_runtime::Tape;

const FULL_JSON: &str = r#"{
  "gravity": [0, -9.81, 0],
  "particle_radius": 0.02,
  "particles": [
    { "x": [0, 1, 0], "mass": 0 },
    { "x": [1, 1, 0], "v": [0, 0.5, 0], "mass": 0.1 },
    { "x": [0, 1, 1], "mass": 0.1 },
    { "x": [1, 1, 1], "mass": 0.1 },
    { "x": [0.5, 2, 0.5], "mass": 0.1 }
  ],
  "springs": [
    { "i": 0, "j": 1, "ke": 100, "kd": 0.1 },
    { "i": 1, "j": 3, "ke": 100, "rest": 0.9 }
  ],
  "triangles": [
    { "indices": [0, 1, 3], "mu": 50, "lambda": 20, "kd": 0.1 },
    { "indices": [0, 3, 2] }
  ],
  "bending": { "ke": 0.5, "rest": "initial" },
  "tets": [ { "indices": [0, 1, 2, 4], "young": 1000, "poisson": 0.3, "kd": 0.1 } ],
  "ground": { "ke": 2000, "leak": 0.01 },
  "drag": { "kd": 0.01, "wind": [1, 0, 0] },
  "particle_contact": { "ke": 500 },
  "shape_contact": { "mu": 0.3 },
  "shapes": [
    { "kind": "sphere", "pos": [0, 0, 0], "radius": 0.5 },
    { "kind": "box", "pos": [3, 0, 0], "rot": [0, 0.383, 0, 0.924], "half_extents": [0.5, 0.2, 0.3] },
    { "kind": "capsule", "pos": [-3, 0, 0], "radius": 0.2, "half_length": 0.5 }
  ],
  "bodies": [
    { "x": [0, 3, 0], "w": [0, 1, 0], "mass": 2, "inertia": [0.1, 0.2, 0.3],
      "contact_points": [[0.1, -0.1, 0.1], [-0.1, -0.1, -0.1]] }
  ],
  "distance_constraints": [ { "i": 2, "j": 4, "compliance": 0.001 } ]
}"#;

#[test]
fn a_full_json_scene_builds_and_steps() {
    let b = ModelBuilder::<f64>::from_json_str(FULL_JSON).unwrap();
    let m = b.finalize();
    assert_eq!(m.particle_count, 5);
    assert_eq!(m.springs().unwrap().len(), 2);
    assert_eq!(m.springs().unwrap().rest.get(1), 0.9);
    assert_eq!(m.tri_fem().unwrap().len(), 1);
    assert_eq!(m.triangles.len(), 2);
    assert_eq!(m.bending().unwrap().len(), 1);
    assert_eq!(m.tets().unwrap().len(), 1);
    assert_eq!(m.shapes().unwrap().kind.to_vec(), vec![0, 1, 2]);
    assert_eq!(m.bodies.as_ref().unwrap().len(), 1);
    assert_eq!(m.distance_constraints.as_ref().unwrap().len(), 1);
    assert_eq!(m.ground().unwrap().leak, 0.01);
    assert_eq!(m.particle_inv_mass.get(0), 0.0);
    let mut tape = Tape::new();
    let s = SemiImplicitEuler
        .step(&m, &mut tape, &m.state(), None, 1e-3)
        .unwrap();
    assert!(s.x.to_vec().iter().all(|p| p.iter().all(|c| c.is_finite())));
    assert!(s.bodies.unwrap().x.get(0).y < 3.0);
}

#[test]
fn a_toml_cloth_grid_is_the_benchmark_cloth() {
    let toml = r#"
particle_radius = 0.01

[[cloth_grids]]
ni = 6
nj = 6
origin = [0.0, 0.03, 0.0]
spacing = 0.2
mass = 0.01
pinned = [[0, 0], [5, 0]]
spring_ke = 50.0
spring_kd = 0.1
bend_ke = 0.01

[ground]
damp_approach = true
"#;
    let m = ModelBuilder::<f32>::from_toml_str(toml).unwrap().finalize();
    let reference = cloth::build::<f32>(6);
    let r = &reference.model;
    assert_eq!(m.particle_x.to_vec(), r.particle_x.to_vec());
    assert_eq!(m.particle_inv_mass.to_vec(), r.particle_inv_mass.to_vec());
    let (s, rs) = (m.springs().unwrap(), r.springs().unwrap());
    assert_eq!(s.pairs.to_vec(), rs.pairs.to_vec());
    assert_eq!(s.rest.to_vec(), rs.rest.to_vec());
    assert_eq!(
        m.bending().unwrap().quads.to_vec(),
        r.bending().unwrap().quads.to_vec()
    );
    assert_eq!(m.ground(), r.ground());
}

fn json_err(src: &str) -> SceneError {
    match ModelBuilder::<f32>::from_json_str(src) {
        Ok(_) => panic!("accepted a malformed file:\n{src}"),
        Err(e) => e,
    }
}

fn toml_err(src: &str) -> SceneError {
    match ModelBuilder::<f32>::from_toml_str(src) {
        Ok(_) => panic!("accepted a malformed file:\n{src}"),
        Err(e) => e,
    }
}

#[track_caller]
fn expect(e: &SceneError, field: &str, line: usize, says: &str) {
    assert_eq!(e.field.as_deref(), Some(field), "{e}");
    assert_eq!(e.line, Some(line), "{e}");
    assert!(e.message.contains(says), "`{says}` not in: {e}");
    let shown = e.to_string();
    assert!(
        shown.contains(&format!("line {line}")) && shown.contains(field),
        "{shown}"
    );
}

#[test]
fn malformed_json_names_the_field_and_line() {
    let e = json_err("{\n  \"particles\": [\n    { \"x\": [0, 1, 0], \"mass\": 1 },\n    { \"x\": [0, 1, 0], \"mass\": \"heavy\" }\n  ]\n}");
    expect(&e, "particles[1].mass", 4, "invalid type");
    let e = json_err("{\n  \"particles\": [\n    { \"x\": [0, 1, 0] }\n  ]\n}");
    expect(&e, "particles[0]", 3, "missing field `mass`");
    let e = json_err("{\n  \"particles\": [ { \"x\": [0, 1, 0], \"mass\": 1 } ],\n  \"springs\": [ { \"i\": 0, \"j\": 0, \"stiffness\": 3 } ]\n}");
    expect(&e, "springs[0].stiffness", 3, "unknown field `stiffness`");
    let e = json_err("{\n  \"particles\": [ { \"x\": [0, 1], \"mass\": 1 } ]\n}");
    expect(&e, "particles[0].x", 2, "invalid length");
    let e = json_err("{\n  \"particles\": [ { \"x\": [0, 1, 0], \"mass\": 1 }, { \"x\": [1, 1, 0], \"mass\": 1 } ],\n  \"springs\": [\n    { \"i\": 0, \"j\": 7, \"ke\": 3 }\n  ]\n}");
    expect(
        &e,
        "springs[0]",
        4,
        "particle index 7 out of range (2 particles)",
    );
    let e = json_err("{\n  \"particles\": [ { \"x\": [0, 1, 0], \"mass\": -1 } ]\n}");
    expect(&e, "particles[0].mass", 2, ">= 0");
    let e = json_err("{\n  \"shapes\": [\n    { \"kind\": \"cone\", \"pos\": [0, 0, 0] }\n  ]\n}");
    expect(&e, "shapes[0].kind", 3, "unknown variant `cone`");
    let e =
        json_err("{\n  \"shapes\": [\n    { \"kind\": \"sphere\", \"pos\": [0, 0, 0] }\n  ]\n}");
    expect(&e, "shapes[0]", 3, "missing field `radius`");
    let e = json_err("{\n \"particles\": [\n  {\"x\": [0,0,0], \"mass\": 1}, {\"x\": [1,0,0], \"mass\": 1},\n  {\"x\": [2,0,0], \"mass\": 1}, {\"x\": [3,0,0], \"mass\": 1}],\n \"tets\": [\n  {\"indices\": [0, 1, 2, 3], \"mu\": 1, \"lambda\": 1}\n ]\n}");
    expect(&e, "tets[0]", 6, "degenerate");
    // A syntax error: line and column, no field needed.
    let e = json_err("{\n  \"gravity\": [0, -9.8, 0]\n  \"particles\": []\n}");
    assert_eq!(e.line, Some(3), "{e}");
    assert!(e.message.contains("expected"), "{e}");
}

#[test]
fn malformed_toml_names_the_field_and_line() {
    let e = toml_err("[[particles]]\nx = [0, 1, 0]\nmass = 1\n\n[[particles]]\nx = [0, 1, 0]\nmass = \"heavy\"\n");
    expect(&e, "particles[1].mass", 7, "invalid type");
    let e =
        toml_err("[[particles]]\nx = [0, 1, 0]\nmass = 1\n\n[[springs]]\ni = 0\nj = 3\nke = 1.0\n");
    expect(&e, "springs[0]", 5, "particle index 3 out of range");
    let e = toml_err("[ground]\nke = 1000.0\nmu = nan\n");
    expect(&e, "ground.mu", 3, ">= 0");
    let e = toml_err("[drag]\nkd = 0.1\nwindy = [1.0, 0.0, 0.0]\n");
    expect(&e, "drag.windy", 3, "unknown field `windy`");
    let e = toml_err("[[cloth_grids]]\nni = 4\nnj = 1\norigin = [0.0, 0.0, 0.0]\nspacing = 0.1\nmass = 1.0\nspring_ke = 1.0\n");
    expect(&e, "cloth_grids[0].ni", 2, "at least 2 per side");
    let e = toml_err("gravity = [0.0, -9.8, 0.0\n");
    assert_eq!(e.line, Some(1), "{e}");
}

#[test]
fn no_input_makes_the_reader_panic() {
    // Every prefix of a valid file and a sweep of single-byte corruptions: errors, not panics.
    let bytes = FULL_JSON.as_bytes();
    for end in 0..bytes.len() {
        if let Ok(s) = std::str::from_utf8(&bytes[..end]) {
            let _ = ModelBuilder::<f32>::from_json_str(s);
        }
    }
    for k in (0..bytes.len()).step_by(3) {
        for c in [b'0', b'-', b'"', b'[', b'}', b'9', b'e'] {
            let mut m = bytes.to_vec();
            m[k] = c;
            if let Ok(s) = std::str::from_utf8(&m) {
                if let Err(e) = ModelBuilder::<f32>::from_json_str(s) {
                    assert!(!e.message.is_empty());
                }
            }
        }
    }
    let toml = "[[particles]]\nx = [0.0, 1.0, 0.0]\nmass = 1.0\n[[springs]]\ni = 0\nj = 0\nke = 1.0\n[ground]\nke = 5.0\n";
    for end in 0..toml.len() {
        let _ = ModelBuilder::<f32>::from_toml_str(&toml[..end]);
    }
}

/// Runs `f` and asserts it took less than `limit` seconds (generous: debug-ish test profile,
/// shared machine; the quadratic reader took 40 s on 40 KB).
#[track_caller]
fn quick<T>(limit: f64, what: &str, f: impl FnOnce() -> T) -> T {
    let t = std::time::Instant::now();
    let r = f();
    let s = t.elapsed().as_secs_f64();
    assert!(s < limit, "{what} took {s:.2} s (limit {limit} s)");
    r
}

#[test]
fn deeply_nested_input_is_an_error_at_once() {
    for n in [40_000, 80_000, 1_000_000] {
        let brackets = "[".repeat(n);
        let e = quick(1.0, "json [", || json_err(&brackets));
        assert_eq!(e.line, Some(1), "{e}");
        assert!(!e.message.is_empty());
        let e = quick(1.0, "json particles [", || {
            json_err(&format!("{{\"particles\": {brackets}"))
        });
        assert!(e.field.is_some() && !e.message.is_empty(), "{e}");
        let e = quick(1.0, "json {", || {
            json_err(&"{\"particles\": [".repeat(n / 15))
        });
        assert!(!e.message.is_empty(), "{e}");
        let e = quick(1.0, "toml", || toml_err(&format!("gravity = {brackets}")));
        assert_eq!(e.line, Some(1), "{e}");
        assert!(
            e.message.contains("recursion") || e.message.contains("nested"),
            "{e}"
        );
        let e = quick(1.0, "toml inline tables", || {
            toml_err(&format!("gravity = {}", "{ a = ".repeat(n / 6)))
        });
        assert!(!e.message.is_empty(), "{e}");
    }
}

#[test]
fn nesting_beyond_the_parser_limit_says_so() {
    // serde_json's own limit, reached through a value the schema reads as any type: an
    // unknown field is refused before its value is read, so the limit is only reachable in
    // TOML, whose parser builds the whole document first.
    let e = toml_err(&format!(
        "[ground]\nke = {}1{}\n",
        "[".repeat(200),
        "]".repeat(200)
    ));
    assert_eq!(e.line, Some(2), "{e}");
    assert!(e.message.contains("too deep"), "{e}");
}

/// A valid scene of `n` particles in a chain of springs, as JSON, with particle `bad` given a
/// negative mass (or none if `bad >= n`).
fn chain_json(n: usize, bad: usize) -> String {
    let mut s = String::from("{\n\"particles\": [\n");
    for k in 0..n {
        let mass = if k == bad { -1.0 } else { 0.1 };
        s += &format!(
            "  {{ \"x\": [{}, 1.0, 0.0], \"v\": [0, 0, 0], \"mass\": {mass} }}{}\n",
            k as f64 * 0.01,
            if k + 1 < n { "," } else { "" }
        );
    }
    s += "],\n\"springs\": [\n";
    for k in 0..n - 1 {
        s += &format!(
            "  {{ \"i\": {k}, \"j\": {}, \"ke\": 100, \"kd\": 0.1 }}{}\n",
            k + 1,
            if k + 2 < n { "," } else { "" }
        );
    }
    s + "]\n}\n"
}

#[test]
fn a_large_scene_reads_in_linear_time_and_errors_name_the_line() {
    // ~5 MB; the bound is generous (the reader is within 3x of serde_json alone, see the
    // `scene-file` bench).
    let n = 50_000;
    let ok = chain_json(n, n);
    let b = quick(5.0, "5 MB scene", || {
        ModelBuilder::<f64>::from_json_str(&ok).unwrap()
    });
    assert_eq!(b.particle_count(), n);
    // An error near the end: the semantic check finds its line by one scan.
    let bad = chain_json(n, n - 3);
    let e = quick(5.0, "5 MB scene with an error", || json_err(&bad));
    expect(&e, &format!("particles[{}].mass", n - 3), n - 3 + 3, ">= 0");
}

#[test]
fn scene_file_defaults_are_the_components_defaults() {
    use adflex_kernels::contact::particle::ParticleContact;
    use adflex_kernels::prelude::*;
    let json = r#"{
        "particles": [ { "x": [0, 1, 0], "mass": 1 }, { "x": [1, 1, 0], "mass": 1 } ],
        "ground": {}, "particle_contact": {}
    }"#;
    let m = ModelBuilder::<f64>::from_json_str(json).unwrap().finalize();
    assert_eq!(m.ground().unwrap(), Ground::default());
    assert_eq!(m.particle_contact().unwrap(), ParticleContact::default());
    // Every component a user configures has a documented Default.
    let cloth = adflex_kernels::scenes::cloth::ClothGrid::<f32>::default();
    assert_eq!((cloth.ni, cloth.nj), (16, 16));
    assert_eq!(Drag::<f64>::default().wind, adflex_runtime::Vec3::zeros());
}

#[test]
fn the_ground_reads_damp_approach_and_defaults_to_the_builders() {
    let read = |ground: &str| {
        let json = format!(
            r#"{{ "particles": [ {{ "x": [0, 1, 0], "mass": 1 }} ], "ground": {ground} }}"#
        );
        adflex_kernels::ModelBuilder::<f64>::from_json_str(&json)
            .unwrap()
            .finalize()
            .ground()
            .unwrap()
    };
    assert!(!read("{}").damp_approach);
    assert_eq!(read("{}"), adflex_kernels::prelude::Ground::default());
    assert!(read(r#"{ "damp_approach": true }"#).damp_approach);
}

/// A rotated cloth grid reads from a file as the builder makes it, and a rotation that is not
/// a unit quaternion is an error naming the field.
#[test]
fn a_rotated_cloth_grid_reads_as_built() {
    use adflex_kernels::prelude::ClothGrid;
    use adflex_runtime::{Quat, Vec3};
    let h = 0.5f64.sqrt();
    let src = format!(
        r#"{{ "cloth_grids": [ {{ "ni": 3, "nj": 4, "origin": [0, 1, 0], "spacing": 0.1,
              "mass": 0.01, "spring_ke": 50, "rotation": [{h}, 0, 0, {h}] }} ] }}"#
    );
    let from_file = ModelBuilder::<f64>::from_json_str(&src).unwrap().finalize();
    let mut b = ModelBuilder::<f64>::new();
    b.add_cloth_grid(&ClothGrid {
        ni: 3,
        nj: 4,
        origin: Vec3::new(0.0, 1.0, 0.0),
        spacing: 0.1,
        mass: 0.01,
        pinned: vec![],
        spring_kd: 0.0,
        bend: None,
        rotation: Quat::new(h, h, 0.0, 0.0),
        ..ClothGrid::benchmark(3)
    });
    let built = b.finalize();
    assert_eq!(from_file.particle_x.to_vec(), built.particle_x.to_vec());
    // Particle (0, 3) hangs 0.3 m below the origin.
    assert!((built.particle_x.get(3) - Vec3::new(0.0, 0.7, 0.0)).norm() < 1e-12);
    let bad = src.replace(&format!("[{h}, 0, 0, {h}]"), "[1, 0, 0, 1]");
    let err = ModelBuilder::<f64>::from_json_str(&bad)
        .unwrap_err()
        .to_string();
    assert!(err.contains("rotation"), "{err}");
}

/// The defaults the scene-file schema documents (in parentheses in `crate::scene_file`'s
/// docs) are the builder's: the ground's and the contacts' scalars, read from the docs' text.
#[test]
fn the_documented_scene_defaults_are_the_builders() {
    use adflex_kernels::prelude::{Ground, ParticleContact};
    let src = include_str!("../src/scene_file/mod.rs");
    // `name (value)` pairs of the documented section starting with `//! - {section}`.
    let documented = |section: &str| -> Vec<(String, String)> {
        let start = src
            .find(&format!("//! - {section}"))
            .unwrap_or_else(|| panic!("no docs for {section}"));
        let text: String = src[start..]
            .lines()
            .take_while(|l| l.starts_with("//!"))
            .enumerate()
            .take_while(|(k, l)| *k == 0 || !l.starts_with("//! - "))
            .map(|(_, l)| l.trim_start_matches("//!"))
            .collect();
        let mut out = Vec::new();
        let mut rest = text.as_str();
        while let Some(open) = rest.find(" (") {
            let name = rest[..open]
                .rsplit([' ', ',', '{', '`'])
                .next()
                .unwrap()
                .to_string();
            let close = rest[open..].find(')').unwrap() + open;
            out.push((name, rest[open + 2..close].to_string()));
            rest = &rest[close..];
        }
        out
    };
    let g = Ground::<f64>::default();
    let ground = documented("`ground`");
    let value = |pairs: &[(String, String)], name: &str| {
        pairs
            .iter()
            .find(|(n, _)| n == name)
            .unwrap_or_else(|| panic!("{name} not documented: {pairs:?}"))
            .1
            .clone()
    };
    for (name, actual) in [
        ("offset", g.offset),
        ("ke", g.ke),
        ("kd", g.kd),
        ("mu", g.mu),
        ("leak", g.leak),
        ("damping_depth", g.damping_depth),
    ] {
        let doc: f64 = value(&ground, name).parse().unwrap();
        assert_eq!(doc, actual, "ground.{name}");
    }
    assert_eq!(value(&ground, "damp_approach"), g.damp_approach.to_string());
    assert_eq!(value(&ground, "normal"), "[0,1,0]");
    let c = ParticleContact::<f64>::default();
    let contact = documented("`particle_contact`");
    for (name, actual) in [
        ("ke", c.ke),
        ("kd", c.kd),
        ("damping_depth", c.damping_depth),
        ("mu", c.mu),
        ("leak", c.leak),
        ("margin", c.margin),
    ] {
        let doc: f64 = value(&contact, name).parse().unwrap();
        assert_eq!(doc, actual, "particle_contact.{name}");
    }
}

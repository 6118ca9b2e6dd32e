//! One validation for the builder and the scene reader: bad input (an index, a mass, a
//! coordinate that overflows the precision, a flat element) is an error naming the item, at
//! `try_finalize` for the builder and as a `SceneError` with field path and line for a file;
//! never a panic inside a builder method and never a NaN at the first step.

use adflex_kernels::prelude::*;
use adflex_kernels::scene_file::SceneError;
use adflex_kernels::{ModelError, Problem};
use adflex_runtime::{Real, Tape, Vec3};

fn v<R: Real>(x: f64, y: f64, z: f64) -> Vec3<R> {
    Vec3::new(R::lit(x), R::lit(y), R::lit(z))
}

#[track_caller]
fn builder_err<R: Real>(b: &ModelBuilder<R>) -> ModelError {
    match b.try_finalize() {
        Ok(_) => panic!("try_finalize accepted a bad scene"),
        Err(e) => e,
    }
}

/// The error has a problem of `item` (and `param`) whose message contains `says`.
#[track_caller]
fn has(e: &ModelError, item: &str, param: Option<&str>, says: &str) {
    assert!(
        e.problems
            .iter()
            .any(|p: &Problem| p.item == item && p.param == param && p.message.contains(says)),
        "no problem {item} {param:?} `{says}` in:\n{e}"
    );
    let shown = e.to_string();
    assert!(shown.contains(item) && shown.contains(says), "{shown}");
}

#[track_caller]
fn json_err<R: Real>(src: &str) -> SceneError {
    match ModelBuilder::<R>::from_json_str(src) {
        Ok(_) => panic!("accepted a bad file:\n{src}"),
        Err(e) => e,
    }
}

#[track_caller]
fn expect(e: &SceneError, field: &str, line: usize, says: &str) {
    assert_eq!(e.field.as_deref(), Some(field), "{e}");
    assert_eq!(e.line, Some(line), "{e}");
    assert!(e.message.contains(says), "`{says}` not in: {e}");
}

/// Two particles and whatever `rest` is, as a JSON file; particle 1 is on line 4.
fn two(p1: &str, rest: &str) -> String {
    format!("{{\n\"particles\": [\n  {{ \"x\": [0, 0, 0], \"mass\": 1 }},\n  {p1}\n]{rest}\n}}")
}

#[test]
fn a_tiny_mass_is_an_error_not_an_infinite_inverse_mass() {
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.0), 1e-320);
    has(
        &builder_err(&b),
        "particles[0]",
        Some("mass"),
        "inverse mass",
    );
    let e = json_err::<f64>(&two("{ \"x\": [1, 0, 0], \"mass\": 1e-320 }", ""));
    expect(&e, "particles[1].mass", 4, "inverse mass");
    // In f32 1e-39 kg has an infinite inverse, and 1e-50 kg rounds to 0 (it would pin).
    let e = json_err::<f32>(&two("{ \"x\": [1, 0, 0], \"mass\": 1e-39 }", ""));
    expect(&e, "particles[1].mass", 4, "f32");
    let e = json_err::<f32>(&two("{ \"x\": [1, 0, 0], \"mass\": 1e-50 }", ""));
    expect(&e, "particles[1].mass", 4, "rounds to 0");
}

#[test]
fn nan_and_negative_masses_are_errors_not_pinned_particles() {
    let mut b = ModelBuilder::<f32>::new();
    b.add_particle(v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.0), f32::NAN);
    b.add_particle(v(1.0, 0.0, 0.0), v(0.0, 0.0, 0.0), -1.0);
    let e = builder_err(&b);
    has(&e, "particles[0]", Some("mass"), ">= 0");
    has(&e, "particles[1]", Some("mass"), ">= 0");
    assert_eq!(e.problems.len(), 2, "{e}");
    let e = json_err::<f32>(&two("{ \"x\": [1, 0, 0], \"mass\": -1 }", ""));
    expect(&e, "particles[1].mass", 4, ">= 0");
    // TOML has NaN literals.
    let e = ModelBuilder::<f32>::from_toml_str("[[particles]]\nx = [0.0, 0.0, 0.0]\nmass = nan\n")
        .unwrap_err();
    expect(&e, "particles[0].mass", 3, ">= 0");
}

#[test]
fn huge_coordinates_overflow_rest_lengths_and_f32() {
    // 1e200 is finite in f64, but the spring's rest length (sqrt of a sum of squares) is not.
    let mut b = ModelBuilder::<f64>::new();
    let p = b.add_particle(v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.0), 1.0);
    let q = b.add_particle(v(1e200, 1e200, 0.0), v(0.0, 0.0, 0.0), 1.0);
    b.add_spring(p, q, 10.0, 0.0);
    has(&builder_err(&b), "springs[0]", None, "rest length");
    let e = json_err::<f64>(&two(
        "{ \"x\": [1e200, 1e200, 0], \"mass\": 1 }",
        ",\n\"springs\": [ { \"i\": 0, \"j\": 1, \"ke\": 10 } ]",
    ));
    expect(&e, "springs[0]", 6, "rest length");
    // 1e39 is not an f32.
    let mut b = ModelBuilder::<f32>::new();
    b.add_particle(v(1e39, 0.0, 0.0), v(0.0, 0.0, 0.0), 1.0);
    has(&builder_err(&b), "particles[0]", Some("x"), "finite in f32");
    let e = json_err::<f32>(&two("{ \"x\": [1e39, 0, 0], \"mass\": 1 }", ""));
    expect(&e, "particles[1].x", 4, "finite in f32");
    // The same file is fine in f64.
    ModelBuilder::<f64>::from_json_str(&two("{ \"x\": [1e39, 0, 0], \"mass\": 1 }", ""))
        .unwrap()
        .try_finalize()
        .unwrap();
}

const TET: &str = "{\n\"particles\": [\n  {\"x\": [0,0,0], \"mass\": 1}, {\"x\": [1,0,0], \"mass\": 1},\n  {\"x\": [0,1,0], \"mass\": 1}, {\"x\": [0.3,0.3,HEIGHT], \"mass\": 1}],\n\"tets\": [\n  {\"indices\": [0, 1, 2, 3], \"mu\": 1000, \"lambda\": 1000}\n]\n}";

#[test]
fn a_nearly_flat_tet_is_an_error_naming_it_and_its_vertices() {
    for h in [1e-9, 1e-30] {
        let mut b = ModelBuilder::<f64>::new();
        for p in [
            [0.0, 0.0, 0.0],
            [1.0, 0.0, 0.0],
            [0.0, 1.0, 0.0],
            [0.3, 0.3, h],
        ] {
            b.add_particle(v(p[0], p[1], p[2]), v(0.0, 0.0, 0.0), 1.0);
        }
        b.add_tet(0, 1, 2, 3, 1000.0, 1000.0, 0.0);
        let e = builder_err(&b);
        has(&e, "tets[0]", None, "nearly degenerate");
        has(&e, "tets[0]", None, "(0, 1, 2, 3)");
        let src = TET.replace("HEIGHT", &format!("{h:e}"));
        expect(&json_err::<f64>(&src), "tets[0]", 6, "nearly degenerate");
        expect(&json_err::<f32>(&src), "tets[0]", 6, "nearly degenerate");
    }
    // A well-shaped one is fine, and steps without NaN.
    let m = ModelBuilder::<f32>::from_json_str(&TET.replace("HEIGHT", "0.5"))
        .unwrap()
        .try_finalize()
        .unwrap();
    let s = SemiImplicitEuler
        .step(&m, &mut Tape::new(), &m.state(), None, 1e-3)
        .unwrap();
    assert!(s.x.to_vec().iter().all(|p| p.iter().all(|c| c.is_finite())));
}

#[test]
fn a_flat_triangle_is_an_error_not_a_panic() {
    let mut b = ModelBuilder::<f32>::new();
    for p in [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 1e-12, 0.0]] {
        b.add_particle(v(p[0], p[1], p[2]), v(0.0, 0.0, 0.0), 1.0);
    }
    b.add_triangle_fem(0, 1, 2, 10.0, 10.0, 0.0);
    has(&builder_err(&b), "triangle_fem[0]", None, "(0, 1, 2)");
}

#[test]
fn a_spring_on_one_particle_and_indices_out_of_range_are_errors() {
    let mut b = ModelBuilder::<f32>::new();
    b.add_particle(v(0.0, 0.0, 0.0), v(0.0, 0.0, 0.0), 1.0);
    b.add_particle(v(1.0, 0.0, 0.0), v(0.0, 0.0, 0.0), 1.0);
    b.add_spring(1, 1, 10.0, 0.0);
    b.add_spring(0, 5, 10.0, 0.0);
    b.add_tet(0, 1, 2, 3, 1.0, 1.0, 0.0);
    b.add_distance_constraint(0, 9, 0.0);
    b.add_body_contact_point(3, v(0.0, 0.0, 0.0));
    b.set_particle_inv_mass(7, 1.0);
    let e = builder_err(&b);
    has(
        &e,
        "springs[0]",
        Some("indices"),
        "particle 1 appears twice",
    );
    has(
        &e,
        "springs[1]",
        Some("indices"),
        "particle index 5 out of range (2 particles)",
    );
    has(&e, "tets[0]", Some("indices"), "out of range");
    has(
        &e,
        "distance_constraints[0]",
        Some("indices"),
        "out of range",
    );
    has(&e, "body_contact_points[0]", Some("body"), "out of range");
    has(&e, "particles[7]", None, "out of range");
    assert_eq!(e.problems.len(), 6, "{e}");
    let err = std::panic::catch_unwind(|| b.finalize()).unwrap_err();
    let msg = err.downcast_ref::<String>().unwrap();
    assert!(
        msg.contains("6 problems") && msg.contains("springs[1].indices"),
        "{msg}"
    );
    let e = json_err::<f32>(&two(
        "{ \"x\": [1, 0, 0], \"mass\": 1 }",
        ",\n\"springs\": [\n  { \"i\": 1, \"j\": 1, \"ke\": 10 }\n]",
    ));
    expect(&e, "springs[0]", 7, "appears twice");
    let e = json_err::<f32>(&two(
        "{ \"x\": [1, 0, 0], \"mass\": 1 }",
        ",\n\"tets\": [\n  { \"indices\": [0, 1, 2, 3], \"mu\": 1, \"lambda\": 1 }\n]",
    ));
    expect(&e, "tets[0].indices", 7, "out of range");
}

#[test]
fn bad_parameters_of_components_are_named() {
    let mut b = ModelBuilder::<f64>::new();
    b.set_ground(Ground {
        mu: -0.5,
        normal: Vec3::new(0.0, 2.0, 0.0),
        ..Ground::default()
    });
    b.set_drag(Drag {
        kd: f64::NAN,
        wind: Vec3::zeros(),
    });
    b.add_shape(Shape::new(ShapeKind::Sphere { radius: 0.0 }, Vec3::zeros()));
    b.gravity = Vec3::new(0.0, f64::INFINITY, 0.0);
    let e = builder_err(&b);
    has(&e, "ground", Some("mu"), ">= 0");
    has(&e, "ground", Some("normal"), "unit vector");
    has(&e, "drag", Some("kd"), ">= 0");
    has(&e, "shapes[0]", Some("radius"), "> 0");
    has(&e, "gravity", None, "finite");
}

#[test]
fn a_good_scene_finalizes_bitwise_as_before() {
    // The cloth benchmark scene through the builder (unchanged figures: see cloth.rs, which
    // checks Warp's loss) and a file scene through try_finalize and finalize alike.
    let scene = adflex_kernels::scenes::cloth::build::<f32>(8);
    let m = &scene.model;
    assert_eq!(m.particle_count, 64);
    let src = "{\n\"particles\": [\n {\"x\": [0,0,0], \"mass\": 0}, {\"x\": [1,0,0], \"mass\": 0.3},\n {\"x\": [0,1,0], \"mass\": 0.7}, {\"x\": [0.2,0.3,0.9], \"mass\": 1.1}],\n\"springs\": [ {\"i\": 0, \"j\": 3, \"ke\": 10} ],\n\"triangles\": [ {\"indices\": [0, 1, 2], \"mu\": 5, \"lambda\": 2} ],\n\"tets\": [ {\"indices\": [0, 2, 1, 3], \"mu\": 5, \"lambda\": 2} ]\n}";
    let b = ModelBuilder::<f64>::from_json_str(src).unwrap();
    let (m1, m2) = (b.try_finalize().unwrap(), b.finalize());
    for m in [&m1, &m2] {
        let inv: Vec<u64> = m
            .particle_inv_mass
            .to_vec()
            .iter()
            .map(|x| x.to_bits())
            .collect();
        let want: Vec<u64> = [0.0, 1.0 / 0.3, 1.0 / 0.7, 1.0 / 1.1]
            .iter()
            .map(|x: &f64| x.to_bits())
            .collect();
        assert_eq!(inv, want);
        let d: f64 = (0.2f64 * 0.2 + 0.3 * 0.3 + 0.9 * 0.9).sqrt();
        assert_eq!(m.springs().unwrap().rest.get(0).to_bits(), d.to_bits());
        let t = m.tets().unwrap();
        // Negatively oriented: stored as (i, k, j, l), with a positive volume.
        assert_eq!(t.tets.get(0), [0, 1, 2, 3]);
        assert_eq!(t.rest_volume.get(0).to_bits(), (0.9f64 / 6.0).to_bits());
    }
}

#[test]
fn bad_grids_are_errors_naming_the_grid_parameter() {
    let tet = |g: TetGrid<f64>| {
        let mut b = ModelBuilder::<f64>::new();
        g.add_to(&mut b);
        builder_err(&b)
    };
    let e = tet(TetGrid {
        dims: [0, 1, 1],
        ..TetGrid::default()
    });
    has(&e, "tet_grid", Some("dims"), "at least one cell");
    let e = tet(TetGrid {
        density: 0.0,
        ..TetGrid::default()
    });
    has(&e, "tet_grid", Some("density"), "> 0");
    // Only the grid's parameter is named, not the masses of its particles.
    assert_eq!(e.problems.len(), 1, "{e}");
    let e = tet(TetGrid {
        cell: f64::NAN,
        ..TetGrid::default()
    });
    has(&e, "tet_grid", Some("cell"), "> 0");

    let cloth = |g: ClothGrid<f64>| {
        let mut b = ModelBuilder::<f64>::new();
        b.add_cloth_grid(&g);
        builder_err(&b)
    };
    for (ni, nj) in [(1, 16), (0, 0), (5, 1)] {
        let e = cloth(ClothGrid {
            ni,
            nj,
            ..ClothGrid::default()
        });
        has(&e, "cloth_grid", Some("ni"), "at least 2 x 2");
    }
    let e = cloth(ClothGrid {
        pinned: vec![(99, 99)],
        ..ClothGrid::default()
    });
    has(&e, "cloth_grid", Some("pinned"), "(99, 99) is outside");
    // The defaults are good.
    let mut b = ModelBuilder::<f64>::new();
    b.add_cloth_grid(&ClothGrid::default());
    TetGrid::default().add_to(&mut b);
    b.try_finalize().unwrap();
}

//! Files written by adflex-viz read back: PLY, OBJ, USDA, PNG, GIF, SVG; and the errors.

use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};

use adflex_kernels::prelude::*;
use adflex_kernels::scenes::cloth;
use adflex_runtime::{Mat33, Quat, Tape, Vec3};
use adflex_viz::export::{self, Format};
use adflex_viz::render::{self, Camera, RenderOptions};
use adflex_viz::{plot, Error};

/// A fresh directory under the system temp dir, removed on drop.
struct TempDir(PathBuf);

impl TempDir {
    fn new(tag: &str) -> Self {
        static N: AtomicUsize = AtomicUsize::new(0);
        let k = N.fetch_add(1, Ordering::Relaxed);
        let p =
            std::env::temp_dir().join(format!("adflex-viz-test-{tag}-{}-{k}", std::process::id()));
        let _ = std::fs::remove_dir_all(&p);
        std::fs::create_dir_all(&p).unwrap();
        TempDir(p)
    }
    fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for TempDir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn rollout(model: &Model<f64>, initial: &State<f64>, steps: usize, dt: f64) -> Vec<State<f64>> {
    let mut tape = Tape::new();
    let mut states = vec![initial.clone()];
    for _ in 0..steps {
        let s = SemiImplicitEuler
            .step(model, &mut tape, states.last().unwrap(), None, dt)
            .unwrap();
        states.push(s);
    }
    states
}

/// The 4 x 4 cloth and 6 states of it falling.
fn cloth_states() -> (Model<f64>, Vec<State<f64>>) {
    let scene = cloth::build::<f64>(4);
    let states = rollout(&scene.model, &scene.initial, 5, 2e-2);
    (scene.model, states)
}

/// One tetrahedron, no triangles.
fn tet_model() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    let p = [
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(1.0, 1.0, 0.0),
        Vec3::new(0.0, 2.0, 0.0),
        Vec3::new(0.0, 1.0, 1.0),
    ];
    for x in p {
        b.add_particle(x, Vec3::zeros(), 1.0);
    }
    b.add_tet(0, 1, 2, 3, 100.0, 100.0, 0.0);
    b.finalize()
}

/// Three particles joined by springs, no triangles.
fn spring_model() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    for k in 0..3 {
        b.add_particle(Vec3::new(k as f64 * 0.5, 1.0, 0.0), Vec3::zeros(), 1.0);
    }
    b.add_spring(0, 1, 100.0, 0.1);
    b.add_spring(1, 2, 100.0, 0.1);
    b.finalize()
}

/// A cube-shaped rigid body (8 contact points) over the ground, spinning, plus a particle.
fn body_model() -> Model<f64> {
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle(Vec3::new(1.0, 1.0, 0.0), Vec3::zeros(), 1.0);
    let body = b.add_body(
        Vec3::new(0.0, 0.5, 0.0),
        Quat::identity(),
        Vec3::new(0.5, 0.0, 0.0),
        Vec3::new(0.0, 2.0, 1.0),
        1.0,
        Mat33::identity() * 0.1,
    );
    for sx in [-0.2, 0.2] {
        for sy in [-0.2, 0.2] {
            for sz in [-0.2, 0.2] {
                b.add_body_contact_point(body, Vec3::new(sx, sy, sz));
            }
        }
    }
    b.set_ground(Ground::default());
    b.finalize()
}

// ---------------------------------------------------------------- PLY / OBJ parsers

#[derive(Debug, Default)]
struct ParsedMesh {
    vertices: Vec<[f64; 3]>,
    faces: Vec<Vec<usize>>,
    edges: Vec<[usize; 2]>,
}

/// Header of a PLY file: format and `(element, count)` in order, and the header's length.
fn ply_header(bytes: &[u8]) -> (String, Vec<(String, usize)>, usize) {
    let end = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .expect("end_header")
        + 11;
    let text = std::str::from_utf8(&bytes[..end]).unwrap();
    let mut lines = text.lines();
    assert_eq!(lines.next(), Some("ply"));
    let mut format = String::new();
    let mut elements = Vec::new();
    for l in lines {
        let w: Vec<&str> = l.split_whitespace().collect();
        match w.first() {
            Some(&"format") => format = w[1].to_string(),
            Some(&"element") => elements.push((w[1].to_string(), w[2].parse().unwrap())),
            _ => {}
        }
    }
    (format, elements, end)
}

fn parse_ply(path: &Path) -> ParsedMesh {
    let bytes = std::fs::read(path).unwrap();
    let (format, elements, end) = ply_header(&bytes);
    let names: Vec<&str> = elements.iter().map(|e| e.0.as_str()).collect();
    assert_eq!(names, ["vertex", "face", "edge"]);
    let (nv, nf, ne) = (elements[0].1, elements[1].1, elements[2].1);
    let mut m = ParsedMesh::default();
    if format == "ascii" {
        let text = std::str::from_utf8(&bytes[end..]).unwrap();
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(lines.len(), nv + nf + ne, "body lines");
        for l in &lines[..nv] {
            let v: Vec<f64> = l.split_whitespace().map(|t| t.parse().unwrap()).collect();
            m.vertices.push([v[0], v[1], v[2]]);
        }
        for l in &lines[nv..nv + nf] {
            let v: Vec<usize> = l.split_whitespace().map(|t| t.parse().unwrap()).collect();
            assert_eq!(v[0], v.len() - 1);
            m.faces.push(v[1..].to_vec());
        }
        for l in &lines[nv + nf..] {
            let v: Vec<usize> = l.split_whitespace().map(|t| t.parse().unwrap()).collect();
            m.edges.push([v[0], v[1]]);
        }
    } else {
        assert_eq!(format, "binary_little_endian");
        let mut r = &bytes[end..];
        let mut take = |n: usize| {
            let (a, b) = r.split_at(n);
            r = b;
            a.to_vec()
        };
        for _ in 0..nv {
            let v = [0, 1, 2].map(|_| f32::from_le_bytes(take(4).try_into().unwrap()) as f64);
            m.vertices.push(v);
        }
        for _ in 0..nf {
            let n = take(1)[0] as usize;
            let f = (0..n)
                .map(|_| i32::from_le_bytes(take(4).try_into().unwrap()) as usize)
                .collect();
            m.faces.push(f);
        }
        for _ in 0..ne {
            let e = [0, 1].map(|_| i32::from_le_bytes(take(4).try_into().unwrap()) as usize);
            m.edges.push(e);
        }
        assert!(r.is_empty(), "trailing bytes");
    }
    m
}

fn parse_obj(path: &Path) -> ParsedMesh {
    let text = std::fs::read_to_string(path).unwrap();
    let mut m = ParsedMesh::default();
    for l in text.lines() {
        let mut w = l.split_whitespace();
        match w.next() {
            Some("v") => {
                let v: Vec<f64> = w.map(|t| t.parse().unwrap()).collect();
                m.vertices.push([v[0], v[1], v[2]]);
            }
            Some("f") => m
                .faces
                .push(w.map(|t| t.parse::<usize>().unwrap() - 1).collect()),
            Some("l") => {
                let v: Vec<usize> = w.map(|t| t.parse::<usize>().unwrap() - 1).collect();
                m.edges.push([v[0], v[1]]);
            }
            Some("#") | Some("o") | None => {}
            Some(other) => panic!("unexpected OBJ line {other}"),
        }
    }
    m
}

fn assert_positions(parsed: &[[f64; 3]], x: &[Vec3<f64>]) {
    for (k, (p, x)) in parsed.iter().zip(x).enumerate() {
        for c in 0..3 {
            let tol = 1e-6 * (1.0 + x[c].abs());
            assert!((p[c] - x[c]).abs() <= tol, "vertex {k}: {p:?} vs {x:?}");
        }
    }
}

fn check_cloth_mesh(m: &ParsedMesh, model: &Model<f64>, state: &State<f64>) {
    assert_eq!(m.vertices.len(), 16);
    assert_positions(&m.vertices, &state.x.to_vec());
    assert_eq!(m.faces.len(), model.triangles.len());
    assert_eq!(m.faces.len(), 18);
    let springs = model.springs().unwrap().pairs.to_vec();
    assert_eq!(m.edges.len(), springs.len());
    for (f, t) in m.faces.iter().zip(&model.triangles) {
        assert_eq!(f, &t.map(|i| i as usize).to_vec());
    }
    for (e, s) in m.edges.iter().zip(&springs) {
        assert_eq!(e, &s.map(|i| i as usize));
    }
}

#[test]
fn ply_ascii_parses_back() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("ply");
    let last = states.last().unwrap();
    export::write_ply(dir.path("c.ply"), &model, last).unwrap();
    let m = parse_ply(&dir.path("c.ply"));
    check_cloth_mesh(&m, &model, last);
    // The cloth has moved: frame 0 and the last differ.
    assert_ne!(states[0].x.to_vec(), last.x.to_vec());
}

#[test]
fn ply_binary_parses_back() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("plyb");
    let last = states.last().unwrap();
    export::write_ply_binary(dir.path("c.ply"), &model, last).unwrap();
    let m = parse_ply(&dir.path("c.ply"));
    // f32 storage: compare with f32 precision.
    let x: Vec<Vec3<f64>> = last
        .x
        .to_vec()
        .iter()
        .map(|v| v.map(|c| c as f32 as f64))
        .collect();
    assert_positions(&m.vertices, &x);
    assert_eq!(
        (m.faces.len(), m.edges.len()),
        (18, model.springs().unwrap().len())
    );
}

#[test]
fn obj_parses_back() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("obj");
    let last = states.last().unwrap();
    export::write_obj(dir.path("c.obj"), &model, last).unwrap();
    let m = parse_obj(&dir.path("c.obj"));
    check_cloth_mesh(&m, &model, last);
}

#[test]
fn tet_boundary_faces_are_exported() {
    let model = tet_model();
    let dir = TempDir::new("tet");
    export::write_ply(dir.path("t.ply"), &model, &model.state()).unwrap();
    let m = parse_ply(&dir.path("t.ply"));
    assert_eq!((m.vertices.len(), m.faces.len(), m.edges.len()), (4, 4, 0));
    let keys: HashSet<Vec<usize>> = m
        .faces
        .iter()
        .map(|f| {
            let mut k = f.clone();
            k.sort();
            k
        })
        .collect();
    assert_eq!(keys.len(), 4);
}

#[test]
fn rigid_body_points_and_edges_are_exported() {
    let model = body_model();
    let states = rollout(&model, &model.state(), 4, 1e-2);
    let dir = TempDir::new("body");
    let last = states.last().unwrap();
    export::write_obj(dir.path("b.obj"), &model, last).unwrap();
    let m = parse_obj(&dir.path("b.obj"));
    // 1 particle + 8 contact points; the cube's 12 edges.
    assert_eq!((m.vertices.len(), m.faces.len(), m.edges.len()), (9, 0, 12));
    // The contact points are the body's, moved by its pose: centred on its centre of mass.
    let c = last.bodies.as_ref().unwrap().x.get(0);
    let mean = m.vertices[1..]
        .iter()
        .fold(Vec3::zeros(), |a, v| a + Vec3::new(v[0], v[1], v[2]))
        / 8.0;
    assert!((mean - c).norm() < 1e-6, "{mean:?} vs {c:?}");
    // Distances to the centre stay sqrt(3) 0.2 (a rotation).
    for v in &m.vertices[1..] {
        let d = (Vec3::new(v[0], v[1], v[2]) - c).norm();
        assert!((d - 0.2 * 3f64.sqrt()).abs() < 1e-5, "{d}");
    }

    export::write_usda(dir.path("b.usda"), &model, &states, 24.0).unwrap();
    let text = std::fs::read_to_string(dir.path("b.usda")).unwrap();
    assert!(text.contains("def Xform \"body_0\""));
    let translate = sample_block(&text, "double3 xformOp:translate.timeSamples");
    let orient = sample_block(&text, "quatf xformOp:orient.timeSamples");
    assert_eq!(translate.len(), states.len());
    assert_eq!(orient.len(), states.len());
    assert!(text.contains("xformOpOrder = [\"xformOp:translate\", \"xformOp:orient\"]"));
    assert!(text.contains("def Points \"contacts\""));
}

#[test]
fn sequence_writes_numbered_frames() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("seq");
    for format in [Format::Ply, Format::PlyBinary, Format::Obj] {
        let sub = dir.path(format.extension()).join(format!("{format:?}"));
        let files = export::write_sequence(&sub, &model, &states, format).unwrap();
        assert_eq!(files.len(), states.len());
        for (k, f) in files.iter().enumerate() {
            assert_eq!(
                f.file_name().unwrap().to_str().unwrap(),
                format!("frame_{k:04}.{}", format.extension())
            );
            assert!(f.is_file());
        }
        let m = match format {
            Format::Obj => parse_obj(&files[2]),
            _ => parse_ply(&files[2]),
        };
        assert_eq!(m.vertices.len(), 16);
    }
}

// ---------------------------------------------------------------- USDA

/// The `k: value` entries of the time-sample block that starts with `head` (one per line).
fn sample_block(text: &str, head: &str) -> Vec<(usize, String)> {
    let start = text.find(head).unwrap_or_else(|| panic!("no {head}"));
    let mut out = Vec::new();
    for l in text[start..].lines().skip(1) {
        let l = l.trim();
        if l == "}" {
            break;
        }
        let (k, v) = l.split_once(':').unwrap();
        out.push((
            k.trim().parse().unwrap(),
            v.trim().trim_end_matches(',').to_string(),
        ));
    }
    out
}

fn parse_points(v: &str) -> Vec<[f64; 3]> {
    let v = v.trim().trim_start_matches('[').trim_end_matches(']');
    v.split("), (")
        .map(|p| {
            let c: Vec<f64> = p
                .trim_matches(|c| c == '(' || c == ')')
                .split(',')
                .map(|t| t.trim().parse().unwrap())
                .collect();
            [c[0], c[1], c[2]]
        })
        .collect()
}

fn stage_metadata(text: &str, key: &str) -> f64 {
    let l = text
        .lines()
        .find(|l| l.trim_start().starts_with(key))
        .unwrap_or_else(|| panic!("no {key}"));
    l.split('=').nth(1).unwrap().trim().parse().unwrap()
}

#[test]
fn usda_points_and_time_codes_parse_back() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("usda");
    export::write_usda(dir.path("c.usda"), &model, &states, 30.0).unwrap();
    let text = std::fs::read_to_string(dir.path("c.usda")).unwrap();
    assert!(text.starts_with("#usda 1.0\n"));
    assert_eq!(stage_metadata(&text, "startTimeCode"), 0.0);
    assert_eq!(
        stage_metadata(&text, "endTimeCode"),
        (states.len() - 1) as f64
    );
    assert_eq!(stage_metadata(&text, "timeCodesPerSecond"), 30.0);
    assert!(text.contains("def Mesh \"mesh\""));
    let samples = sample_block(&text, "point3f[] points.timeSamples");
    let codes: Vec<usize> = samples.iter().map(|s| s.0).collect();
    assert_eq!(codes, (0..states.len()).collect::<Vec<_>>());
    for k in [0, states.len() - 1] {
        let pts = parse_points(&samples[k].1);
        assert_eq!(pts.len(), 16);
        assert_positions(&pts, &states[k].x.to_vec());
    }
    let counts = text
        .lines()
        .find(|l| l.contains("int[] faceVertexCounts"))
        .unwrap();
    assert_eq!(counts.matches('3').count(), 18);
    let indices = text
        .lines()
        .find(|l| l.contains("int[] faceVertexIndices"))
        .unwrap();
    assert_eq!(indices.split(',').count(), 54);
    // Braces balance.
    assert_eq!(text.matches('{').count(), text.matches('}').count());
}

#[test]
fn usda_springs_without_triangles_are_points_and_curves() {
    let model = spring_model();
    let states = rollout(&model, &model.state(), 3, 1e-2);
    let dir = TempDir::new("usda-springs");
    export::write_usda(dir.path("s.usda"), &model, &states, 60.0).unwrap();
    let text = std::fs::read_to_string(dir.path("s.usda")).unwrap();
    assert!(!text.contains("def Mesh"));
    assert!(text.contains("def Points \"particles\""));
    assert!(text.contains("def BasisCurves \"springs\""));
    assert!(text.contains("curveVertexCounts = [2, 2]"));
    assert!(text.contains("float[] widths = [0.02]"));
    let curves_at = text.find("def BasisCurves").unwrap();
    let pts = sample_block(&text, "point3f[] points.timeSamples");
    assert_eq!(pts.len(), 4);
    assert_eq!(parse_points(&pts[3].1).len(), 3);
    let curve = sample_block(&text[curves_at..], "point3f[] points.timeSamples");
    assert_eq!(curve.len(), 4);
    assert_eq!(parse_points(&curve[0].1).len(), 4);
}

// ---------------------------------------------------------------- pictures

fn decode_png(path: &Path) -> (u32, u32, Vec<[u8; 4]>) {
    let dec = png::Decoder::new(std::io::BufReader::new(std::fs::File::open(path).unwrap()));
    let mut reader = dec.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgba);
    assert_eq!(info.bit_depth, png::BitDepth::Eight);
    let px = buf[..info.buffer_size()]
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]])
        .collect();
    (info.width, info.height, px)
}

#[test]
fn png_of_cloth_is_a_picture() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("png");
    let opts = RenderOptions {
        width: 200,
        height: 150,
        ..RenderOptions::default()
    };
    render::render_png(dir.path("c.png"), &model, states.last().unwrap(), &opts).unwrap();
    let (w, h, px) = decode_png(&dir.path("c.png"));
    assert_eq!((w, h), (200, 150));
    let colors: HashSet<[u8; 4]> = px.iter().copied().collect();
    assert!(colors.len() >= 8, "{} colours", colors.len());
    // The middle of the picture shows the cloth, not the background.
    let bg = opts.background;
    let bg = [bg.r, bg.g, bg.b, bg.a];
    let mut fg = 0;
    for y in h / 3..2 * h / 3 {
        for x in w / 3..2 * w / 3 {
            if px[(y * w + x) as usize] != bg {
                fg += 1;
            }
        }
    }
    let area = (w / 3) * (h / 3);
    assert!(
        fg > area / 4,
        "{fg} of {area} foreground pixels in the middle"
    );
}

#[test]
fn render_frame_draws_bodies_tets_and_springs() {
    for model in [body_model(), tet_model(), spring_model()] {
        let opts = RenderOptions {
            width: 96,
            height: 64,
            ..RenderOptions::default()
        };
        let pm = render::render_frame(&model, &model.state(), &opts).unwrap();
        let colors: HashSet<[u8; 4]> = pm
            .pixels()
            .iter()
            .map(|p| {
                let c = p.demultiply();
                [c.red(), c.green(), c.blue(), c.alpha()]
            })
            .collect();
        assert!(colors.len() >= 3, "{} colours", colors.len());
    }
}

#[test]
fn fitted_camera_sees_every_particle() {
    let (model, states) = cloth_states();
    let cam = Camera::fit(&model, &states);
    for s in &states {
        for x in s.x.to_vec() {
            let (px, py) = cam.project(x, 320, 240).unwrap();
            assert!((0.0..320.0).contains(&px) && (0.0..240.0).contains(&py));
        }
    }
}

#[test]
fn gif_has_the_expected_frames() {
    let model = body_model();
    let states = rollout(&model, &model.state(), 6, 1e-2);
    assert_eq!(states.len(), 7);
    let dir = TempDir::new("gif");
    let opts = RenderOptions {
        width: 64,
        height: 48,
        ..RenderOptions::default()
    };
    render::render_gif(dir.path("b.gif"), &model, &states, &opts, 20.0, 2).unwrap();
    let mut opts_dec = gif::DecodeOptions::new();
    opts_dec.set_color_output(gif::ColorOutput::RGBA);
    let mut dec = opts_dec
        .read_info(std::fs::File::open(dir.path("b.gif")).unwrap())
        .unwrap();
    assert_eq!((dec.width(), dec.height()), (64, 48));
    let mut frames = 0;
    while let Some(f) = dec.read_next_frame().unwrap() {
        assert_eq!((f.width, f.height), (64, 48));
        assert_eq!(f.delay, 5);
        frames += 1;
    }
    // States 0, 2, 4, 6.
    assert_eq!(frames, 4);
}

// ---------------------------------------------------------------- plots

#[test]
fn loss_curve_is_svg_with_a_line() {
    let dir = TempDir::new("svg");
    let log: Vec<f64> = (0..40).map(|k| 100.0 * 0.7f64.powi(k)).collect();
    plot::loss_curve(dir.path("log.svg"), &log, "decaying").unwrap();
    let lin = [3.0, 2.5, 2.4, f64::NAN, 2.3];
    plot::loss_curve(dir.path("lin.svg"), &lin, "flat").unwrap();
    for f in ["log.svg", "lin.svg"] {
        let text = std::fs::read_to_string(dir.path(f)).unwrap();
        assert!(
            text.contains("<svg") && text.trim_end().ends_with("</svg>"),
            "{f}"
        );
        assert!(text.contains("<polyline") || text.contains("<path"), "{f}");
    }
    let text = std::fs::read_to_string(dir.path("log.svg")).unwrap();
    assert!(text.contains("decaying"));
}

#[test]
fn curves_have_a_legend() {
    let dir = TempDir::new("curves");
    let a: Vec<(f64, f64)> = (0..50).map(|k| (k as f64 * 0.1, 1.0)).collect();
    let b: Vec<(f64, f64)> = (0..50)
        .map(|k| (k as f64 * 0.1, 1.0 + 0.05 * k as f64))
        .collect();
    plot::curves(
        dir.path("e.svg"),
        "energy",
        "time (s)",
        "energy (J)",
        &[("semi-implicit Euler", &a[..]), ("explicit Euler", &b[..])],
    )
    .unwrap();
    let text = std::fs::read_to_string(dir.path("e.svg")).unwrap();
    for s in [
        "semi-implicit Euler",
        "explicit Euler",
        "time (s)",
        "energy (J)",
    ] {
        assert!(text.contains(s), "{s}");
    }
    assert!(text.matches("<polyline").count() + text.matches("<path").count() >= 2);
}

/// A `.png` path draws the same chart in pixels: the size of an SVG chart, each series in its
/// colour, the title in dark text at the top, the y axis label drawn rotated (taller than
/// wide).
#[test]
fn png_charts_draw_lines_and_text() {
    let dir = TempDir::new("png-chart");
    let a: Vec<(f64, f64)> = (0..50).map(|k| (k as f64 * 0.1, 1.0)).collect();
    let b: Vec<(f64, f64)> = (0..50)
        .map(|k| (k as f64 * 0.1, 1.0 + 0.05 * k as f64))
        .collect();
    let path = dir.path("e.png");
    plot::curves(
        &path,
        "energy",
        "time (s)",
        "energy (J)",
        &[("semi-implicit Euler", &a[..]), ("explicit Euler", &b[..])],
    )
    .unwrap();
    let (w, h, px) = decode_png(&path);
    assert_eq!((w, h), plot::SIZE);
    let at = |x: u32, y: u32| px[(y * w + x) as usize];
    let count = |f: &dyn Fn([u8; 4]) -> bool, x0: u32, x1: u32, y0: u32, y1: u32| {
        let mut n = 0;
        for y in y0..y1 {
            for x in x0..x1 {
                n += f(at(x, y)) as usize;
            }
        }
        n
    };
    let dark = |c: [u8; 4]| c[0] < 60 && c[1] < 60 && c[2] < 60;
    // The series' colours (blue, orange).
    let blue = |c: [u8; 4]| c[2] > 150 && c[0] < 80;
    let orange = |c: [u8; 4]| c[0] > 220 && c[1] > 100 && c[1] < 160 && c[2] < 60;
    assert!(count(&blue, 0, w, 0, h) > 200, "the first series");
    assert!(count(&orange, 0, w, 0, h) > 200, "the second series");
    // The title: dark pixels in the top band, centred.
    assert!(
        count(&dark, w / 2 - 60, w / 2 + 60, 0, 40) > 50,
        "the title"
    );
    // The y label, left of the axis: its dark pixels span more rows than columns.
    let (mut rows, mut cols) = (
        std::collections::BTreeSet::new(),
        std::collections::BTreeSet::new(),
    );
    for y in 60..h - 60 {
        for x in 0..30 {
            if dark(at(x, y)) {
                rows.insert(y);
                cols.insert(x);
            }
        }
    }
    assert!(
        rows.len() > 3 * cols.len() && cols.len() >= 6,
        "rotated y label: {} rows, {} columns",
        rows.len(),
        cols.len()
    );
    // The other format from the same call, by extension: text a viewer renders.
    plot::loss_curve(dir.path("l.svg"), &[3.0, 1.0], "svg").unwrap();
    plot::loss_curve(dir.path("l.PNG"), &[3.0, 1.0], "png").unwrap();
    assert!(std::fs::read_to_string(dir.path("l.svg"))
        .unwrap()
        .contains("<svg"));
    assert_eq!(&std::fs::read(dir.path("l.PNG")).unwrap()[1..4], b"PNG");
}

// ---------------------------------------------------------------- errors

#[test]
fn unwritable_paths_are_errors_naming_the_path() {
    let (model, states) = cloth_states();
    let dir = TempDir::new("err");
    // A path under a regular file cannot be created, even by root.
    std::fs::write(dir.path("file"), b"x").unwrap();
    let bad = dir.path("file").join("sub");
    let s = &states[0];
    let opts = RenderOptions {
        width: 32,
        height: 32,
        ..RenderOptions::default()
    };
    let results: Vec<(PathBuf, Result<(), Error>)> = vec![
        (
            bad.join("a.ply"),
            export::write_ply(bad.join("a.ply"), &model, s),
        ),
        (
            bad.join("b.ply"),
            export::write_ply_binary(bad.join("b.ply"), &model, s),
        ),
        (
            bad.join("a.obj"),
            export::write_obj(bad.join("a.obj"), &model, s),
        ),
        (
            bad.join("a.usda"),
            export::write_usda(bad.join("a.usda"), &model, &states, 30.0),
        ),
        (
            bad.clone(),
            export::write_sequence(&bad, &model, &states, Format::Ply).map(|_| ()),
        ),
        (
            bad.join("a.png"),
            render::render_png(bad.join("a.png"), &model, s, &opts),
        ),
        (
            bad.join("a.gif"),
            render::render_gif(bad.join("a.gif"), &model, &states, &opts, 10.0, 1),
        ),
        (
            bad.join("a.svg"),
            plot::loss_curve(bad.join("a.svg"), &[1.0, 0.5], "l"),
        ),
    ];
    for (path, r) in results {
        let e = r.expect_err("unwritable path");
        assert!(matches!(e, Error::Io { .. }), "{e:?}");
        assert_eq!(e.path(), Some(path.as_path()));
        assert!(e.to_string().contains(&path.display().to_string()), "{e}");
    }
}

#[test]
fn empty_inputs_are_errors() {
    let model = spring_model();
    let dir = TempDir::new("empty");
    let none: &[State<f64>] = &[];
    let opts = RenderOptions::default();
    let errs = [
        export::write_sequence(dir.path("seq"), &model, none, Format::Obj).map(|_| ()),
        export::write_usda(dir.path("a.usda"), &model, none, 30.0),
        render::render_gif(dir.path("a.gif"), &model, none, &opts, 10.0, 1),
        plot::loss_curve(dir.path("a.svg"), &[], "empty"),
        plot::loss_curve(dir.path("b.svg"), &[f64::NAN], "nan"),
        plot::curves(dir.path("c.svg"), "t", "x", "y", &[]),
    ];
    for e in errs {
        let e = e.expect_err("empty input");
        assert!(matches!(e, Error::Empty { .. }), "{e:?}");
        assert!(e.path().is_some());
    }
    assert!(!dir.path("seq").exists());
}

#[test]
fn bad_options_are_errors() {
    let model = spring_model();
    let s = model.state();
    let zero = RenderOptions {
        width: 0,
        ..RenderOptions::default()
    };
    assert!(matches!(
        render::render_frame(&model, &s, &zero),
        Err(Error::Invalid(_))
    ));
    let cam = Camera::looking_at(Vec3::zeros(), Vec3::zeros(), Vec3::y(), 40.0);
    let degenerate = RenderOptions {
        camera: Some(cam),
        ..RenderOptions::default()
    };
    assert!(matches!(
        render::render_frame(&model, &s, &degenerate),
        Err(Error::Invalid(_))
    ));
    // A state of another model.
    let other = tet_model().state();
    let (cloth_model, _) = cloth_states();
    let e = render::render_frame(&cloth_model, &other, &RenderOptions::default()).unwrap_err();
    assert!(e.to_string().contains("4 particles, the model 16"), "{e}");
    let dir = TempDir::new("badopt");
    assert!(matches!(
        export::write_ply(dir.path("o.ply"), &cloth_model, &other),
        Err(Error::Invalid(_))
    ));
    assert!(matches!(
        export::write_usda(dir.path("o.usda"), &cloth_model, &[other], 30.0),
        Err(Error::Invalid(_))
    ));
    let wide = RenderOptions {
        width: 70000,
        height: 1,
        ..RenderOptions::default()
    };
    assert!(matches!(
        render::render_gif(
            dir.path("w.gif"),
            &model,
            std::slice::from_ref(&s),
            &wide,
            10.0,
            1
        ),
        Err(Error::Invalid(_))
    ));
    assert!(matches!(
        export::write_usda(dir.path("a.usda"), &model, &[s], 0.0),
        Err(Error::Invalid(_))
    ));
}

#[test]
fn per_particle_radii_are_exported_and_drawn() {
    // Two particles: a 0.1 m ball and a default (0.01 m) one.
    let mut b = ModelBuilder::<f64>::new();
    b.add_particle_with_radius(Vec3::new(-0.5, 0.5, 0.0), Vec3::zeros(), 1.0, 0.1);
    b.add_particle(Vec3::new(0.5, 0.5, 0.0), Vec3::zeros(), 1.0);
    let model = b.finalize();
    let states = vec![model.state()];
    let dir = TempDir::new("radii");
    export::write_usda(dir.path("r.usda"), &model, &states, 60.0).unwrap();
    let text = std::fs::read_to_string(dir.path("r.usda")).unwrap();
    assert!(text.contains("float[] widths = [0.2, 0.02]"), "{text}");
    assert!(text.contains("interpolation = \"vertex\""), "{text}");

    // The big ball covers many more pixels than the small one (same distance to the camera).
    let opts = RenderOptions {
        width: 200,
        height: 100,
        draw_ground: false,
        ..RenderOptions::default()
    };
    let pm = render::render_frame(&model, &states[0], &opts).unwrap();
    let bg = opts.background;
    let count = |half: std::ops::Range<u32>| {
        let mut n = 0;
        for y in 0..pm.height() {
            for x in half.clone() {
                let p = pm.pixel(x, y).unwrap().demultiply();
                if [p.red(), p.green(), p.blue()] != [bg.r, bg.g, bg.b] {
                    n += 1;
                }
            }
        }
        n
    };
    let (big, small) = (count(0..100), count(100..200));
    assert!(
        small > 0 && big > 8 * small,
        "big {big} px, small {small} px"
    );
}

#[test]
fn non_finite_coordinates_are_written_as_usd_and_ply_read_them() {
    let model = spring_model();
    let s = model.state();
    s.x.set(1, Vec3::new(f64::NAN, f64::INFINITY, 0.0));
    let dir = TempDir::new("nan");
    // The exporters write what they are given (a diverged frame is worth seeing), spelled
    // the way USD's parser reads it.
    export::write_usda(dir.path("n.usda"), &model, std::slice::from_ref(&s), 60.0).unwrap();
    let text = std::fs::read_to_string(dir.path("n.usda")).unwrap();
    assert!(
        text.contains("(nan, inf, 0)") && !text.contains("NaN"),
        "{text}"
    );
}

// ---------------------------------------------------------------- independent readers

/// The Python of a venv with the readers of `viz/tools/requirements.txt` (Pixar's usd-core,
/// plyfile): `ADFLEX_VIZ_PYTHON` if set, else a venv this test makes once under the target
/// directory (`python3 -m venv`, then `pip install -r`; needs python3 and PyPI). Panics with
/// what is missing and how to provide it: a check that cannot run must not pass.
fn reader_python() -> PathBuf {
    if let Some(p) = std::env::var_os("ADFLEX_VIZ_PYTHON") {
        return PathBuf::from(p);
    }
    let venv = Path::new(env!("CARGO_TARGET_TMPDIR")).join("viz-tools-venv");
    let python = venv.join("bin").join("python");
    let reqs = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/requirements.txt");
    let stamp = venv.join("requirements.txt");
    let wanted = std::fs::read_to_string(&reqs).unwrap();
    if std::fs::read_to_string(&stamp).ok().as_deref() == Some(wanted.as_str()) {
        return python;
    }
    let run = |cmd: &mut std::process::Command, what: &str| {
        let out = cmd
            .output()
            .unwrap_or_else(|e| panic!("{what}: cannot start it ({e}); install Python 3 (python3 with venv and pip), or set ADFLEX_VIZ_PYTHON to a Python that has viz/tools/requirements.txt"));
        assert!(
            out.status.success(),
            "{what} failed ({}):\n{}\nInstall Python 3 with venv and pip and PyPI access, or set ADFLEX_VIZ_PYTHON to a Python that has viz/tools/requirements.txt",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
    };
    run(
        std::process::Command::new("python3")
            .args(["-m", "venv"])
            .arg(&venv),
        "python3 -m venv",
    );
    run(
        std::process::Command::new(&python)
            .args(["-m", "pip", "install", "-q", "-r"])
            .arg(&reqs),
        "pip install -r viz/tools/requirements.txt",
    );
    std::fs::write(&stamp, wanted).unwrap();
    python
}

/// Runs `viz/tools/check_files.py` on `files`: one JSON object per file.
fn read_with_python(files: &[PathBuf]) -> Vec<serde_json::Value> {
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/check_files.py");
    let out = std::process::Command::new(reader_python())
        .arg(script)
        .args(files)
        .output()
        .expect("run check_files.py");
    assert!(
        out.status.success(),
        "an independent reader rejected a file: {}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

/// The USD stages open with Pixar's own library (usd-core): every prim is of a registered
/// schema type, points are time-sampled over the whole rollout, every boundable prim authors
/// its extent and it is what USD computes from the points and widths at every time code;
/// PLY files (ASCII and binary) read with plyfile give the particles.
#[test]
fn files_open_in_their_makers_readers() {
    let dir = TempDir::new("readers");
    let (cloth_model, cloth) = cloth_states();
    let springs = spring_model();
    let spring_states = rollout(&springs, &springs.state(), 4, 2e-2);
    let bodies = body_model();
    let body_states = rollout(&bodies, &bodies.state(), 4, 2e-2);
    let mut b = ModelBuilder::<f64>::new();
    for k in 0..4 {
        let i = b.add_particle(Vec3::new(k as f64, 1.0, 0.0), Vec3::new(0.0, 1.0, 0.0), 1.0);
        b.set_particle_radius(i, 0.05 * (k + 1) as f64);
    }
    let radii = b.finalize();
    let radii_states = rollout(&radii, &radii.state(), 3, 2e-2);
    let files = [
        dir.path("cloth.usda"),
        dir.path("springs.usda"),
        dir.path("bodies.usda"),
        dir.path("radii.usda"),
        dir.path("cloth.ply"),
        dir.path("cloth_binary.ply"),
    ];
    export::write_usda(&files[0], &cloth_model, &cloth, 30.0).unwrap();
    export::write_usda(&files[1], &springs, &spring_states, 30.0).unwrap();
    export::write_usda(&files[2], &bodies, &body_states, 30.0).unwrap();
    export::write_usda(&files[3], &radii, &radii_states, 30.0).unwrap();
    let last = cloth.last().unwrap();
    export::write_ply(&files[4], &cloth_model, last).unwrap();
    export::write_ply_binary(&files[5], &cloth_model, last).unwrap();
    let found = read_with_python(&files);
    assert_eq!(found.len(), files.len());
    let frames = [
        cloth.len(),
        spring_states.len(),
        body_states.len(),
        radii_states.len(),
    ];
    let mut types = HashSet::new();
    for (stage, &n) in found[..4].iter().zip(&frames) {
        assert_eq!(stage["default_prim"], "/World", "{stage}");
        for prim in stage["prims"].as_array().unwrap() {
            let ty = prim["type"].as_str().unwrap();
            types.insert(ty.to_string());
            assert_eq!(prim["schema"], true, "{prim}");
            if let Some(k) = prim.get("points_time_samples") {
                // Body contact points and edges are static, in the body's frame.
                let static_ok = prim["path"].as_str().unwrap().contains("/body_");
                assert!(
                    k == n || (static_ok && k == 0),
                    "{prim}: {k} samples of {n}"
                );
            }
            if prim.get("extent_authored").is_some() {
                assert_eq!(prim["extent_authored"], true, "{prim}");
                let err = prim["extent_error"].as_f64().unwrap_or(f64::INFINITY);
                assert!(err < 1e-6, "{prim}: extent off by {err}");
            }
        }
    }
    for ty in ["Xform", "Mesh", "Points", "BasisCurves"] {
        assert!(types.contains(ty), "no {ty} prim in {types:?}");
    }
    let x = last.x.to_vec();
    for ply in &found[4..] {
        let v = &ply["elements"]["vertex"];
        assert_eq!(v["count"], x.len(), "{ply}");
        let first: Vec<f64> = serde_json::from_value(ply["first_vertex"].clone()).unwrap();
        for c in 0..3 {
            assert!((first[c] - x[0][c]).abs() < 1e-6, "{ply}");
        }
        assert_eq!(
            ply["elements"]["face"]["count"],
            cloth_model.triangles.len(),
            "{ply}"
        );
    }
}

/// `node` with the packages of `viz/tools/package.json` (the Khronos glTF validator) on its
/// module path, installed once under the target directory by `npm install` (needs Node.js,
/// npm and the npm registry); panics with what is missing otherwise.
fn validator_node() -> (PathBuf, PathBuf) {
    let dir = Path::new(env!("CARGO_TARGET_TMPDIR")).join("viz-tools-node");
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/package.json");
    let wanted = std::fs::read_to_string(&manifest).unwrap();
    let modules = dir.join("node_modules");
    if std::fs::read_to_string(dir.join("package.json"))
        .ok()
        .as_deref()
        != Some(wanted.as_str())
        || !modules.join("gltf-validator").exists()
    {
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(dir.join("package.json"), &wanted).unwrap();
        let out = std::process::Command::new("npm")
            .args(["install", "--no-audit", "--no-fund", "--loglevel=error"])
            .current_dir(&dir)
            .output()
            .unwrap_or_else(|e| {
                panic!(
                    "npm: cannot start it ({e}); install Node.js and npm to run the glTF validator"
                )
            });
        assert!(
            out.status.success(),
            "npm install (viz/tools/package.json) failed: {}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
    }
    (PathBuf::from("node"), modules)
}

/// Animated `.glb` files of a cloth (mesh with morph targets), springs (lines), loose
/// particles (points) and a rigid body (animated node) pass the Khronos glTF validator with
/// no error and no warning, and say so in its report (the animation is there).
#[test]
fn glb_files_pass_the_khronos_validator() {
    let dir = TempDir::new("gltf");
    let (cloth_model, cloth) = cloth_states();
    let springs = spring_model();
    let spring_states = rollout(&springs, &springs.state(), 4, 2e-2);
    let bodies = body_model();
    let body_states = rollout(&bodies, &bodies.state(), 4, 2e-2);
    let tet = tet_model();
    let one = vec![tet.state()];
    // A body without contact points, one state: nothing to put in a buffer.
    let mut b = ModelBuilder::<f64>::new();
    b.add_body(
        Vec3::new(0.0, 1.0, 0.0),
        Quat::identity(),
        Vec3::zeros(),
        Vec3::zeros(),
        1.0,
        Mat33::identity(),
    );
    let bare = b.finalize();
    let files = [
        dir.path("cloth.glb"),
        dir.path("springs.glb"),
        dir.path("bodies.glb"),
        dir.path("tet_one_frame.glb"),
        dir.path("bare_body.glb"),
    ];
    adflex_viz::gltf::write_glb(&files[0], &cloth_model, &cloth, 30.0).unwrap();
    adflex_viz::gltf::write_glb(&files[1], &springs, &spring_states, 30.0).unwrap();
    adflex_viz::gltf::write_glb(&files[2], &bodies, &body_states, 30.0).unwrap();
    adflex_viz::gltf::write_glb(&files[3], &tet, &one, 30.0).unwrap();
    adflex_viz::gltf::write_glb(&files[4], &bare, &[bare.state()], 30.0).unwrap();
    let (node, modules) = validator_node();
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tools/validate_gltf.js");
    let out = std::process::Command::new(node)
        .arg(script)
        .args(&files)
        .env("NODE_PATH", modules)
        .output()
        .unwrap_or_else(|e| panic!("node: cannot start it ({e}); install Node.js"));
    assert!(
        out.status.success(),
        "the validator failed to run: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    let reports: Vec<serde_json::Value> = String::from_utf8(out.stdout)
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(reports.len(), files.len());
    for (r, animated) in reports.iter().zip([true, true, true, false, false]) {
        assert_eq!(r["errors"], 0, "{r}");
        assert_eq!(r["warnings"], 0, "{r}");
        assert_eq!(r["animations"], animated as u64, "{r}");
    }
    // A non-finite position is refused, naming it.
    let s = cloth[1].clone();
    let mut x = s.x.to_vec();
    x[3].y = f64::NAN;
    s.x.assign(&x);
    let e = adflex_viz::gltf::write_glb(
        dir.path("nan.glb"),
        &cloth_model,
        &[cloth[0].clone(), s],
        30.0,
    )
    .unwrap_err();
    assert!(e.to_string().contains("particle 3 of state 1"), "{e}");
}

// ---------------------------------------------------------------- overlays

fn count(pm: &render::Pixmap, f: impl Fn(u8, u8, u8) -> bool) -> usize {
    pm.pixels()
        .iter()
        .map(|p| p.demultiply())
        .filter(|p| f(p.red(), p.green(), p.blue()))
        .count()
}

/// A target far from the scene is framed and drawn; a caption and a colour bar appear; a
/// stretched spring is red and a compressed one blue; the first guess shows as a ghost.
#[test]
fn overlays_show_targets_strain_ghosts_and_captions() {
    use adflex_viz::overlay::{ColorBy, Colormap, Ghost, Marker, Overlay, Trail, Values};
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    for k in 0..4 {
        b.add_particle(Vec3::new(k as f64, 1.0, 0.0), Vec3::zeros(), 1.0);
    }
    b.add_spring(0, 1, 10.0, 0.0);
    b.add_spring(2, 3, 10.0, 0.0);
    let model = b.finalize();
    let s = model.state();
    // Spring 0 stretched by 50%, spring 1 compressed by 50%.
    s.x.assign(&[
        Vec3::new(0.0, 1.0, 0.0),
        Vec3::new(1.5, 1.0, 0.0),
        Vec3::new(2.5, 1.0, 0.0),
        Vec3::new(3.0, 1.0, 0.0),
    ]);
    let states = vec![model.state(), s];
    let opts = RenderOptions {
        width: 320,
        height: 240,
        draw_points: false,
        ..RenderOptions::default()
    };
    let plain = render::render_frame_with(&model, &states, 1, &opts, &Overlay::default()).unwrap();
    let red = |r: u8, g: u8, b: u8| r > 150 && g < 90 && b < 90;
    let blue = |r: u8, _g: u8, b: u8| b > 150 && r < 90;
    assert_eq!(count(&plain, red), 0);
    let overlay = Overlay {
        markers: vec![Marker::target(Vec3::new(1.5, 6.0, 0.0), "target")],
        color_by: Some(ColorBy::new(
            Values::EdgeStrain,
            (-0.5, 0.5),
            Colormap::Diverging,
            "strain",
        )),
        captions: vec!["iteration 0".into(), "iteration 7, loss 1.2e-9".into()],
        ..Overlay::default()
    };
    let strain_only = Overlay {
        color_by: overlay.color_by.clone(),
        ..Overlay::default()
    };
    let ps = render::render_frame_with(&model, &states, 1, &opts, &strain_only).unwrap();
    assert!(count(&ps, red) > 20, "the stretched spring is red");
    assert!(count(&ps, blue) > 20, "the compressed spring is blue");
    let pm = render::render_frame_with(&model, &states, 1, &opts, &overlay).unwrap();
    // The target, 5 m above the springs, is in the picture (the camera was fitted to it):
    // red pixels in the top third, where the plain picture has nothing.
    let red_above = |pm: &render::Pixmap| {
        let mut n = 0;
        for y in 30..80 {
            for x in 0..320 {
                let p = pm.pixel(x, y).unwrap().demultiply();
                n += red(p.red(), p.green(), p.blue()) as usize;
            }
        }
        n
    };
    assert!(red_above(&pm) > 10, "no target drawn above the scene");
    let dark = |r: u8, g: u8, b: u8| r < 60 && g < 60 && b < 60;
    let top_left = |pm: &render::Pixmap| {
        let mut n = 0;
        for y in 0..28 {
            for x in 0..200 {
                let p = pm.pixel(x, y).unwrap().demultiply();
                n += dark(p.red(), p.green(), p.blue()) as usize;
            }
        }
        n
    };
    assert!(top_left(&pm) > 100, "a caption");
    assert_eq!(top_left(&plain), 0);
    // A ghost of the first state and a trail: more non-background pixels.
    let bg = |r: u8, g: u8, b: u8| (r, g, b) == (250, 250, 247);
    let with_ghost = Overlay {
        ghosts: vec![Ghost::of(&states[0], "first guess")],
        trails: vec![Trail::of(1)],
        ..Overlay::default()
    };
    let pg = render::render_frame_with(&model, &states, 1, &opts, &with_ghost).unwrap();
    assert!(count(&pg, bg) < count(&plain, bg));
    // Asking for a state past the end is an error, not a panic.
    assert!(render::render_frame_with(&model, &states, 2, &opts, &overlay).is_err());
}

/// One camera and one ground for a whole animation: the ground drawn under a particle that
/// moves far sideways is the same in the first and last pictures where the particle is not.
#[test]
fn the_ground_stays_put_across_frames() {
    use adflex_viz::overlay::Overlay;
    let mut b = ModelBuilder::<f64>::new();
    b.gravity = Vec3::zeros();
    b.add_particle(Vec3::new(0.0, 0.2, 0.0), Vec3::new(4.0, 0.0, 0.0), 1.0);
    b.set_ground(Ground::default());
    let model = b.finalize();
    let states = rollout(&model, &model.state(), 10, 0.1);
    let opts = RenderOptions {
        width: 160,
        height: 120,
        draw_points: false,
        ..RenderOptions::default()
    };
    let none = Overlay::default();
    let first = render::render_frame_with(&model, &states, 0, &opts, &none).unwrap();
    let last = render::render_frame_with(&model, &states, 10, &opts, &none).unwrap();
    assert_eq!(first.data(), last.data());
}

//! Reading a subset of MuJoCo's MJCF.
//!
//! Read: `<include file>` (the included file's elements in its place; file names relative to the
//! main file's directory, or the current one for [`parse`]; errors name the included file and
//! line), `<compiler angle eulerseq inertiafromgeom autolimits coordinate="local" settotalmass>`
//! (and, passed over, the mesh and texture directories and the compiler's own switches), `<option
//! timestep gravity integrator density viscosity wind>` (`integrator` `Euler`, `RK4` or
//! `implicitfast`, [`ArticulationBuilder::integrator`]; a fluid: MuJoCo's inertia-box model,
//! [`super::fluid`]) with `<flag>` (`contact`, `limit`, `constraint`, `gravity`, `spring`, `damper`
//! and `actuation` switched off are off here too, `eulerdamp` switches
//! [`ArticulationBuilder::implicit_damping`] and `clampctrl` the clamping of controls; flags about
//! MuJoCo's solver, sensors or checks are passed over; others that change the default are refused),
//! `<default>` classes (nested, with `joint`, `geom`, actuator and `tendon` defaults),
//! `<worldbody>` with nested `<body pos quat|euler|axisangle|xyaxes|zaxis childclass gravcomp>`
//! (`gravcomp`: [`LinkDesc::gravcomp`](super::LinkDesc)), `<joint
//! type="hinge|slide|ball|free" pos axis range limited margin ref damping armature stiffness
//! springref>` (a spring on hinges and slides; `springref` and `ref` in the file's angle unit;
//! `ref` is the coordinate at which the body is where the file puts it, and the initial one; a
//! `margin` moves a limit that far inside the range, where MuJoCo's limit pushes back to),
//! `<freejoint>`, `<geom type="sphere|capsule|box|cylinder|ellipsoid|plane" size fromto pos quat
//! mass density contype conaffinity friction group>` (a geom outside groups 0 to 5 has no mass, as
//! MuJoCo's default `inertiagrouprange`), `type="mesh"` geoms as decoration only (passed over,
//! not in [`Mjcf::geoms`]: one that would touch, or whose mass would count because its body has
//! no `<inertial>`, is an error saying what to change), `<inertial pos quat mass
//! diaginertia|fullinertia>`,
//! `<actuator>` with `<motor>`, `<position kp kv>`, `<velocity kv>`, `<damper kv>` and `<general
//! gaintype biastype gainprm biasprm>` (`dyntype="none"`, fixed or affine gain and bias) on a joint
//! or a fixed tendon, with `gear`, `ctrlrange`, `ctrllimited`, `forcerange` and `forcelimited`:
//! each becomes an [`Actuator`] of the builder, driven by `ArticulationControl::ctrl` as MuJoCo's
//! `ctrl` (clamped unless `<flag clampctrl="disable">`). Passed over: visual-only elements
//! (`<visual>`, `<asset>`, `<statistic>`, `<site>`, `<camera>`, `<light>`), `<custom>` data,
//! `<sensor>` and `<keyframe>` (they read or set the state, not the dynamics), MuJoCo's own solver
//! settings in `<option>` (`iterations`, `solver`, `tolerance`, `cone`, `jacobian`, `impratio`).
//! `<tendon>` with `<fixed>` tendons (no limits or friction): a spring and damper with `stiffness`,
//! `damping` and `springlength` ([`TendonSpring`]), and what actuators may drive. A limit follows
//! the joint's `solreflimit` and `solimplimit` (MuJoCo's defaults `0.02 1` and `0.9 0.95 0.001`;
//! a step's time constant at least twice its `dt` unless `<flag refsafe="disable">`), as
//! [`Joint::limit_time_constant`] describes. Anything else is an error naming the element and its
//! line: MuJoCo would simulate it, and silently dropping it would simulate a different robot.
//!
//! The worldbody's first plane is the ground; its other planes (walls) and its spheres,
//! capsules, boxes and cylinders are static shapes on a massless link named `world`, fixed to
//! the world and added after the robot's links (a wall stands for its half-space as a box
//! 200 m wide whose face is the plane). Geoms that touch nothing (`contype` and
//! `conaffinity` 0, or any geom under `<flag contact="disable">`) are decoration; a worldbody
//! ellipsoid that would touch is an error (ellipsoids touch only the floor).
//!
//! `<contact>` with `<exclude body1 body2>` is read too (`<pair>` is an error).
//!
//! Geoms touch as in MuJoCo: two geoms on bodies that are neither the same, nor welded together,
//! nor parent and child after welding (MuJoCo's filterparent: unless the parent is fixed to the
//! world), nor excluded, touch when their `contype` and `conaffinity` masks match
//! ([`ContactFilter`]); a geom touches the floor, a `plane` geom of the worldbody, when its masks
//! match the plane's. Spheres, capsules and boxes touch (see [`contact`](super::contact) for how
//! exactly); a cylinder touches the floor, spheres and capsules, an ellipsoid the floor only: a
//! model in which one would touch another body's geom is refused when it is built (the error names
//! both; `<exclude>` the pair or set their masks). The law is [`GroundContact`]'s, not MuJoCo's
//! soft constraints: a stiffness that lets the robot's weight sink one contact by 5 mm, half the
//! critical damping of a quarter of its mass, and MuJoCo's friction: a contact's is the larger of
//! its two geoms' sliding `friction` (the plane's against the floor; 1 by default), as MuJoCo
//! combines geoms of equal `priority` (`priority` is refused). Set `builder.ground` to tune the
//! law. Without a plane there is no floor (`ground_filter` [`ContactFilter::NONE`]; set
//! `builder.ground_filter` too when you add one) but geoms still touch each other; set
//! `builder.link_contact = false` to keep only the floor. The torsional and rolling frictions are
//! passed over, and so is `condim`: every contact has sliding friction (MuJoCo's `condim="1"`
//! contacts have none).
//!
//! Where MuJoCo reads an attribute in a way of its own, so does this reader: `limited` and
//! `ctrllimited` default to `"auto"`, which limits only a range with lower < upper (`range="0
//! 0"` leaves a joint free); a box from `fromto` has a square cross-section of half-side
//! `size[0]`; a class's actuator defaults (`<motor>`, `<position>`, ...) are one default;
//! `zaxis="0 0 -1"` is half a turn about x; an element's own orientation overrides any its
//! class gives. Refused: `fullinertia` with an orientation (MuJoCo reads it in the body's
//! frame), a gear with more than its first component, and an actuator on a ball or free
//! joint.
//!
//! Angles are in degrees unless `<compiler angle="radian">` (MuJoCo's default). A body
//! without `<inertial>` gets its mass properties from its geoms (density 1000 by default),
//! as MuJoCo's `inertiafromgeom="auto"`. Several joints in one body become a chain of
//! massless links, in order, each moving about its own `pos`.
//!
//! ```
//! use adflex_kernels::articulation::mjcf;
//! let xml = r#"<mujoco model="pendulum">
//!   <compiler angle="radian"/>
//!   <worldbody>
//!     <body name="pole" pos="0 0 1">
//!       <joint name="hinge" type="hinge" axis="0 1 0" range="-1 1"/>
//!       <geom type="capsule" fromto="0 0 0 0 0 -0.5" size="0.02"/>
//!     </body>
//!   </worldbody>
//!   <actuator><motor joint="hinge" gear="2"/></actuator>
//! </mujoco>"#;
//! let robot = mjcf::parse(xml).unwrap();
//! assert_eq!(robot.builder.actuators().len(), 1);
//! let model = robot.builder.finalize::<f64>().unwrap();
//! assert_eq!(model.n_dof, 1);
//!
//! let err = mjcf::parse(&xml.replace("hinge\" axis", "screw\" axis")).unwrap_err();
//! assert_eq!(err.line, Some(5));
//! assert!(err.to_string().contains("screw"), "{err}");
//! ```

use std::collections::HashMap;
use std::f64::consts::PI;
use std::path::Path;

use adflex_runtime::{Mat33, Quat, Vec3};
use roxmltree::Node;

use super::actuator::{Actuator, TendonSpring};
use super::build::{check_inertial, check_mass};
pub use super::contact::GeomShape;
use super::contact::{ContactFilter, GroundContact};
use super::fluid::Fluid;
use super::model::{
    axis_angle, from_to, ArticulationBuilder, ArticulationError, ArticulationIntegrator, Inertial,
    Joint, LinkId, Pose,
};
use super::xml::{self, children, Source};

/// A robot read from MJCF: the builder, its actuators and geometry.
#[derive(Clone, Debug)]
pub struct Mjcf {
    /// The links and joints (set gravity or add more, then finalize).
    pub builder: ArticulationBuilder,
    /// `<option timestep>`, if given (s).
    pub timestep: Option<f64>,
    /// The geoms: on links, and the world's (planes are the ground).
    pub geoms: Vec<Geom>,
}

/// A geom: its shape, where it is and whose it is.
#[derive(Clone, Debug, PartialEq)]
pub struct Geom {
    /// Name (empty if none).
    pub name: String,
    /// The link it is on (`None`: the world).
    pub link: Option<LinkId>,
    /// Its frame in the link's frame (or the world's).
    pub pose: Pose,
    /// Its shape.
    pub shape: GeomShape,
    /// Sliding friction coefficient.
    pub friction: f64,
}

/// Reads the MJCF file at `path`.
pub fn load(path: impl AsRef<Path>) -> Result<Mjcf, ArticulationError> {
    let path = path.as_ref();
    let text = xml::read(path)?;
    let dir = path.parent().unwrap_or(Path::new(""));
    parse_named(&text, Some(&path.display().to_string()), dir)
}

/// Reads MJCF text; an `<include file>` is relative to the current directory.
pub fn parse(text: &str) -> Result<Mjcf, ArticulationError> {
    parse_named(text, None, Path::new(""))
}

/// Attribute defaults of one class, per element tag.
type Class = HashMap<String, HashMap<String, String>>;

struct Reader<'a> {
    src: Source<'a>,
    radians: bool,
    eulerseq: Vec<(usize, bool)>,
    from_geoms: Option<bool>,
    classes: HashMap<String, Class>,
    builder: ArticulationBuilder,
    geoms: Vec<Geom>,
    joints: HashMap<String, ()>,
    /// The bodies' names so far (MuJoCo refuses a repeated one).
    bodies: HashMap<String, ()>,
    /// Each moving body's link and its parent body's link, for MuJoCo's filterparent.
    parents: Vec<(LinkId, LinkId)>,
    /// `<flag contact="disable">` (or `constraint`): no contact at all.
    no_contact: bool,
    /// `<flag limit="disable">` (or `constraint`): joint ranges limit nothing.
    no_limits: bool,
    /// `<flag spring="disable">`, `damper`, `actuation`: those forces are off (and with both
    /// springs and dampers off, the fluid, as MuJoCo's passive forces).
    no_spring: bool,
    no_damper: bool,
    no_actuation: bool,
    /// The worldbody's geoms that touch, other than planes.
    world_shapes: Vec<(Geom, ContactFilter)>,
    /// `<compiler settotalmass>`, when positive.
    total_mass: Option<f64>,
    /// `<flag clampctrl>` (on by default): controls are clamped to their `ctrlrange`.
    clamp_ctrl: bool,
    /// The named fixed tendons: their joints' links and coefficients.
    tendons: HashMap<String, Vec<(LinkId, f64)>>,
}

const SKIPPED: &[&str] = &[
    "visual",
    "asset",
    "statistic",
    "size",
    "extension",
    "custom",
    // Sensors read the state and keyframes are states a caller may reset to: neither changes
    // the dynamics.
    "sensor",
    "keyframe",
];
const BODY_SKIPPED: &[&str] = &["site", "camera", "light"];

/// The attributes of a `<joint>` read (or passed over, as said where they are read).
const JOINT_ATTRS: &[&str] = &[
    "name",
    "type",
    "pos",
    "axis",
    "range",
    "limited",
    "damping",
    "armature",
    "class",
    "stiffness",
    "springref",
    "ref",
    "frictionloss",
    "group",
    "margin",
    // A limit's time constant, damping ratio and impedance (read below); friction loss's
    // (refused anyway).
    "solreflimit",
    "solimplimit",
    "solreffriction",
    "solimpfriction",
];

/// The attributes of a `<geom>` read (or passed over).
const GEOM_ATTRS: &[&str] = &[
    "name",
    "type",
    "size",
    "fromto",
    "pos",
    "quat",
    "euler",
    "axisangle",
    "xyaxes",
    "zaxis",
    "mass",
    "density",
    "class",
    "rgba",
    "material",
    "friction",
    "contype",
    "conaffinity",
    "condim",
    "group",
    "solref",
    "solimp",
    "margin",
    "user",
    // The asset a mesh geom draws (mesh geoms are decoration, see `Reader::decoration_mesh`).
    "mesh",
];

/// The actuator elements read: MuJoCo's general actuator and its shortcuts without
/// activation dynamics.
const ACTUATOR_TAGS: &[&str] = &["motor", "position", "velocity", "damper", "general"];

/// The attributes of an actuator element read.
const ACTUATOR_ATTRS: &[&str] = &[
    "name",
    "joint",
    "tendon",
    "gear",
    "ctrlrange",
    "ctrllimited",
    "forcerange",
    "forcelimited",
    "kp",
    "kv",
    "gainprm",
    "biasprm",
    "gaintype",
    "biastype",
    "dyntype",
    "dynprm",
    "class",
    "group",
];

/// Half the side of the box that stands for a plane other than the ground (m): the plane's
/// half-space within this distance.
const WALL: f64 = 100.0;

/// The attributes that give a frame's orientation, with how many numbers each takes.
const ORIENTATIONS: [(&str, usize); 5] = [
    ("quat", 4),
    ("euler", 3),
    ("axisangle", 4),
    ("xyaxes", 6),
    ("zaxis", 3),
];

/// Where a `<default>` keeps an element's attributes: MuJoCo's actuator elements all write
/// one actuator default, so a class's `<motor gear>` also applies to a `<position>`.
fn defaults_of(tag: &str) -> &str {
    match tag {
        t if ACTUATOR_TAGS.contains(&t) => "actuator",
        "fixed" | "spatial" => "tendon",
        other => other,
    }
}

fn parse_named(text: &str, file: Option<&str>, dir: &Path) -> Result<Mjcf, ArticulationError> {
    // MuJoCo's `<include>`: the included files' elements in its place.
    let (text, lines) = xml::splice_includes(text, file, dir)?;
    let doc = xml::parse(&text, file)?;
    let mut r = Reader {
        src: Source {
            file: file.map(str::to_string),
            doc: &doc,
            lines: Some(&lines),
        },
        radians: false,
        eulerseq: vec![(0, true), (1, true), (2, true)],
        from_geoms: None,
        classes: HashMap::new(),
        builder: ArticulationBuilder::new(),
        geoms: Vec::new(),
        joints: HashMap::new(),
        bodies: HashMap::new(),
        parents: Vec::new(),
        no_contact: false,
        no_limits: false,
        no_spring: false,
        no_damper: false,
        no_actuation: false,
        world_shapes: Vec::new(),
        total_mass: None,
        clamp_ctrl: true,
        tendons: HashMap::new(),
    };
    let root = doc.root_element();
    if root.tag_name().name() != "mujoco" {
        return Err(r
            .src
            .error(root, "the root element of an MJCF file must be <mujoco>"));
    }
    r.src.only_attributes(root, &["model"])?;
    let items = children(
        &r.src,
        root,
        &[
            "compiler",
            "option",
            "default",
            "worldbody",
            "actuator",
            "contact",
            "tendon",
        ],
        SKIPPED,
    )?;
    let mut timestep = None;
    // Settings first: they apply to the whole file wherever they are.
    for n in &items {
        match n.tag_name().name() {
            "compiler" => r.compiler(*n)?,
            "option" => {
                // MuJoCo's inertia-box fluid model, on when density or viscosity is.
                let density = r.src.number(*n, "density")?.unwrap_or(0.0);
                let viscosity = r.src.number(*n, "viscosity")?.unwrap_or(0.0);
                let wind = r.src.vec3(*n, "wind")?.unwrap_or_else(Vec3::zeros);
                if density < 0.0 || viscosity < 0.0 {
                    return Err(r
                        .src
                        .error(*n, "density and viscosity must be non-negative"));
                }
                if density > 0.0 || viscosity > 0.0 {
                    r.builder.fluid = Some(Fluid {
                        density,
                        viscosity,
                        wind,
                    });
                }
                // MuJoCo's own solver's settings name no property of the model: contacts
                // follow the library's law.
                r.src.only_attributes(
                    *n,
                    &[
                        "timestep",
                        "gravity",
                        "integrator",
                        "iterations",
                        "ls_iterations",
                        "solver",
                        "tolerance",
                        "ls_tolerance",
                        "cone",
                        "jacobian",
                        "noslip_iterations",
                        "noslip_tolerance",
                        "impratio",
                        "density",
                        "viscosity",
                        "wind",
                        "collision",
                    ],
                )?;
                // A later <option> without these attributes keeps what an earlier one set.
                if let Some(t) = r.src.number(*n, "timestep")? {
                    timestep = Some(t);
                }
                r.builder.integrator = match n.attribute("integrator") {
                    None => r.builder.integrator,
                    Some("Euler") => ArticulationIntegrator::Euler,
                    Some("RK4") => ArticulationIntegrator::Rk4,
                    Some("implicitfast") => ArticulationIntegrator::ImplicitFast,
                    Some(o) => {
                        let why = match o {
                            "implicit" => {
                                " (MuJoCo's implicit adds the Coriolis forces' velocity \
                                 derivative to implicitfast's, which adflex does not compute)"
                            }
                            _ => "",
                        };
                        return Err(r.src.error(
                            *n,
                            format!(
                                "integrator=\"{o}\": Euler, RK4 and implicitfast are \
                                 supported{why}"
                            ),
                        ));
                    }
                };
                match n.attribute("collision") {
                    None | Some("all") => {}
                    Some(o) => {
                        return Err(r
                            .src
                            .error(*n, format!("collision=\"{o}\": only \"all\" is supported")))
                    }
                }
                if let Some(g) = r.src.vec3(*n, "gravity")? {
                    r.builder.gravity = g;
                }
                for f in children(&r.src, *n, &["flag"], &[])? {
                    r.flags(f)?;
                }
            }
            "default" => r.default(*n, None)?,
            _ => {}
        }
    }
    for n in items.iter().filter(|n| n.has_tag_name("worldbody")) {
        r.worldbody(*n)?;
    }
    // Fixed tendons: a spring and damper when they have stiffness or damping (the couplings
    // gym's humanoid declares have neither), and what actuators may drive.
    for n in items.iter().filter(|n| n.has_tag_name("tendon")) {
        r.src.only_attributes(*n, &[])?;
        for t in children(&r.src, *n, &["fixed"], &[])? {
            const HARMLESS: [&str; 9] = [
                "name",
                "class",
                "group",
                "rgba",
                "width",
                "material",
                "stiffness",
                "damping",
                "springlength",
            ];
            r.src.only_attributes(t, &HARMLESS).map_err(|mut e| {
                e.message += " (a tendon with limits or friction is not supported)";
                e
            })?;
            r.check_class(t)?;
            let class = t.attribute("class").unwrap_or("main");
            if let Some(d) = r.classes.get(class).and_then(|c| c.get("tendon")) {
                if let Some(k) = d.keys().find(|k| !HARMLESS.contains(&k.as_str())) {
                    return Err(r.src.error(
                        t,
                        format!(
                            "its class \"{class}\" gives tendons `{k}`: a tendon with limits \
                             or friction is not supported"
                        ),
                    ));
                }
            }
            let mut joints = Vec::new();
            for j in children(&r.src, t, &["joint"], &[])? {
                r.src.only_attributes(j, &["joint", "coef"])?;
                let name = r.src.required(j, "joint")?;
                let Some(link) = r.joint_link(name) else {
                    return Err(r.src.error(j, format!("joint \"{name}\" is not defined")));
                };
                let coef = r.src.number(j, "coef")?.unwrap_or(1.0);
                joints.push((link, coef));
            }
            r.tendon_spring(t, class, &joints)?;
            if let Some(name) = t.attribute("name") {
                r.tendons.insert(name.to_string(), joints);
            }
        }
    }
    for n in items.iter().filter(|n| n.has_tag_name("actuator")) {
        for a in children(&r.src, *n, ACTUATOR_TAGS, &[])? {
            r.actuator(a)?;
        }
    }
    // The worldbody's shapes on a massless link fixed to the world, after the robots' links
    // (so that these keep their indices), touched by the bodies as in MuJoCo.
    if !r.world_shapes.is_empty() {
        let world = r.builder.add_link(
            "world",
            None,
            Joint::fixed().name("world_weld"),
            Inertial::massless(),
        );
        for (g, filter) in std::mem::take(&mut r.world_shapes) {
            if let Some(k) = r.builder.add_contact_shape(world, &g.pose, &g.shape) {
                r.builder.set_contact_filter(k, filter);
                r.builder.set_contact_friction(k, g.friction);
            }
        }
    }
    if let Some(total) = r.total_mass {
        let links = r.builder.links_mut();
        let sum: f64 = links.iter().map(|l| l.inertial.mass).sum();
        if sum > 0.0 {
            for l in links {
                l.inertial.mass *= total / sum;
                l.inertial.inertia *= total / sum;
            }
        }
    }
    r.filter_parents();
    for n in items.iter().filter(|n| n.has_tag_name("contact")) {
        r.src.only_attributes(*n, &[])?;
        for e in children(&r.src, *n, &["exclude"], &[])? {
            r.src.only_attributes(e, &["name", "body1", "body2"])?;
            let body = |k: &str| match e.attribute(k) {
                None => Err(r.src.error(e, format!("<exclude> needs `{k}`"))),
                // MuJoCo's would cover the floor too, which is the ground's law here.
                Some("world") => Err(r.src.error(e, "excluding the world is not supported")),
                Some(b) => r
                    .builder
                    .find(b)
                    .ok_or_else(|| r.src.error(e, format!("{k}=\"{b}\" names no body"))),
            };
            let (a, b) = (body("body1")?, body("body2")?);
            r.builder.exclude_contact(a, b);
        }
    }
    // The ground's stiffness from the robot's weight (5 mm sag on one contact), damped at half
    // the critical rate of a quarter of the mass: MuJoCo's contacts are soft constraints with
    // a time constant, not springs, so a fixed stiffness would suit only one size of robot.
    // Geoms touch each other as in MuJoCo; without a plane there is no floor, but the
    // ground's law serves the links' contacts.
    if r.builder.ground.is_none() && !r.builder.contact_shapes().is_empty() {
        r.builder.ground = Some(GroundContact::default());
        r.builder.ground_filter = ContactFilter::NONE;
    }
    r.builder.link_contact = r.builder.ground.is_some();
    if r.no_contact {
        (r.builder.ground, r.builder.link_contact) = (None, false);
    }
    r.switch_off_forces();
    let mass: f64 = r.builder.links().iter().map(|l| l.inertial.mass).sum();
    let weight = mass * r.builder.gravity.norm().max(1.0);
    if let (Some(g), true) = (r.builder.ground.as_mut(), mass > 0.0) {
        g.ke = weight / 0.005;
        g.kd = 0.5 * (g.ke * mass).sqrt();
    }
    Ok(Mjcf {
        builder: r.builder,
        timestep,
        geoms: r.geoms,
    })
}

impl<'a> Reader<'a> {
    fn compiler(&mut self, n: Node) -> Result<(), ArticulationError> {
        self.src.only_attributes(
            n,
            &[
                "angle",
                "eulerseq",
                "inertiafromgeom",
                "autolimits",
                "coordinate",
                "settotalmass",
                // Where meshes and textures are, and how the compiler runs: nothing simulated
                // here depends on them (mesh geoms are decoration, or refused).
                "meshdir",
                "texturedir",
                "assetdir",
                "discardvisual",
                "strippath",
                "usethread",
                "exactmeshinertia",
                "fitaabb",
                "saveinertial",
            ],
        )?;
        if let Some(m) = self.src.number(n, "settotalmass")? {
            // MuJoCo: a positive value scales every body's mass and inertia to that total.
            self.total_mass = (m > 0.0).then_some(m);
        }
        children(&self.src, n, &[], &[])?;
        match n.attribute("coordinate") {
            None | Some("local") => {}
            Some(o) => {
                return Err(self.src.error(
                    n,
                    format!("coordinate=\"{o}\": only local coordinates are supported"),
                ))
            }
        }
        match n.attribute("angle") {
            None | Some("degree") => self.radians = false,
            Some("radian") => self.radians = true,
            Some(o) => {
                return Err(self
                    .src
                    .error(n, format!("angle=\"{o}\": use \"degree\" or \"radian\"")))
            }
        }
        if let Some(seq) = n.attribute("eulerseq") {
            let parsed: Option<Vec<(usize, bool)>> = seq
                .chars()
                .map(|c| {
                    let axis = "xyz".find(c.to_ascii_lowercase())?;
                    Some((axis, c.is_ascii_lowercase()))
                })
                .collect();
            match parsed {
                Some(p) if p.len() == 3 => self.eulerseq = p,
                _ => {
                    return Err(self
                        .src
                        .error(n, format!("eulerseq=\"{seq}\": three of x, y, z, X, Y, Z")))
                }
            }
        }
        match n.attribute("inertiafromgeom") {
            None | Some("auto") => self.from_geoms = None,
            Some("true") => self.from_geoms = Some(true),
            Some("false") => self.from_geoms = Some(false),
            Some(o) => {
                return Err(self.src.error(
                    n,
                    format!("inertiafromgeom=\"{o}\": use auto, true or false"),
                ))
            }
        }
        match n.attribute("autolimits") {
            None | Some("true") => Ok(()),
            Some(o) => Err(self.src.error(
                n,
                format!("autolimits=\"{o}\" is not supported (limits follow `range`)"),
            )),
        }
    }

    /// The forces `<flag>` switched off, on the model read: MuJoCo's `spring` (joint and tendon
    /// springs), `damper` (joint and tendon damping) and, with both, the fluid and gravity
    /// compensation (MuJoCo's other passive forces); `actuation` (the actuators' gains and
    /// biases become 0 and their force ranges go: their controls remain, exerting nothing, as
    /// MuJoCo's).
    fn switch_off_forces(&mut self) {
        let (spring, damper) = (self.no_spring, self.no_damper);
        for l in self.builder.links_mut() {
            if spring {
                l.joint.stiffness = 0.0;
            }
            if damper {
                l.joint.damping = 0.0;
            }
        }
        for t in self.builder.tendon_springs_mut() {
            if spring {
                t.stiffness = 0.0;
            }
            if damper {
                t.damping = 0.0;
            }
        }
        if spring && damper {
            self.builder.fluid = None;
            for l in self.builder.links_mut() {
                l.gravcomp = 0.0;
            }
        }
        if self.no_actuation {
            for a in self.builder.actuators_mut() {
                (a.gain, a.bias, a.force_range) = ([0.0; 3], [0.0; 3], None);
            }
        }
    }

    /// `<option><flag>`: the switches that change this model's dynamics are applied
    /// (`contact`, `limit`, `constraint`, `gravity`, `spring`, `damper`, `actuation`,
    /// `eulerdamp`, `clampctrl`, `refsafe`); those about MuJoCo's own solver, sensors or checks
    /// are passed over; the rest are refused when they change the default.
    fn flags(&mut self, n: Node) -> Result<(), ArticulationError> {
        // MuJoCo's defaults: these flags start enabled, every other one disabled.
        const ENABLED: &[&str] = &[
            "constraint",
            "equality",
            "frictionloss",
            "limit",
            "contact",
            "spring",
            "damper",
            "gravity",
            "clampctrl",
            "warmstart",
            "filterparent",
            "actuation",
            "refsafe",
            "sensor",
            "midphase",
            "eulerdamp",
            "autoreset",
            "nativeccd",
            "island",
        ];
        // No effect on the dynamics simulated here (no equality or friction-loss constraint is
        // read; MuJoCo's solver, sensors and checks are its own).
        const NO_EFFECT: &[&str] = &[
            "equality",
            "frictionloss",
            "warmstart",
            "sensor",
            "midphase",
            "autoreset",
            "nativeccd",
            "island",
            "energy",
            "fwdinv",
            "invdiscrete",
            "multiccd",
            "sleep",
        ];
        for a in n.attributes() {
            let (name, value) = (a.name(), a.value());
            let enabled = match value {
                "enable" => true,
                "disable" => false,
                o => {
                    return Err(self
                        .src
                        .error(n, format!("{name}=\"{o}\": use \"enable\" or \"disable\"")))
                }
            };
            match (name, enabled) {
                ("contact", false) => self.no_contact = true,
                ("limit", false) => self.no_limits = true,
                ("constraint", false) => (self.no_contact, self.no_limits) = (true, true),
                ("gravity", false) => self.builder.gravity = Vec3::zeros(),
                ("refsafe", e) => self.builder.limit_refsafe = e,
                ("eulerdamp", e) => self.builder.implicit_damping = e,
                ("clampctrl", e) => self.clamp_ctrl = e,
                ("spring", e) => self.no_spring = !e,
                ("damper", e) => self.no_damper = !e,
                ("actuation", e) => self.no_actuation = !e,
                ("sleep", true) => {
                    return Err(self.src.error(n, "sleep=\"enable\" is not supported"))
                }
                (f, _) if NO_EFFECT.contains(&f) => {}
                (f, true) if ENABLED.contains(&f) => {}
                ("override", false) => {}
                (f, _) if !ENABLED.contains(&f) && f != "override" => {
                    return Err(self.src.error(n, format!("flag `{f}` is not supported")))
                }
                (f, e) => {
                    return Err(self.src.error(
                        n,
                        format!(
                            "{f}=\"{}\" is not supported (MuJoCo's default is {})",
                            if e { "enable" } else { "disable" },
                            if e { "disable" } else { "enable" }
                        ),
                    ))
                }
            }
        }
        Ok(())
    }

    fn default(&mut self, n: Node, parent: Option<&str>) -> Result<(), ArticulationError> {
        self.src.only_attributes(n, &["class"])?;
        let name = match (n.attribute("class"), parent) {
            (Some(c), _) => c.to_string(),
            (None, None) => "main".to_string(),
            (None, Some(_)) => return Err(self.src.error(n, "a nested <default> needs a `class`")),
        };
        let mut class = parent
            .and_then(|p| self.classes.get(p).cloned())
            .unwrap_or_default();
        let tags: Vec<&str> = ["default", "joint", "geom", "tendon"]
            .into_iter()
            .chain(ACTUATOR_TAGS.iter().copied())
            .collect();
        let kids = children(
            &self.src,
            n,
            &tags,
            &["site", "camera", "light", "mesh", "material"],
        )?;
        for k in kids.iter().filter(|k| k.tag_name().name() != "default") {
            // A class's attributes are checked as an element's: one the reader does not know
            // would be lost on every element of the class.
            match k.tag_name().name() {
                "joint" => self.src.only_attributes(*k, JOINT_ATTRS)?,
                "geom" => self.src.only_attributes(*k, GEOM_ATTRS)?,
                t if ACTUATOR_TAGS.contains(&t) => self.src.only_attributes(*k, ACTUATOR_ATTRS)?,
                _ => {}
            }
            let entry = class
                .entry(defaults_of(k.tag_name().name()).to_string())
                .or_default();
            for a in k.attributes() {
                entry.insert(a.name().to_string(), a.value().to_string());
            }
        }
        self.classes.insert(name.clone(), class);
        for k in kids.iter().filter(|k| k.tag_name().name() == "default") {
            self.default(*k, Some(&name))?;
        }
        Ok(())
    }

    /// Refuses a `class` attribute naming no `<default>` class (its defaults would be lost).
    fn check_class(&self, n: Node) -> Result<(), ArticulationError> {
        match n.attribute("class") {
            Some(a) if !self.classes.contains_key(a) => {
                Err(self.src.error(n, format!("class \"{a}\" is not defined")))
            }
            _ => Ok(()),
        }
    }

    /// The value of attribute `name` of `n`: its own, or its class's default.
    fn attr<'n>(&'n self, n: Node<'n, 'n>, class: &str, name: &str) -> Option<&'n str> {
        if let Some(v) = n.attribute(name) {
            return Some(v);
        }
        let class = n.attribute("class").unwrap_or(class);
        self.classes
            .get(class)
            .and_then(|c| c.get(defaults_of(n.tag_name().name())))
            .and_then(|m| m.get(name))
            .map(String::as_str)
    }

    /// Numbers from an attribute (own or default), checked.
    fn nums(
        &self,
        n: Node,
        class: &str,
        name: &str,
        counts: &[usize],
    ) -> Result<Option<Vec<f64>>, ArticulationError> {
        let Some(text) = self.attr(n, class, name) else {
            return Ok(None);
        };
        let v: Vec<f64> = text
            .split_whitespace()
            .map(|t| t.parse::<f64>().ok().filter(|x| x.is_finite()))
            .collect::<Option<Vec<_>>>()
            .ok_or_else(|| {
                self.src.error(
                    n,
                    format!(
                        "attribute `{name}=\"{text}\"` has a value that is not a finite number"
                    ),
                )
            })?;
        if !counts.contains(&v.len()) {
            return Err(self.src.error(
                n,
                format!(
                    "attribute `{name}=\"{text}\"` needs {} numbers, has {}",
                    counts
                        .iter()
                        .map(|c| c.to_string())
                        .collect::<Vec<_>>()
                        .join(" or "),
                    v.len()
                ),
            ));
        }
        Ok(Some(v))
    }

    fn angle(&self, x: f64) -> f64 {
        if self.radians {
            x
        } else {
            x * PI / 180.0
        }
    }

    /// The orientation of a frame element (`quat`, `euler`, `axisangle`, `xyaxes`, `zaxis`).
    fn orientation(&self, n: Node, class: &str) -> Result<Quat<f64>, ArticulationError> {
        let given: Vec<&str> = ORIENTATIONS
            .into_iter()
            .map(|(a, _)| a)
            .filter(|a| n.attribute(*a).is_some())
            .collect();
        if given.len() > 1 {
            return Err(self.src.error(
                n,
                format!("gives its orientation twice ({})", given.join(", ")),
            ));
        }
        let axis_angle = |a: Vec3<f64>, t: f64| axis_angle(&a.normalize(), t);
        // The element's own orientation, if it gives one, overrides every default: a class's
        // `quat` does not override an element's `euler`.
        let read = |a: &str| -> Result<Option<Vec<f64>>, ArticulationError> {
            if given.is_empty() || given.contains(&a) {
                let count = ORIENTATIONS.iter().find(|o| o.0 == a).map_or(0, |o| o.1);
                self.nums(n, class, a, &[count])
            } else {
                Ok(None)
            }
        };
        if let Some(q) = read("quat")? {
            let q = Quat::new(q[0], q[1], q[2], q[3]);
            if q.norm() < 1e-12 {
                return Err(self.src.error(n, "quat has norm 0"));
            }
            return Ok(q.normalize());
        }
        if let Some(e) = read("euler")? {
            let mut q = Quat::identity();
            for (k, &(axis, intrinsic)) in self.eulerseq.iter().enumerate() {
                let r = axis_angle(Vec3::ith(axis, 1.0), self.angle(e[k]));
                q = if intrinsic { q * r } else { r * q };
            }
            return Ok(q);
        }
        if let Some(a) = read("axisangle")? {
            let axis = Vec3::new(a[0], a[1], a[2]);
            if axis.norm() < 1e-12 {
                return Err(self.src.error(n, "axisangle has a zero axis"));
            }
            return Ok(axis_angle(axis, self.angle(a[3])));
        }
        if let Some(a) = read("zaxis")? {
            let z = Vec3::new(a[0], a[1], a[2]);
            if z.norm() < 1e-12 {
                return Err(self.src.error(n, "zaxis is zero"));
            }
            return Ok(from_to(&Vec3::z(), &z.normalize()));
        }
        if let Some(a) = read("xyaxes")? {
            let x = Vec3::new(a[0], a[1], a[2]);
            let y0 = Vec3::new(a[3], a[4], a[5]);
            let y = y0 - x * (x.dot(&y0) / x.norm_squared().max(1e-300));
            let z = x.cross(&y);
            if x.norm() < 1e-12 || z.norm() < 1e-12 {
                return Err(self.src.error(n, "xyaxes are zero or parallel"));
            }
            let m = Mat33::from_columns(&[x.normalize(), y.normalize(), z.normalize()]);
            let r = nalgebra::Rotation3::from_matrix_unchecked(m);
            return Ok(*nalgebra::UnitQuaternion::from_rotation_matrix(&r).quaternion());
        }
        Ok(Quat::identity())
    }

    fn worldbody(&mut self, n: Node) -> Result<(), ArticulationError> {
        self.src.only_attributes(n, &["childclass"])?;
        let class = n.attribute("childclass").unwrap_or("main").to_string();
        for c in children(&self.src, n, &["body", "geom"], BODY_SKIPPED)? {
            match c.tag_name().name() {
                "body" => self.body(c, None, Vec3::zeros(), &class)?,
                _ => {
                    if self.decoration_mesh(c, &class, false)? {
                        continue;
                    }
                    let (g, _) = self.geom(c, &class, None)?;
                    let filter = self.filter(c, &class)?;
                    if g.shape == GeomShape::Plane && filter == ContactFilter::NONE {
                        // A plane that touches nothing (decoration).
                    } else if g.shape == GeomShape::Plane && self.builder.ground.is_some() {
                        // A wall: its half-space as a box whose face is the plane.
                        let pose = g.pose.compose(&Pose::at(Vec3::new(0.0, 0.0, -WALL)));
                        let shape = GeomShape::Box(Vec3::new(WALL, WALL, WALL));
                        self.world_shapes.push((
                            Geom {
                                pose,
                                shape,
                                ..g.clone()
                            },
                            filter,
                        ));
                    } else if g.shape == GeomShape::Plane {
                        let normal = g.pose.transform_vector(&Vec3::z());
                        self.builder.ground = Some(GroundContact {
                            normal,
                            offset: normal.dot(&g.pose.pos),
                            mu: g.friction,
                            ..GroundContact::default()
                        });
                        self.builder.ground_filter = filter;
                    } else if filter != ContactFilter::NONE && !self.no_contact {
                        if matches!(g.shape, GeomShape::Ellipsoid(..)) {
                            return Err(self.src.error(
                                c,
                                "an ellipsoid of the worldbody that touches is not supported \
                                 (ellipsoids touch only the floor); set contype and \
                                 conaffinity to 0, or use a sphere, capsule, box or cylinder",
                            ));
                        }
                        // A static shape (a wall, a rail), added once the bodies are.
                        self.world_shapes.push((g.clone(), filter));
                    }
                    self.geoms.push(g);
                }
            }
        }
        Ok(())
    }

    /// Reads `<body>` `n`, whose parent's link is `parent` with its frame at `offset` in the
    /// parent body's frame.
    fn body(
        &mut self,
        n: Node,
        parent: Option<LinkId>,
        offset: Vec3<f64>,
        class: &str,
    ) -> Result<(), ArticulationError> {
        self.src.only_attributes(
            n,
            &[
                "name",
                "pos",
                "quat",
                "euler",
                "axisangle",
                "xyaxes",
                "zaxis",
                "childclass",
                "gravcomp",
            ],
        )?;
        // MuJoCo's gravity compensation, a fraction of the body's weight (a passive force).
        let gravcomp = self.src.number(n, "gravcomp")?.unwrap_or(0.0);
        if let Some(c) = n.attribute("childclass") {
            if !self.classes.contains_key(c) {
                return Err(self
                    .src
                    .error(n, format!("childclass \"{c}\" is not defined")));
            }
        }
        let class = n.attribute("childclass").unwrap_or(class).to_string();
        if let Some(name) = n.attribute("name") {
            if self.bodies.insert(name.to_string(), ()).is_some() {
                return Err(self.src.error(n, "a second body with this name"));
            }
        }
        let name = n
            .attribute("name")
            .map(str::to_string)
            .unwrap_or_else(|| format!("body{}", self.builder.links().len()));
        let pos = self.src.vec3(n, "pos")?.unwrap_or_else(Vec3::zeros);
        let rot = self.orientation(n, &class)?;
        let body_pose = Pose::new(pos - offset, rot);
        let kids = children(
            &self.src,
            n,
            &["body", "joint", "freejoint", "geom", "inertial"],
            BODY_SKIPPED,
        )?;
        // Joints, in order.
        let mut joints = Vec::new();
        for j in kids
            .iter()
            .filter(|k| matches!(k.tag_name().name(), "joint" | "freejoint"))
        {
            joints.push((*j, self.joint(*j, &class)?));
        }
        if joints
            .iter()
            .any(|(_, (j, _))| j.kind == super::JointType::Free)
            && (joints.len() > 1 || parent.is_some())
        {
            let node = joints[0].0;
            return Err(self.src.error(
                node,
                "a free joint must be the only joint of a body of the worldbody",
            ));
        }
        // Mass properties in the body frame.
        let inertial_node = kids.iter().find(|k| k.has_tag_name("inertial"));
        let use_geoms = match self.from_geoms {
            Some(b) => b,
            None => inertial_node.is_none(),
        };
        let mut geoms = Vec::new();
        let mut from_geoms = Inertial::massless();
        for g in kids.iter().filter(|k| k.has_tag_name("geom")) {
            if self.decoration_mesh(*g, &class, use_geoms)? {
                continue;
            }
            let (geom, inertial) = self.geom(*g, &class, Some(LinkId(0)))?;
            if let Some(i) = inertial {
                from_geoms = from_geoms.combine(&i);
            }
            let filter = self.filter(*g, &class)?;
            geoms.push((geom, filter));
        }
        let inertial = if use_geoms {
            from_geoms
        } else if let Some(i) = inertial_node {
            self.inertial(*i)?
        } else {
            Inertial::massless()
        };
        // One link per joint (massless but the last), each frame at its joint's `pos`.
        let mut link = parent;
        let mut at = Vec3::zeros();
        if joints.is_empty() {
            let id = self.builder.add_link(
                name.clone(),
                link,
                Joint::fixed()
                    .name(format!("{name}_weld"))
                    .origin(body_pose),
                inertial,
            );
            link = Some(id);
        }
        let count = joints.len();
        for (k, (_, (mut joint, jpos))) in joints.into_iter().enumerate() {
            if joint.kind == super::JointType::Free {
                // MuJoCo's free joint: q is the body's pose in the world; the body's `pos` and
                // orientation are its initial value.
                let r = rot.normalize();
                joint.initial = vec![pos.x, pos.y, pos.z, r.i, r.j, r.k, r.w];
                link = Some(self.builder.add_link(name.clone(), None, joint, inertial));
                continue;
            }
            let origin = if k == 0 {
                Pose::new(body_pose.transform_point(&jpos), rot)
            } else {
                Pose::at(jpos - at)
            };
            // A joint with a `ref` places the body at q = ref: the joint's frame is moved by
            // -ref along (about) its axis, which the axis does not change.
            let origin = match (joint.kind, joint.initial.as_slice()) {
                (super::JointType::Revolute, &[r]) => origin.compose(&Pose::new(
                    Vec3::zeros(),
                    axis_angle(&joint.axis.normalize(), -r),
                )),
                (super::JointType::Prismatic, &[r]) => {
                    origin.compose(&Pose::at(-joint.axis.normalize() * r))
                }
                _ => origin,
            };
            at = jpos;
            let last = k + 1 == count;
            let link_name = if last {
                name.clone()
            } else {
                format!("{name}:{}", joint.name)
            };
            let mass = if last {
                inertial.transformed(&Pose::at(-jpos))
            } else {
                Inertial::massless()
            };
            link = Some(
                self.builder
                    .add_link(link_name, link, joint.origin(origin), mass),
            );
        }
        if let Some(l) = link.filter(|_| gravcomp != 0.0) {
            self.builder.links_mut()[l.0].gravcomp = gravcomp;
        }
        for (mut g, filter) in geoms {
            g.link = link;
            g.pose.pos -= at;
            if let Some(l) = link {
                if let Some(k) = self.builder.add_contact_shape(l, &g.pose, &g.shape) {
                    self.builder.set_contact_filter(k, filter);
                    self.builder.set_contact_friction(k, g.friction);
                }
            }
            self.geoms.push(g);
        }
        if let (Some(l), Some(p)) = (link, parent) {
            self.parents.push((l, p));
        }
        for b in kids.iter().filter(|k| k.has_tag_name("body")) {
            self.body(*b, link, at, &class)?;
        }
        Ok(())
    }

    /// MuJoCo's filterparent: the bodies welded together (a body with joints and the bodies
    /// joined to it without one) never touch those welded to its parent body, unless these
    /// are fixed to the world.
    /// (The builder's rule sees a body with several joints as a chain of links, the last one's
    /// parent a massless link; hence the exclusions here.)
    fn filter_parents(&mut self) {
        let links = self.builder.links();
        // The link at the root of each link's weld (`None`: the world).
        let weld = |mut i: usize| -> Option<usize> {
            while links[i].joint.kind == super::JointType::Fixed {
                i = links[i].parent?.0;
            }
            Some(i)
        };
        let welds: Vec<Option<usize>> = (0..links.len()).map(weld).collect();
        let welds = &welds;
        let group = |w: usize| (0..links.len()).filter(move |&k| welds[k] == Some(w));
        let mut pairs = Vec::new();
        // A welded body is its parent's weld (never touching it anyway): only bodies with
        // joints start a weld, whose every link skips every link of the parent's.
        for &(l, p) in self.parents.iter().filter(|(l, _)| welds[l.0] == Some(l.0)) {
            if let Some(w) = welds[p.0] {
                for a in group(l.0) {
                    pairs.extend(group(w).map(|b| (LinkId(a), LinkId(b))));
                }
            }
        }
        for (a, b) in pairs {
            self.builder.exclude_contact(a, b);
        }
    }

    /// Whether `n` is a mesh geom, passed over as decoration (the robots of MuJoCo Menagerie
    /// draw their links with meshes that touch nothing and have an `<inertial>`). A mesh must
    /// change nothing simulated: one that would touch (its `contype` or `conaffinity` not 0,
    /// with contacts on), or whose mass would count (`mass_from_geoms`: the body has no
    /// `<inertial>`, or `inertiafromgeom="true"`; in the geom groups 0 to 5, without
    /// `mass="0"`), is an error naming it and what to change.
    fn decoration_mesh(
        &self,
        n: Node,
        class: &str,
        mass_from_geoms: bool,
    ) -> Result<bool, ArticulationError> {
        if self.attr(n, class, "type") != Some("mesh") {
            return Ok(false);
        }
        self.src.only_attributes(n, GEOM_ATTRS)?;
        self.check_class(n)?;
        let what = match n.attribute("name").or(self.attr(n, class, "mesh")) {
            Some(name) => format!("mesh geom `{name}`"),
            None => "a mesh geom".to_string(),
        };
        if self.filter(n, class)? != ContactFilter::NONE && !self.no_contact {
            return Err(self.src.error(
                n,
                format!(
                    "{what} would touch other geoms, and meshes are not contact shapes here: \
                     set contype=\"0\" conaffinity=\"0\" (it is then decoration), or put a \
                     sphere, capsule, box or cylinder in its place"
                ),
            ));
        }
        let group = self.nums(n, class, "group", &[1])?.map_or(0.0, |g| g[0]);
        let massless = self
            .nums(n, class, "mass", &[1])?
            .is_some_and(|m| m[0] == 0.0);
        if mass_from_geoms && (0.0..=5.0).contains(&group) && !massless {
            return Err(self.src.error(
                n,
                format!(
                    "the body's mass would come from {what}, whose volume is not computed here: \
                     give the body an <inertial> (MuJoCo then ignores its geoms' mass, unless \
                     <compiler inertiafromgeom=\"true\">), or set mass=\"0\" on the mesh"
                ),
            ));
        }
        Ok(true)
    }

    /// A geom's `contype` and `conaffinity` (own or default; 1 when not given).
    fn filter(&self, n: Node, class: &str) -> Result<ContactFilter, ArticulationError> {
        let mask = |k: &str| -> Result<u32, ArticulationError> {
            match self.attr(n, class, k) {
                None => Ok(1),
                Some(v) => v.trim().parse().map_err(|_| {
                    self.src.error(
                        n,
                        format!("{k}=\"{v}\": a non-negative integer (a bit mask)"),
                    )
                }),
            }
        };
        Ok(ContactFilter {
            contype: mask("contype")?,
            conaffinity: mask("conaffinity")?,
        })
    }

    /// A joint and its `pos` in the body frame.
    fn joint(&mut self, n: Node, class: &str) -> Result<(Joint, Vec3<f64>), ArticulationError> {
        self.src.only_attributes(n, JOINT_ATTRS)?;
        self.check_class(n)?;
        let kind = if n.has_tag_name("freejoint") {
            "free"
        } else {
            self.attr(n, class, "type").unwrap_or("hinge")
        }
        .to_string();
        let kind = kind.as_str();
        let axis = self
            .nums(n, class, "axis", &[3])?
            .map(|a| Vec3::new(a[0], a[1], a[2]))
            .unwrap_or_else(Vec3::z);
        if axis.norm() < 1e-12 {
            return Err(self.src.error(n, "axis is zero"));
        }
        let mut j = match kind {
            "hinge" => Joint::revolute(axis),
            "slide" => Joint::prismatic(axis),
            "ball" => Joint::ball(),
            "free" => Joint::free(),
            o => {
                return Err(self.src.error(
                    n,
                    format!("joint type `{o}` is not supported (hinge, slide, ball, free)"),
                ))
            }
        };
        if let Some(v) = self.nums(n, class, "frictionloss", &[1])? {
            if v[0] != 0.0 {
                return Err(self.src.error(
                    n,
                    "`frictionloss` is not supported; remove it or set it to 0",
                ));
            }
        }
        // MuJoCo's `ref` (hinges and slides): the coordinate at which the body is where the
        // file puts it, and the initial one. `body` turns the joint's frame by `-ref`.
        if let (Some(v), "hinge" | "slide") = (self.nums(n, class, "ref", &[1])?, kind) {
            let r = if kind == "hinge" {
                self.angle(v[0])
            } else {
                v[0]
            };
            j = j.initial(&[r]);
        }
        let name = n
            .attribute("name")
            .map(str::to_string)
            .unwrap_or_else(|| format!("joint{}", self.joints.len()));
        if self.joints.insert(name.clone(), ()).is_some() {
            return Err(self.src.error(n, "a second joint with this name"));
        }
        j = j.name(name);
        let range = self.nums(n, class, "range", &[2])?;
        // MuJoCo's limit acts from `margin` inside the range and pushes back to there: the
        // limit is at the range shrunk by the margin.
        let margin = self.nums(n, class, "margin", &[1])?.map_or(0.0, |v| v[0]);
        if margin < 0.0 {
            return Err(self.src.error(n, format!("margin {margin} is negative")));
        }
        let limited = self.attr(n, class, "limited").unwrap_or("auto");
        self.keyword(n, "limited", limited)?;
        if let Some(r) = range {
            if limited != "false" && (kind == "hinge" || kind == "slide") {
                let s = |x| if kind == "hinge" { self.angle(x) } else { x };
                let (lo, hi) = (s(r[0]), s(r[1]));
                if lo > hi || (lo == hi && limited == "true") {
                    let (a, b) = (r[0], r[1]);
                    return Err(self.src.error(n, format!("range: lower {a} >= upper {b}")));
                }
                // As MuJoCo, `limited="auto"` limits only a range with lower < upper: `range="0
                // 0"` (MuJoCo's default) leaves the joint free.
                if lo < hi && !self.no_limits {
                    // In the joint's coordinate (radians for a hinge), as MuJoCo reads it.
                    let m = margin;
                    if lo + m >= hi - m {
                        return Err(self.src.error(
                            n,
                            format!("margin {margin} closes the range [{}, {}]", r[0], r[1]),
                        ));
                    }
                    j = j.limits(lo + m, hi - m);
                    // MuJoCo's limit law: a time constant and a damping ratio.
                    let sr = self.nums(n, class, "solreflimit", &[2])?;
                    let (tc, zeta) = sr.map_or((0.02, 1.0), |v| (v[0], v[1]));
                    if !(tc > 0.0 && zeta > 0.0) {
                        return Err(self.src.error(
                            n,
                            format!(
                                "solreflimit=\"{tc} {zeta}\": only a positive time constant and \
                                 damping ratio are supported"
                            ),
                        ));
                    }
                    // (MuJoCo's `refsafe` applies at each step: `builder.limit_refsafe`.)
                    j = j.limit_time_constant(tc, zeta);
                    if let Some(v) = self.nums(n, class, "solimplimit", &[3, 4, 5])? {
                        if v.len() > 3 && (v[3] != 0.5 || v.get(4).is_some_and(|&p| p != 2.0)) {
                            return Err(self.src.error(
                                n,
                                "solimplimit: only MuJoCo's default midpoint 0.5 and power 2 \
                                 are supported",
                            ));
                        }
                        // MuJoCo keeps the impedance within [1e-4, 0.9999].
                        let clamp = |x: f64| x.clamp(1e-4, 0.9999);
                        let (dmin, dmax) = (clamp(v[0]), clamp(v[1]));
                        if dmin > dmax || v[2] <= 0.0 {
                            return Err(self.src.error(
                                n,
                                "solimplimit: dmin <= dmax and a positive width are supported",
                            ));
                        }
                        j = j.limit_impedance(dmin, dmax, v[2]);
                    }
                }
            } else if limited != "false" && kind == "ball" {
                // MuJoCo would limit the cone of a ball joint with a range.
                return Err(self.src.error(
                    n,
                    "a range on a ball joint (a cone limit) is not supported; remove it or set \
                     limited=\"false\"",
                ));
            }
        } else if limited == "true" && (kind == "hinge" || kind == "slide") {
            return Err(self.src.error(n, "limited=\"true\" needs a `range`"));
        }
        let stiffness = self
            .nums(n, class, "stiffness", &[1])?
            .map_or(0.0, |v| v[0]);
        if stiffness != 0.0 {
            if !(kind == "hinge" || kind == "slide") {
                return Err(self.src.error(
                    n,
                    format!(
                        "stiffness on a {kind} joint is not supported; remove it or set it to 0"
                    ),
                ));
            }
            if !(stiffness.is_finite() && stiffness > 0.0) {
                return Err(self
                    .src
                    .error(n, format!("stiffness {stiffness} is negative")));
            }
            let r = self
                .nums(n, class, "springref", &[1])?
                .map_or(0.0, |v| v[0]);
            let r = if kind == "hinge" { self.angle(r) } else { r };
            j = j.stiffness(stiffness, r);
        }
        for (attr, set) in [("damping", 0), ("armature", 1)] {
            if let Some(v) = self.nums(n, class, attr, &[1])? {
                if v[0] < 0.0 {
                    return Err(self.src.error(n, format!("{attr} {} is negative", v[0])));
                }
                if set == 1 && kind == "free" && v[0] != 0.0 {
                    // MuJoCo adds it to the world-frame linear velocities, which are not this
                    // joint's coordinates: the motion would differ.
                    return Err(self.src.error(
                        n,
                        "armature on a free joint is not supported; set armature=\"0\"",
                    ));
                }
                j = if set == 0 {
                    j.damping(v[0])
                } else {
                    j.armature(v[0])
                };
            }
        }
        let pos = if kind == "free" {
            Vec3::zeros()
        } else {
            self.nums(n, class, "pos", &[3])?
                .map(|a| Vec3::new(a[0], a[1], a[2]))
                .unwrap_or_else(Vec3::zeros)
        };
        Ok((j, pos))
    }

    /// A geom (in its body's frame) and its mass properties, if it has any.
    fn geom(
        &self,
        n: Node,
        class: &str,
        on_link: Option<LinkId>,
    ) -> Result<(Geom, Option<Inertial>), ArticulationError> {
        self.src.only_attributes(n, GEOM_ATTRS)?;
        self.check_class(n)?;
        let kind = self.attr(n, class, "type").unwrap_or("sphere");
        let size = self.nums(n, class, "size", &[1, 2, 3])?.unwrap_or_default();
        let fromto = self.nums(n, class, "fromto", &[6])?;
        let need = |k: usize| -> Result<(), ArticulationError> {
            if size.len() < k || size[..k].iter().any(|&s| s <= 0.0) {
                Err(self.src.error(
                    n,
                    format!(
                        "a {kind} needs {k} positive size value{}",
                        if k > 1 { "s" } else { "" }
                    ),
                ))
            } else {
                Ok(())
            }
        };
        let mut pose = Pose::new(
            self.nums(n, class, "pos", &[3])?
                .map(|a| Vec3::new(a[0], a[1], a[2]))
                .unwrap_or_else(Vec3::zeros),
            self.orientation(n, class)?,
        );
        let mut half = 0.0;
        if let Some(f) = &fromto {
            if !matches!(kind, "capsule" | "cylinder" | "box") {
                return Err(self
                    .src
                    .error(n, format!("fromto does not apply to a {kind}")));
            }
            let (a, b) = (Vec3::new(f[0], f[1], f[2]), Vec3::new(f[3], f[4], f[5]));
            if (b - a).norm() < 1e-12 {
                return Err(self.src.error(n, "fromto has two equal points"));
            }
            half = 0.5 * (b - a).norm();
            pose = Pose::new(0.5 * (a + b), from_to(&Vec3::z(), &(b - a).normalize()));
        }
        let shape = match kind {
            "sphere" => {
                need(1)?;
                GeomShape::Sphere(size[0])
            }
            "capsule" | "cylinder" => {
                if fromto.is_some() {
                    need(1)?;
                } else {
                    need(2)?;
                    half = size[1];
                }
                if kind == "capsule" {
                    GeomShape::Capsule(size[0], half)
                } else {
                    GeomShape::Cylinder(size[0], half)
                }
            }
            "box" => {
                if fromto.is_some() {
                    // As MuJoCo: the length from `fromto`, a square cross-section of half-side
                    // `size[0]`.
                    need(1)?;
                    GeomShape::Box(Vec3::new(size[0], size[0], half))
                } else {
                    need(3)?;
                    GeomShape::Box(Vec3::new(size[0], size[1], size[2]))
                }
            }
            "ellipsoid" => {
                need(3)?;
                GeomShape::Ellipsoid(Vec3::new(size[0], size[1], size[2]))
            }
            "plane" => {
                if on_link.is_some() {
                    return Err(self.src.error(n, "a plane must be a geom of the worldbody"));
                }
                GeomShape::Plane
            }
            o => {
                return Err(self.src.error(
                    n,
                    format!(
                        "geom type `{o}` is not supported (sphere, capsule, cylinder, ellipsoid, \
                         box, plane)"
                    ),
                ))
            }
        };
        let friction = self
            .nums(n, class, "friction", &[1, 2, 3])?
            .map(|f| f[0])
            .unwrap_or(1.0);
        if !(friction.is_finite() && friction >= 0.0) {
            return Err(self.src.error(
                n,
                format!("friction {friction} must be finite and non-negative"),
            ));
        }
        let geom = Geom {
            name: n.attribute("name").unwrap_or("").to_string(),
            link: on_link,
            pose,
            shape,
            friction,
        };
        if on_link.is_none() {
            return Ok((geom, None));
        }
        let volume_and_inertia = |s: &GeomShape| -> (f64, Vec3<f64>) {
            // Volume, and the principal moments per unit mass.
            match *s {
                GeomShape::Sphere(r) => (4.0 / 3.0 * PI * r.powi(3), Vec3::repeat(0.4 * r * r)),
                GeomShape::Box(h) => (
                    8.0 * h.x * h.y * h.z,
                    Vec3::new(
                        h.y * h.y + h.z * h.z,
                        h.x * h.x + h.z * h.z,
                        h.x * h.x + h.y * h.y,
                    ) / 3.0,
                ),
                GeomShape::Cylinder(r, h) => {
                    let l = 2.0 * h;
                    let t = (3.0 * r * r + l * l) / 12.0;
                    (PI * r * r * l, Vec3::new(t, t, 0.5 * r * r))
                }
                GeomShape::Capsule(r, h) => {
                    // A cylinder and two hemispheres, exactly.
                    let l = 2.0 * h;
                    let (vc, vs) = (PI * r * r * l, 4.0 / 3.0 * PI * r.powi(3));
                    let (fc, fs) = (vc / (vc + vs), vs / (vc + vs));
                    let t = fc * (3.0 * r * r + l * l) / 12.0
                        + fs * (0.4 * r * r + l * (3.0 * r + 2.0 * l) / 8.0);
                    (
                        vc + vs,
                        Vec3::new(t, t, fc * 0.5 * r * r + fs * 0.4 * r * r),
                    )
                }
                GeomShape::Ellipsoid(a) => (
                    4.0 / 3.0 * PI * a.x * a.y * a.z,
                    Vec3::new(
                        a.y * a.y + a.z * a.z,
                        a.x * a.x + a.z * a.z,
                        a.x * a.x + a.y * a.y,
                    ) / 5.0,
                ),
                GeomShape::Plane => (0.0, Vec3::zeros()),
            }
        };
        let (volume, per_mass) = volume_and_inertia(&shape);
        let mass = match (
            self.nums(n, class, "mass", &[1])?,
            self.nums(n, class, "density", &[1])?,
        ) {
            (Some(m), _) => m[0],
            (None, Some(d)) => d[0] * volume,
            (None, None) => 1000.0 * volume,
        };
        if mass < 0.0 {
            return Err(self.src.error(n, format!("mass {mass} is negative")));
        }
        // MuJoCo's `inertiagrouprange` (default 0 to 5): a geom of another group has no mass.
        let group = self.nums(n, class, "group", &[1])?.map_or(0.0, |g| g[0]);
        if !(0.0..=5.0).contains(&group) {
            return Ok((geom, None));
        }
        let local = Inertial::new(
            mass,
            Vec3::zeros(),
            Mat33::from_diagonal(&(per_mass * mass)),
        );
        Ok((geom, Some(local.transformed(&pose))))
    }

    fn inertial(&self, n: Node) -> Result<Inertial, ArticulationError> {
        self.src.only_attributes(
            n,
            &[
                "pos",
                "quat",
                "euler",
                "axisangle",
                "xyaxes",
                "zaxis",
                "mass",
                "diaginertia",
                "fullinertia",
            ],
        )?;
        children(&self.src, n, &[], &[])?;
        let pos = self
            .src
            .vec3(n, "pos")?
            .ok_or_else(|| self.src.error(n, "needs `pos`"))?;
        let mass = self
            .src
            .number(n, "mass")?
            .ok_or_else(|| self.src.error(n, "needs `mass`"))?;
        check_mass(mass, "a body").map_err(|m| self.src.error(n, m))?;
        let rot = self.orientation(n, "main")?;
        let inertia = match (
            self.src.vec3(n, "diaginertia")?,
            self.src.numbers(n, "fullinertia", 6)?,
        ) {
            (Some(d), None) => Mat33::from_diagonal(&d),
            (None, Some(f)) => {
                // MuJoCo reads `fullinertia` in the body's frame, whatever orientation is given.
                if ORIENTATIONS.iter().any(|(a, _)| n.attribute(*a).is_some()) {
                    return Err(self.src.error(
                        n,
                        "`fullinertia` is in the body's frame: remove the orientation",
                    ));
                }
                Mat33::new(f[0], f[3], f[4], f[3], f[1], f[5], f[4], f[5], f[2])
            }
            _ => {
                return Err(self
                    .src
                    .error(n, "needs one of `diaginertia` and `fullinertia`"))
            }
        };
        let i = Inertial::new(mass, Vec3::zeros(), inertia).transformed(&Pose::new(pos, rot));
        check_inertial(&i).map_err(|m| self.src.error(n, m))?;
        Ok(i)
    }

    /// An actuator element: MuJoCo's general actuator (`dyntype="none"`; fixed or affine
    /// gain, none or affine bias) and its `<motor>`, `<position>`, `<velocity>` and `<damper>`
    /// shortcuts, on a hinge or slide joint or a fixed tendon of such joints, added to the
    /// builder.
    fn actuator(&mut self, n: Node) -> Result<(), ArticulationError> {
        let tag = n.tag_name().name();
        let class = "main";
        self.src.only_attributes(n, ACTUATOR_ATTRS)?;
        self.check_class(n)?;
        let transmission = match (n.attribute("joint"), n.attribute("tendon")) {
            (Some(joint), None) => match self.joint_link(joint) {
                Some(link) => vec![(link, 1.0)],
                None => {
                    return Err(self
                        .src
                        .error(n, format!("joint \"{joint}\" is not defined")))
                }
            },
            (None, Some(tendon)) => match self.tendons.get(tendon) {
                Some(joints) => joints.clone(),
                None => {
                    return Err(self
                        .src
                        .error(n, format!("fixed tendon \"{tendon}\" is not defined")))
                }
            },
            _ => {
                return Err(self.src.error(
                    n,
                    "an actuator needs a `joint` or a fixed `tendon` (exactly one)",
                ))
            }
        };
        let gears = self.nums(n, class, "gear", &[1, 6])?;
        let gear = gears.as_ref().map_or(1.0, |g| g[0]);
        // MuJoCo's other gear components turn the force into a torque, or act on the other
        // axes of a ball or free joint: not read here, so refused.
        if gears
            .as_ref()
            .is_some_and(|g| g[1..].iter().any(|&x| x != 0.0))
        {
            return Err(self.src.error(
                n,
                "gear: only the first component is supported (a force on the joint's axis)",
            ));
        }
        if let Some(&(l, _)) = transmission
            .iter()
            .find(|(l, _)| !self.builder.links()[l.0].joint.kind.is_scalar())
        {
            return Err(self.src.error(
                n,
                format!(
                    "<{tag}> needs hinge or slide joints (joint \"{}\" is not)",
                    self.builder.links()[l.0].joint.name
                ),
            ));
        }
        let ctrl_range = self.range(n, class, "ctrl")?.filter(|_| self.clamp_ctrl);
        let force_range = self.range(n, class, "force")?;
        let gain = |name: &str, default: f64| self.non_negative(n, class, name, default);
        let link = transmission[0].0;
        let mut actuator = match tag {
            "motor" => Actuator::motor(link),
            "position" => Actuator::position(link, gain("kp", 1.0)?, gain("kv", 0.0)?),
            "velocity" => Actuator::velocity(link, gain("kv", 1.0)?),
            "damper" => {
                // MuJoCo's damper: force -kv v ctrl, with a non-negative control range.
                if !ctrl_range.is_some_and(|r| r.0 >= 0.0) {
                    return Err(self.src.error(
                        n,
                        "<damper> needs a `ctrlrange` with a non-negative lower end",
                    ));
                }
                Actuator {
                    gain: [0.0, 0.0, -gain("kv", 1.0)?],
                    ..Actuator::motor(link)
                }
            }
            _ => self.general(n, class, link)?,
        };
        actuator.transmission = transmission;
        actuator.name = n.attribute("name").unwrap_or("").to_string();
        actuator.gear = gear;
        actuator.ctrl_range = ctrl_range;
        actuator.force_range = force_range;
        self.builder.add_actuator(actuator);
        Ok(())
    }

    /// A fixed tendon's spring and damper, if it has stiffness or damping: MuJoCo's
    /// `springlength` (one length, or a dead band's two; `-1`, the default, for the length
    /// at the joints' spring references).
    fn tendon_spring(
        &mut self,
        t: Node,
        class: &str,
        joints: &[(LinkId, f64)],
    ) -> Result<(), ArticulationError> {
        let stiffness = self.non_negative(t, class, "stiffness", 0.0)?;
        let damping = self.non_negative(t, class, "damping", 0.0)?;
        if stiffness == 0.0 && damping == 0.0 {
            return Ok(());
        }
        let rest = match self.nums(t, class, "springlength", &[1, 2])?.as_deref() {
            None | Some([-1.0]) | Some([-1.0, -1.0]) => None,
            Some(&[l]) => Some((l, l)),
            Some(&[lo, hi]) if lo <= hi => Some((lo, hi)),
            Some(_) => return Err(self.src.error(t, "springlength: lower > upper")),
        };
        self.builder.add_tendon_spring(TendonSpring {
            name: t.attribute("name").unwrap_or("").to_string(),
            joints: joints.to_vec(),
            stiffness,
            damping,
            rest,
        });
        Ok(())
    }

    /// A number attribute (own or default; `default` when neither) that must be
    /// non-negative.
    fn non_negative(
        &self,
        n: Node,
        class: &str,
        name: &str,
        default: f64,
    ) -> Result<f64, ArticulationError> {
        let v = self.nums(n, class, name, &[1])?.map_or(default, |v| v[0]);
        match v >= 0.0 {
            true => Ok(v),
            false => Err(self.src.error(n, format!("{name} must be non-negative"))),
        }
    }

    /// The link of the joint called `name`.
    fn joint_link(&self, name: &str) -> Option<LinkId> {
        let links = self.builder.links();
        links.iter().position(|l| l.joint.name == name).map(LinkId)
    }

    /// A `<general>` actuator's gain and bias.
    fn general(&self, n: Node, class: &str, link: LinkId) -> Result<Actuator, ArticulationError> {
        let kind = |what: &str| self.attr(n, class, what).unwrap_or("none");
        for (what, allowed) in [
            ("dyntype", &["none"][..]),
            ("gaintype", &["fixed", "affine"][..]),
            ("biastype", &["none", "affine"][..]),
        ] {
            let v = self.attr(n, class, what).unwrap_or(allowed[0]);
            if !allowed.contains(&v) {
                return Err(self.src.error(
                    n,
                    format!(
                        "{what}=\"{v}\" is not supported (only {})",
                        allowed.join(", ")
                    ),
                ));
            }
        }
        let prm = |name: &str, default: [f64; 3]| -> Result<[f64; 3], ArticulationError> {
            let counts: Vec<usize> = (1..=10).collect();
            Ok(match self.nums(n, class, name, &counts)? {
                Some(v) => std::array::from_fn(|i| v.get(i).copied().unwrap_or(0.0)),
                None => default,
            })
        };
        let mut gain = prm("gainprm", [1.0, 0.0, 0.0])?;
        if kind("gaintype") != "affine" {
            gain[1..].fill(0.0);
        }
        let mut bias = prm("biasprm", [0.0; 3])?;
        if kind("biastype") != "affine" {
            bias = [0.0; 3];
        }
        Ok(Actuator {
            gain,
            bias,
            ..Actuator::motor(link)
        })
    }

    /// Refuses a `limited`-style attribute that is not MuJoCo's `true`, `false` or `auto`.
    fn keyword(&self, n: Node, attr: &str, value: &str) -> Result<(), ArticulationError> {
        match value {
            "true" | "false" | "auto" => Ok(()),
            v => Err(self.src.error(
                n,
                format!("{attr}=\"{v}\": MuJoCo's keywords are true, false and auto"),
            )),
        }
    }

    /// `ctrlrange`/`ctrllimited` (`what` "ctrl") or `forcerange`/`forcelimited` ("force"), as
    /// MuJoCo reads them: `"auto"` (the default) limits a range with lower < upper.
    fn range(
        &self,
        n: Node,
        class: &str,
        what: &str,
    ) -> Result<Option<(f64, f64)>, ArticulationError> {
        let limited = self
            .attr(n, class, &format!("{what}limited"))
            .unwrap_or("auto");
        self.keyword(n, &format!("{what}limited"), limited)?;
        Ok(match self.nums(n, class, &format!("{what}range"), &[2])? {
            Some(r) if limited != "false" => {
                if r[0] > r[1] || (r[0] == r[1] && limited == "true") {
                    return Err(self.src.error(n, format!("{what}range: lower >= upper")));
                }
                // As MuJoCo, `"auto"` limits only a range with lower < upper.
                (r[0] < r[1]).then_some((r[0], r[1]))
            }
            Some(_) => None,
            None if limited == "true" => {
                return Err(self
                    .src
                    .error(n, format!("{what}limited=\"true\" needs a `{what}range`")));
            }
            None => None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::pose::{rotate, rotation_matrix};
    use super::*;

    #[test]
    fn from_to_rotates_a_onto_b() {
        for (a, b) in [
            (Vec3::z(), Vec3::new(1.0, 2.0, -0.5).normalize()),
            (Vec3::z(), -Vec3::z()),
            (Vec3::z(), Vec3::z()),
        ] {
            let q = from_to(&a, &b);
            assert!((rotate(&q, &a) - b).norm() < 1e-12);
            assert!((rotation_matrix(&q) * a - b).norm() < 1e-12);
        }
    }
}

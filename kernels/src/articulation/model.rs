//! Describing articulations: joints, inertias, the builder and the finished model.

use std::fmt;
use std::ops::Range;

use adflex_runtime::prelude::*;

use super::actuator::{Actuator, TendonSpring};
use super::contact::{ContactFilter, ContactShape, GeomShape, GroundContact};
use super::fluid::Fluid;
pub(crate) use super::pose::{axis_angle, from_to, rotate};
pub use super::pose::{Inertial, LinkId, Pose};

/// How [`Articulations::step`] advances a state by `dt`: MuJoCo's integrators, step for step
/// (checked against `mj_step` in the tests, contact and limits aside).
///
/// | Integrator | MuJoCo | A step |
/// |---|---|---|
/// | `Euler` | `Euler` | `qd' = qd + dt qdd`, then `q'` from `qd'` (semi-implicit); the joint damping implicit when [`ArticulationBuilder::implicit_damping`] (MuJoCo's `eulerdamp`) |
/// | `Rk4` | `RK4` | the classic fourth-order Runge-Kutta method on `(q, qd)`: four evaluations of the dynamics, every force explicit |
/// | `ImplicitFast` | `implicitfast` | as `Euler`, solving with `M - dt df/dqd` in place of `M`: the velocity derivatives of the joint damping, the tendons' damping, the actuators' speed terms and the joints' PD `kv` (not the Coriolis terms') |
///
/// Violated joint limits are implicit in `Euler` and `ImplicitFast` steps
/// ([`Joint::limit_time_constant`]) and explicit in `Rk4`'s stages; so is the friction's damper
/// of the contacts with the ground and with links fixed to the world
/// ([`GroundContact::implicit_friction`](super::GroundContact)). The rest of
/// the contact law, muscles and the fluid are explicit in all three.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum ArticulationIntegrator {
    /// Semi-implicit Euler (the default, as MuJoCo's).
    #[default]
    Euler,
    /// Classic fourth-order Runge-Kutta.
    Rk4,
    /// Euler with the velocity-dependent forces' derivative in the solve (MuJoCo's
    /// `implicitfast`): stable with stiff damping and servos' `kv` at large steps.
    ImplicitFast,
}

/// The kind of a joint, which says how the link moves relative to its parent.
///
/// | kind | coordinates `q` | velocities `qd` |
/// |---|---|---|
/// | `Fixed` | none | none |
/// | `Revolute` | angle (rad) about the axis | angular rate (rad/s) |
/// | `Prismatic` | offset (m) along the axis | rate (m/s) |
/// | `Ball` | unit quaternion `x, y, z, w` | angular velocity in the link frame (rad/s) |
/// | `Free` | position (m) in the joint's frame (its origin in the parent; the world for a root), then a unit quaternion `x, y, z, w` | linear velocity of the link origin, then angular velocity, both in the link frame |
///
/// These are Pinocchio's conventions (`JointModelSpherical`, `JointModelFreeFlyer`), so that
/// `q`, `qd`, `M(q)` and the derivatives compare entry for entry. MuJoCo orders a quaternion
/// `w, x, y, z` and gives a free joint's linear velocity in the world frame; convert when
/// comparing (the reference script `kernels/tests/references/robots.py` shows how).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum JointType {
    /// Welded to the parent.
    Fixed,
    /// Rotation about an axis through the link frame's origin.
    Revolute,
    /// Translation along an axis.
    Prismatic,
    /// Any rotation about the link frame's origin.
    Ball,
    /// Any motion (a floating base).
    Free,
}

impl JointType {
    /// Number of coordinates in `q`.
    pub fn nq(self) -> usize {
        match self {
            JointType::Fixed => 0,
            JointType::Revolute | JointType::Prismatic => 1,
            JointType::Ball => 4,
            JointType::Free => 7,
        }
    }

    /// Number of velocities (degrees of freedom) in `qd`.
    pub fn nv(self) -> usize {
        match self {
            JointType::Fixed => 0,
            JointType::Revolute | JointType::Prismatic => 1,
            JointType::Ball => 3,
            JointType::Free => 6,
        }
    }

    /// The code the kernels use (see `articulation_fk`).
    pub(crate) fn code(self) -> u32 {
        match self {
            JointType::Fixed => 0,
            JointType::Revolute => 1,
            JointType::Prismatic => 2,
            JointType::Ball => 3,
            JointType::Free => 4,
        }
    }

    /// True for the joints with one coordinate (PD targets and limits apply to them).
    pub fn is_scalar(self) -> bool {
        self.nq() == 1
    }
}

/// A joint: its kind, where it sits on the parent link, its axis and its passive and actuation
/// properties. The link's frame is the joint's frame: at `q = 0` it is `origin` in the parent
/// link's frame, and the joint moves it from there.
///
/// ```
/// use adflex_kernels::articulation::{Joint, Pose};
/// use adflex_runtime::Vec3;
/// let elbow = Joint::revolute(Vec3::new(0.0, 1.0, 0.0))
///     .origin(Pose::at(Vec3::new(0.0, 0.0, 0.3)))
///     .limits(-2.0, 2.0)
///     .damping(0.1)
///     .armature(0.01);
/// assert_eq!(elbow.limits, Some((-2.0, 2.0)));
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct Joint {
    /// The kind.
    pub kind: JointType,
    /// Name, for errors and lookup (the link's name when empty).
    pub name: String,
    /// The joint frame in the parent link's frame at `q = 0`.
    pub origin: Pose,
    /// Axis in the joint frame (revolute, prismatic; normalized by the builder).
    pub axis: Vec3<f64>,
    /// Lower and upper position limits (rad or m), revolute and prismatic only.
    pub limits: Option<(f64, f64)>,
    /// How the limits push back: `None`, the builder's penalty `limit_ke`, `limit_kd`; or
    /// `(time constant, damping ratio)` (s, 1): a spring and damper scaled by the joint's
    /// inertia, MuJoCo's `solreflimit` (see [`Joint::limit_time_constant`]).
    pub limit_time: Option<(f64, f64)>,
    /// MuJoCo's `solimplimit` `(dmin, dmax, width)` for a limit with a time constant
    /// (default `(0.9, 0.95, 0.001)`, MuJoCo's; see [`Joint::limit_impedance`]).
    pub limit_impedance: (f64, f64, f64),
    /// Viscous damping (N m s/rad or N s/m) on every velocity of the joint.
    pub damping: f64,
    /// A passive spring `-stiffness (q - spring_ref)` (N m/rad or N/m; revolute and
    /// prismatic only; default 0: none), as MuJoCo's joint `stiffness` and `springref`.
    pub stiffness: f64,
    /// The spring's rest position (rad or m).
    pub spring_ref: f64,
    /// Armature (rotor inertia, kg m^2 or kg) added to the mass matrix's diagonal.
    pub armature: f64,
    /// Position gain of a PD actuator toward `target_q` (N m/rad or N/m; 0 = none).
    pub kp: f64,
    /// Velocity gain toward `target_qd` (N m s/rad or N s/m; 0 = none).
    pub kv: f64,
    /// The joint's initial coordinates (`JointType::nq` of them); empty: zeros and the
    /// identity quaternion.
    pub initial: Vec<f64>,
}

impl Joint {
    fn new(kind: JointType, axis: Vec3<f64>) -> Self {
        Joint {
            kind,
            name: String::new(),
            origin: Pose::identity(),
            axis,
            limits: None,
            limit_time: None,
            limit_impedance: (0.9, 0.95, 0.001),
            damping: 0.0,
            stiffness: 0.0,
            spring_ref: 0.0,
            armature: 0.0,
            kp: 0.0,
            kv: 0.0,
            initial: Vec::new(),
        }
    }

    /// Welded to the parent.
    pub fn fixed() -> Self {
        Self::new(JointType::Fixed, Vec3::z())
    }

    /// Rotation about `axis` (joint frame).
    pub fn revolute(axis: Vec3<f64>) -> Self {
        Self::new(JointType::Revolute, axis)
    }

    /// Translation along `axis` (joint frame).
    pub fn prismatic(axis: Vec3<f64>) -> Self {
        Self::new(JointType::Prismatic, axis)
    }

    /// A spherical joint.
    pub fn ball() -> Self {
        Self::new(JointType::Ball, Vec3::z())
    }

    /// A floating joint (six degrees of freedom).
    pub fn free() -> Self {
        Self::new(JointType::Free, Vec3::z())
    }

    /// Sets the name.
    pub fn name(mut self, name: impl Into<String>) -> Self {
        self.name = name.into();
        self
    }

    /// Sets the joint frame in the parent link's frame.
    pub fn origin(mut self, origin: Pose) -> Self {
        self.origin = origin;
        self
    }

    /// Sets position limits.
    pub fn limits(mut self, lower: f64, upper: f64) -> Self {
        self.limits = Some((lower, upper));
        self
    }

    /// Makes the limits push back as MuJoCo's limit constraint
    /// (`solreflimit="time_constant damping_ratio"`, MuJoCo's default `0.02 1`;
    /// [`Joint::limit_impedance`] is its `solimplimit`). Past a limit by `r < 0` (measured into
    /// the range: `q - lower` or `upper - q`) at the velocity `u` into the range (`qd` or
    /// `-qd`), the constraint asks for the acceleration `a_ref = -b u - k d r`, with
    /// `k = 1 / (dmax tc zeta)^2`, `b = 2 / (dmax tc)` and `d` the impedance at that depth, and
    /// pushes with the force `f = (a_ref - a0) / (A + R) >= 0` into the range: `a0` is the
    /// acceleration the joint would have without it, `A = (M^-1)[j][j]`, and
    /// `R = (1 - d) / (d m)` with `m = 1 / (M^-1)[j][j]` at the neutral configuration (MuJoCo's
    /// `dof_invweight0`, the model's [`limit_m`](Articulations::limit_m)). Violated limits
    /// are solved together (forces that would pull are dropped, as MuJoCo's solver does), so:
    /// - a light link and a heavy one come back alike, in about `tc`;
    /// - a steady load pressing into the limit is cancelled but for about `1 - d` of it (the
    ///   joint sags past the limit by `(1 - d) a0 / (d^2 k)`, as in MuJoCo);
    /// - the force is explicit (from the step's start, as MuJoCo's); with
    ///   [`ArticulationBuilder::limit_refsafe`] (the default) a step uses a time constant of at
    ///   least `2 dt`, which keeps it stable at any step.
    ///
    /// `Euler` and `ImplicitFast` steps solve with the implicit damping terms on the mass
    /// matrix after the constraint (computed with `M` alone), as MuJoCo's. (The builder's
    /// `limit_ke`, `limit_kd` are one stiffness for every joint, a penalty integrated
    /// implicitly: a light link pressed far past its limit snaps back, and a load sags
    /// `load / limit_ke` past it.)
    pub fn limit_time_constant(mut self, time_constant: f64, damping_ratio: f64) -> Self {
        self.limit_time = Some((time_constant, damping_ratio));
        self
    }

    /// Sets the impedance of a time-constant limit (MuJoCo's `solimplimit`, with its default
    /// midpoint 0.5 and power 2): `d` rises from `dmin` at the limit to `dmax` at `width`
    /// past it.
    pub fn limit_impedance(mut self, dmin: f64, dmax: f64, width: f64) -> Self {
        self.limit_impedance = (dmin, dmax, width);
        self
    }

    /// Sets viscous damping.
    pub fn damping(mut self, damping: f64) -> Self {
        self.damping = damping;
        self
    }

    /// Sets a passive spring toward `reference` (revolute and prismatic joints).
    pub fn stiffness(mut self, stiffness: f64, reference: f64) -> Self {
        self.stiffness = stiffness;
        self.spring_ref = reference;
        self
    }

    /// Sets the armature.
    pub fn armature(mut self, armature: f64) -> Self {
        self.armature = armature;
        self
    }

    /// Sets the initial coordinates (e.g. a free joint's `x, y, z, qx, qy, qz, qw`).
    pub fn initial(mut self, q: &[f64]) -> Self {
        self.initial = q.to_vec();
        self
    }

    /// Sets a PD actuator's gains.
    pub fn pd(mut self, kp: f64, kv: f64) -> Self {
        self.kp = kp;
        self.kv = kv;
        self
    }
}

/// A Hill-type muscle-tendon unit between two links (see
/// [`muscle`](super::muscle) for its force).
#[derive(Clone, Debug, PartialEq)]
pub struct Muscle {
    /// Name, for errors.
    pub name: String,
    /// The origin: a link and a point in its frame (m).
    pub origin: (LinkId, Vec3<f64>),
    /// The insertion: a link and a point in its frame (m).
    pub insertion: (LinkId, Vec3<f64>),
    /// Peak isometric force (N).
    pub f_max: f64,
    /// Optimal fibre length (m).
    pub l_opt: f64,
    /// Tendon slack length (m; the tendon is rigid).
    pub tendon_slack: f64,
    /// Maximum shortening speed, in optimal lengths per second (typically 10).
    pub v_max: f64,
}

/// A link as described: name, parent, the joint to the parent, mass properties.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkDesc {
    /// Name (unique within the builder for lookups; errors use it).
    pub name: String,
    /// The parent link (`None`: the world; the link is the root of an articulation).
    pub parent: Option<LinkId>,
    /// The joint to the parent (or to the world).
    pub joint: Joint,
    /// Mass properties.
    pub inertial: Inertial,
    /// Gravity compensation (default 0), MuJoCo's `gravcomp`: an upward force of this fraction
    /// of the link's weight at its centre of mass (1 cancels gravity on the link; any finite
    /// value, e.g. buoyancy). A passive force: it joins the step's forces with a control, as
    /// MuJoCo adds it to `qfrc_passive`, not the bias forces.
    pub gravcomp: f64,
}

/// What is wrong with a described articulation (or robot file): the element, where it is,
/// and what to do.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ArticulationError {
    /// The element: `link "forearm"`, `joint "elbow"`, `<joint name="elbow">`.
    pub element: String,
    /// The file, when read from one.
    pub file: Option<String>,
    /// The line in the file (1-based), when read from one.
    pub line: Option<u32>,
    /// What is wrong and what to do about it.
    pub message: String,
}

impl ArticulationError {
    pub(crate) fn new(element: impl Into<String>, message: impl Into<String>) -> Self {
        ArticulationError {
            element: element.into(),
            file: None,
            line: None,
            message: message.into(),
        }
    }
}

impl fmt::Display for ArticulationError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (&self.file, self.line) {
            (Some(file), Some(line)) => write!(f, "{file}:{line}: ")?,
            (Some(file), None) => write!(f, "{file}: ")?,
            (None, Some(line)) => write!(f, "line {line}: ")?,
            (None, None) => {}
        }
        write!(f, "{}: {}", self.element, self.message)
    }
}

impl std::error::Error for ArticulationError {}

/// Builds articulated bodies: trees of links joined by joints. Several trees (roots) make
/// several articulations in one model.
///
/// ```
/// use adflex_kernels::articulation::*;
/// use adflex_runtime::{Tape, Vec3};
///
/// // A pendulum: a 1 kg point mass 0.5 m below a revolute joint about y.
/// let mut b = ArticulationBuilder::new();
/// b.add_link(
///     "pole",
///     None,
///     Joint::revolute(Vec3::y()),
///     Inertial::point(1.0, Vec3::new(0.0, 0.0, -0.5)),
/// );
/// let model = b.finalize::<f64>().unwrap();
/// let mut tape = Tape::new();
/// let q = model.state().q;
/// let m = model.mass_matrix(&mut tape, &q);
/// assert!((m.get(0) - 0.25).abs() < 1e-12); // m l^2
/// ```
#[derive(Clone, Debug)]
pub struct ArticulationBuilder {
    links: Vec<LinkDesc>,
    /// Contact shapes (spheres, capsules, boxes on links).
    shapes: Vec<ContactShape>,
    /// Pairs of links whose shapes never touch each other.
    excluded: Vec<(LinkId, LinkId)>,
    /// The ground the contact shapes touch (`None`: no contact at all), and the contact law
    /// of every contact.
    pub ground: Option<GroundContact<f64>>,
    /// Which shapes touch the ground (default: every default shape; [`ContactFilter::NONE`]
    /// for no floor, the ground's law then serving the links' contacts only).
    pub ground_filter: ContactFilter,
    /// Muscle-tendon units.
    muscles: Vec<Muscle>,
    /// Actuators on joints.
    actuators: Vec<Actuator>,
    /// Passive fixed tendons.
    tendon_springs: Vec<TendonSpring>,
    /// Whether contact shapes of different links touch each other too (with the ground's
    /// law; default false), as their [`ContactFilter`]s say. Links welded together by fixed
    /// joints, links joined directly (after welding) and excluded pairs never touch.
    pub link_contact: bool,
    /// Gravity (m/s^2) of the worlds not added by [`ArticulationBuilder::add_world`] (which
    /// keep their own builder's); default `(0, 0, -9.81)` (z up, as URDF and MJCF).
    pub gravity: Vec3<f64>,
    /// Stiffness of the joint limits (N m/rad or N/m), for the joints without a
    /// [`Joint::limit_time_constant`] (those scale theirs by their inertia).
    pub limit_ke: f64,
    /// Damping of the joint limits while violated.
    pub limit_kd: f64,
    /// Whether a step keeps the time constant of a [`Joint::limit_time_constant`] limit at
    /// least twice its `dt` (default true, MuJoCo's `refsafe` flag): the limit is then stable
    /// at any step, softer at steps longer than half its time constant.
    pub limit_refsafe: bool,
    /// Whether an `Euler` step integrates the joint damping implicitly (default true, as
    /// MuJoCo's Euler integrator with its `eulerdamp` flag): stable for any damping at any
    /// step. (`ImplicitFast` always does, `Rk4` never: see [`ArticulationIntegrator`].)
    pub implicit_damping: bool,
    /// How a step integrates (default [`ArticulationIntegrator::Euler`]).
    pub integrator: ArticulationIntegrator,
    /// A fluid around the links (default `None`): drag of MuJoCo's inertia-box model (see
    /// [`fluid`](super::fluid)).
    pub fluid: Option<Fluid>,
    /// The worlds: each one's first link and gravity (`None`: [`ArticulationBuilder::gravity`]).
    /// World 0 starts at link 0; links added with [`ArticulationBuilder::add_link`] go to the
    /// last world.
    worlds: Vec<(usize, Option<Vec3<f64>>)>,
    /// Whether `add_world` was called: an empty builder's first `add_world` fills world 0,
    /// later ones (even of empty worlds) add worlds.
    world_added: bool,
    /// The first world added whose shared settings (ground, link contact, limit law) differ
    /// from this builder's: [`ArticulationBuilder::finalize`] refuses it.
    mismatch: Option<String>,
}

impl Default for ArticulationBuilder {
    fn default() -> Self {
        Self::new()
    }
}

impl ArticulationBuilder {
    /// An empty builder with gravity `(0, 0, -9.81)`.
    pub fn new() -> Self {
        ArticulationBuilder {
            links: Vec::new(),
            shapes: Vec::new(),
            excluded: Vec::new(),
            ground: None,
            ground_filter: ContactFilter::default(),
            link_contact: false,
            muscles: Vec::new(),
            actuators: Vec::new(),
            tendon_springs: Vec::new(),
            gravity: Vec3::new(0.0, 0.0, -9.81),
            limit_ke: 1e4,
            limit_kd: 10.0,
            limit_refsafe: true,
            implicit_damping: true,
            integrator: ArticulationIntegrator::Euler,
            fluid: None,
            worlds: vec![(0, None)],
            world_added: false,
            mismatch: None,
        }
    }

    /// Adds a link joined to `parent` (or to the world) by `joint`. Everything is checked by
    /// [`ArticulationBuilder::finalize`].
    pub fn add_link(
        &mut self,
        name: impl Into<String>,
        parent: Option<LinkId>,
        joint: Joint,
        inertial: Inertial,
    ) -> LinkId {
        self.links.push(LinkDesc {
            name: name.into(),
            parent,
            joint,
            inertial,
            gravcomp: 0.0,
        });
        LinkId(self.links.len() - 1)
    }

    /// Adds a contact sphere of `radius` (m; 0 for a point) centred at `centre` in `link`'s
    /// frame; returns its index among the contact shapes. It touches the ground
    /// ([`ArticulationBuilder::ground`]) and, with [`ArticulationBuilder::link_contact`], the
    /// shapes of other links.
    pub fn add_contact_sphere(&mut self, link: LinkId, centre: Vec3<f64>, radius: f64) -> usize {
        self.add_contact_shape(link, &Pose::at(centre), &GeomShape::Sphere(radius))
            .expect("a sphere is a contact shape")
    }

    /// Adds a box of half extents `half` at `pose` in `link`'s frame; returns its index. It
    /// touches the ground by its corners, spheres and capsules by its faces, other boxes by
    /// its edges.
    pub fn add_contact_box(&mut self, link: LinkId, pose: &Pose, half: Vec3<f64>) -> usize {
        self.add_contact_shape(link, pose, &GeomShape::Box(half))
            .expect("a box is a contact shape")
    }

    /// Adds `shape` at `pose` in `link`'s frame as a contact shape (a capsule or cylinder
    /// along the pose's z), with the default [`ContactFilter`]; returns its index. A plane adds
    /// nothing (`None`). A cylinder touches the ground, particles, spheres and capsules, an
    /// ellipsoid the ground only: building a model in which one would touch another link's
    /// shape is an error.
    pub fn add_contact_shape(
        &mut self,
        link: LinkId,
        pose: &Pose,
        shape: &GeomShape,
    ) -> Option<usize> {
        match shape {
            GeomShape::Plane => None,
            _ => {
                self.shapes.push(ContactShape {
                    link,
                    pose: *pose,
                    shape: *shape,
                    filter: ContactFilter::default(),
                    friction: None,
                });
                Some(self.shapes.len() - 1)
            }
        }
    }

    /// Adds a capsule of `radius` whose axis runs from `a` to `b` (link frame); returns its
    /// index. It touches the ground by its end spheres (exact against a plane), other shapes
    /// along its whole axis.
    pub fn add_contact_capsule(
        &mut self,
        link: LinkId,
        a: Vec3<f64>,
        b: Vec3<f64>,
        radius: f64,
    ) -> usize {
        let axis = b - a;
        let pose = match axis.norm() > 0.0 {
            true => Pose::new(0.5 * (a + b), from_to(&Vec3::z(), &axis.normalize())),
            false => Pose::at(a),
        };
        self.add_contact_shape(link, &pose, &GeomShape::Capsule(radius, 0.5 * axis.norm()))
            .expect("a capsule is a contact shape")
    }

    /// Sets which other shapes contact shape `shape` touches (MuJoCo's `contype` and
    /// `conaffinity`).
    ///
    /// # Panics
    /// If there is no shape `shape`.
    pub fn set_contact_filter(&mut self, shape: usize, filter: ContactFilter) {
        let n = self.shapes.len();
        self.shapes
            .get_mut(shape)
            .unwrap_or_else(|| panic!("set_contact_filter: no contact shape {shape} (of {n})"))
            .filter = filter;
    }

    /// Sets contact shape `shape`'s own friction coefficient (without one it has the
    /// ground's). A contact's friction is the larger of its two sides', as MuJoCo's: the
    /// ground's and the shape's against the ground, the two shapes' between links.
    ///
    /// # Panics
    /// If there is no shape `shape`. (A coefficient that is negative or not finite is an
    /// error when the model is built.)
    pub fn set_contact_friction(&mut self, shape: usize, mu: f64) {
        let n = self.shapes.len();
        self.shapes
            .get_mut(shape)
            .unwrap_or_else(|| panic!("set_contact_friction: no contact shape {shape} (of {n})"))
            .friction = Some(mu);
    }

    /// The shapes of links `a` and `b` never touch each other (MuJoCo's `<exclude>`; the
    /// links' own shapes only, not those of links welded to them).
    pub fn exclude_contact(&mut self, a: LinkId, b: LinkId) {
        self.excluded.push((a, b));
    }

    /// The contact shapes.
    pub fn contact_shapes(&self) -> &[ContactShape] {
        &self.shapes
    }

    /// The pairs of links excluded from touching each other.
    pub fn excluded_contacts(&self) -> &[(LinkId, LinkId)] {
        &self.excluded
    }

    /// Adds a muscle-tendon unit; returns its index (its activation's in
    /// [`ArticulationControl::activation`](super::ArticulationControl)).
    pub fn add_muscle(&mut self, muscle: Muscle) -> usize {
        self.muscles.push(muscle);
        self.muscles.len() - 1
    }

    /// The muscles.
    pub fn muscles(&self) -> &[Muscle] {
        &self.muscles
    }

    /// Adds an actuator on a joint; returns its index (its control's in
    /// [`ArticulationControl::ctrl`](super::ArticulationControl)). Add a world's actuators
    /// before the next world's.
    pub fn add_actuator(&mut self, actuator: Actuator) -> usize {
        self.actuators.push(actuator);
        self.actuators.len() - 1
    }

    /// The actuators.
    pub fn actuators(&self) -> &[Actuator] {
        &self.actuators
    }

    /// Adds a passive fixed tendon (a spring and damper on a combination of joints); returns
    /// its index.
    pub fn add_tendon_spring(&mut self, tendon: TendonSpring) -> usize {
        self.tendon_springs.push(tendon);
        self.tendon_springs.len() - 1
    }

    /// The passive fixed tendons.
    pub fn tendon_springs(&self) -> &[TendonSpring] {
        &self.tendon_springs
    }

    /// The spheres by which the contact shapes touch the ground (link, centre in the link
    /// frame, radius, friction; [`ContactShape::ground_spheres`]), of the shapes whose filter
    /// touches [`ArticulationBuilder::ground_filter`]. The friction is the larger of the
    /// ground's and the shape's own.
    pub fn contacts(&self) -> Vec<(LinkId, Vec3<f64>, f64, f64)> {
        self.shapes
            .iter()
            .filter(|c| c.filter.touches(&self.ground_filter))
            .flat_map(|c| {
                let mu = self.contact_friction(c, None);
                let spheres = c.ground_spheres().into_iter();
                spheres.map(move |(p, r)| (c.link, p, r, mu))
            })
            .collect()
    }

    /// The points by which the cylinders and ellipsoids touch the ground (link, the shape,
    /// the point's [`support_offset`](super::contact::support_offset) variant, friction), of
    /// the shapes whose filter touches [`ArticulationBuilder::ground_filter`].
    pub fn support_contacts(&self) -> Vec<(LinkId, &ContactShape, u32, f64)> {
        self.shapes
            .iter()
            .filter(|c| c.filter.touches(&self.ground_filter))
            .flat_map(|c| {
                let mu = self.contact_friction(c, None);
                c.ground_supports().iter().map(move |&v| (c.link, c, v, mu))
            })
            .collect()
    }

    /// The friction of a contact of shape `a` with shape `b` (`None`: the ground): the larger
    /// of the two sides', a shape without its own having the ground's.
    pub(crate) fn contact_friction(&self, a: &ContactShape, b: Option<&ContactShape>) -> f64 {
        let ground = self.ground.map_or(GroundContact::default().mu, |g| g.mu);
        let own = |c: Option<&ContactShape>| c.and_then(|c| c.friction).unwrap_or(ground);
        own(Some(a)).max(own(b))
    }

    /// The links described so far.
    pub fn links(&self) -> &[LinkDesc] {
        &self.links
    }

    /// The links described so far, to edit (e.g. a loaded robot's gains or damping).
    pub fn links_mut(&mut self) -> &mut [LinkDesc] {
        &mut self.links
    }

    /// The actuators, to edit (as [`ArticulationBuilder::actuators`]).
    pub fn actuators_mut(&mut self) -> &mut [Actuator] {
        &mut self.actuators
    }

    /// The passive tendons, to edit (as [`ArticulationBuilder::tendon_springs`]).
    pub fn tendon_springs_mut(&mut self) -> &mut [TendonSpring] {
        &mut self.tendon_springs
    }

    /// The link called `name`.
    pub fn find(&self, name: &str) -> Option<LinkId> {
        self.links.iter().position(|l| l.name == name).map(LinkId)
    }

    /// Adds every link of `other` to the last world (its articulations become more
    /// articulations of this world; its own worlds, if it has several, merge into this one);
    /// returns the id of `other`'s first link here.
    pub fn add_builder(&mut self, other: &ArticulationBuilder) -> LinkId {
        let base = self.links.len();
        // The step's settings come with the first links; later ones must agree.
        let step = |b: &ArticulationBuilder| (b.integrator, b.implicit_damping, b.fluid);
        if base == 0 && !self.world_added {
            (self.integrator, self.implicit_damping, self.fluid) = step(other);
        } else if step(self) != step(other) && self.mismatch.is_none() {
            self.mismatch = Some(format!(
                "add_builder: the added builder's integrator, implicit_damping and fluid {:?} \
                 differ from this builder's {:?}; set them alike",
                step(other),
                step(self)
            ));
        }
        for l in &other.links {
            let mut l = l.clone();
            l.parent = l.parent.map(|p| LinkId(p.0 + base));
            self.links.push(l);
        }
        let shift = |l: LinkId| LinkId(l.0 + base);
        for c in &other.shapes {
            self.shapes.push(ContactShape {
                link: shift(c.link),
                ..*c
            });
        }
        for &(a, b) in &other.excluded {
            self.excluded.push((shift(a), shift(b)));
        }
        for m in &other.muscles {
            let mut m = m.clone();
            m.origin.0 = LinkId(m.origin.0 .0 + base);
            m.insertion.0 = LinkId(m.insertion.0 .0 + base);
            self.muscles.push(m);
        }
        for a in &other.actuators {
            self.actuators.push(Actuator {
                transmission: a.transmission.iter().map(|&(l, c)| (shift(l), c)).collect(),
                ..a.clone()
            });
        }
        for t in &other.tendon_springs {
            self.tendon_springs.push(TendonSpring {
                joints: t.joints.iter().map(|&(l, c)| (shift(l), c)).collect(),
                ..t.clone()
            });
        }
        if self.ground.is_none() {
            // The other's contact settings come with its ground (an MJCF file without a plane
            // brings a law but no floor, and its links touching each other).
            self.ground = other.ground;
            self.ground_filter = other.ground_filter;
            self.link_contact |= other.link_contact;
        }
        LinkId(base)
    }

    /// Adds the worlds of `other` (usually one: a robot, a scene) as new worlds of this
    /// builder, each with its own gravity (`other`'s); returns the index of the first. Worlds
    /// share the ground's law and the joint-limit law but never touch each other, and each is
    /// simulated in its own frame: they need no spacing in space, and a world's results are
    /// the same bits whatever the other worlds are (see [`Articulations::worlds`]).
    ///
    /// An empty builder's first `add_world` fills world 0. Links added afterwards with
    /// [`ArticulationBuilder::add_link`] go to the last world.
    ///
    /// ```
    /// use adflex_kernels::articulation::*;
    /// use adflex_runtime::Vec3;
    ///
    /// let mut pendulum = ArticulationBuilder::new();
    /// pendulum.add_link("pole", None, Joint::revolute(Vec3::y()),
    ///     Inertial::point(1.0, Vec3::new(0.0, 0.0, 0.5)));
    /// let mut moon = pendulum.clone();
    /// moon.gravity = Vec3::new(0.0, 0.0, -1.62);
    ///
    /// let mut b = ArticulationBuilder::new();
    /// assert_eq!(b.add_world(&pendulum), 0);
    /// assert_eq!(b.add_world(&moon), 1);
    /// let model = b.finalize::<f64>().unwrap();
    /// assert_eq!(model.worlds.len(), 2);
    /// assert_eq!(model.gravity.get(1).z, -1.62);
    /// ```
    pub fn add_world(&mut self, other: &ArticulationBuilder) -> usize {
        let first = if self.links.is_empty() && !self.world_added {
            // The first world sets the laws the worlds share.
            self.worlds.clear();
            self.ground = other.ground;
            self.ground_filter = other.ground_filter;
            self.link_contact = other.link_contact;
            self.limit_ke = other.limit_ke;
            self.limit_kd = other.limit_kd;
            self.limit_refsafe = other.limit_refsafe;
            self.implicit_damping = other.implicit_damping;
            self.integrator = other.integrator;
            self.fluid = other.fluid;
            0
        } else {
            self.worlds.len()
        };
        self.world_added = true;
        // A world without a ground of its own (nothing touches) takes the model's.
        let with_ground = other.ground.is_some();
        let shared = |b: &ArticulationBuilder| {
            let ground = match with_ground {
                true => format!("ground {:?}, ", b.ground),
                false => String::new(),
            };
            format!(
                "{ground}ground_filter {:?}, link_contact {}, limit_ke {}, limit_kd {}, \
                 limit_refsafe {}, implicit_damping {}, integrator {:?}, fluid {:?}",
                b.ground_filter,
                b.link_contact,
                b.limit_ke,
                b.limit_kd,
                b.limit_refsafe,
                b.implicit_damping,
                b.integrator,
                b.fluid
            )
        };
        if self.mismatch.is_none() && shared(self) != shared(other) {
            self.mismatch = Some(format!(
                "world {first} was added with other shared settings ({}) than the model's ({}): \
                 the ground, the contact and limit laws, the integrator and the fluid are the \
                 same in every world",
                shared(other),
                shared(self)
            ));
        }
        for k in 0..other.worlds.len() {
            self.append_world(other, k);
        }
        first
    }

    /// `n` copies of this builder's worlds, one after the other (for `n` copies of a robot
    /// or a scene: [`ArticulationBuilder::add_world`] `n` times).
    ///
    /// # Panics
    /// If `n` is 0.
    pub fn replicate(&self, n: usize) -> ArticulationBuilder {
        assert!(
            n > 0,
            "ArticulationBuilder::replicate(0): a model needs a world"
        );
        let mut b = self.clone_settings();
        for _ in 0..n {
            b.add_world(self);
        }
        b
    }

    /// A builder with only the worlds in `worlds` (their links, contacts, muscles and gravity;
    /// the same ground and laws): one process's or thread's share of a scene whose worlds are
    /// spread over several. World `worlds.start` of this builder is world 0 of the new one;
    /// each world's results are the same bits in either (worlds never interact).
    ///
    /// # Panics
    /// If the range is empty or past the last world.
    pub fn worlds_in(&self, worlds: Range<usize>) -> ArticulationBuilder {
        assert!(
            !worlds.is_empty() && worlds.end <= self.worlds.len(),
            "ArticulationBuilder::worlds_in({worlds:?}): the builder has {} worlds",
            self.worlds.len()
        );
        let mut b = self.clone_settings();
        b.worlds.clear();
        b.world_added = true;
        for k in worlds {
            b.append_world(self, k);
        }
        b
    }

    /// Appends world `k` of `other` as a new world: its links, contacts, muscles and actuators with
    /// their link ids shifted, and its gravity.
    fn append_world(&mut self, other: &ArticulationBuilder, k: usize) {
        let (start, g) = other.worlds[k];
        let end = other.worlds.get(k + 1).map_or(other.links.len(), |w| w.0);
        let base = self.links.len();
        self.worlds.push((base, Some(g.unwrap_or(other.gravity))));
        let remap = |l: LinkId| LinkId(l.0 - start + base);
        for l in &other.links[start..end] {
            let mut l = l.clone();
            l.parent = l.parent.map(remap);
            self.links.push(l);
        }
        let inside = |l: LinkId| (start..end).contains(&l.0);
        for c in other.shapes.iter().filter(|c| inside(c.link)) {
            self.shapes.push(ContactShape {
                link: remap(c.link),
                ..*c
            });
        }
        for &(a, b) in other.excluded.iter().filter(|p| inside(p.0) && inside(p.1)) {
            self.excluded.push((remap(a), remap(b)));
        }
        for m in other.muscles.iter().filter(|m| inside(m.origin.0)) {
            let mut m = m.clone();
            m.origin.0 = remap(m.origin.0);
            // (An insertion outside the world wraps to an index finalize refuses.)
            m.insertion.0 = LinkId((m.insertion.0 .0 + base).wrapping_sub(start));
            self.muscles.push(m);
        }
        // (A joint outside the world wraps to an index finalize refuses.)
        let shift = |l: LinkId| LinkId((l.0 + base).wrapping_sub(start));
        for a in other.actuators.iter() {
            if a.transmission.first().is_some_and(|j| inside(j.0)) {
                self.actuators.push(Actuator {
                    transmission: a.transmission.iter().map(|&(l, c)| (shift(l), c)).collect(),
                    ..a.clone()
                });
            }
        }
        for t in other.tendon_springs.iter() {
            if t.joints.first().is_some_and(|j| inside(j.0)) {
                self.tendon_springs.push(TendonSpring {
                    joints: t.joints.iter().map(|&(l, c)| (shift(l), c)).collect(),
                    ..t.clone()
                });
            }
        }
    }

    /// This builder's settings (ground, laws, gravity) without links.
    fn clone_settings(&self) -> ArticulationBuilder {
        ArticulationBuilder {
            links: Vec::new(),
            shapes: Vec::new(),
            excluded: Vec::new(),
            muscles: Vec::new(),
            actuators: Vec::new(),
            tendon_springs: Vec::new(),
            worlds: vec![(0, None)],
            world_added: false,
            mismatch: self.mismatch.clone(),
            ground: self.ground,
            ground_filter: self.ground_filter,
            link_contact: self.link_contact,
            gravity: self.gravity,
            limit_ke: self.limit_ke,
            limit_kd: self.limit_kd,
            limit_refsafe: self.limit_refsafe,
            implicit_damping: self.implicit_damping,
            integrator: self.integrator,
            fluid: self.fluid,
        }
    }

    /// Number of worlds (1 unless [`ArticulationBuilder::add_world`] added more).
    pub fn world_count(&self) -> usize {
        self.worlds.len()
    }

    /// The first world added with other shared settings, if any.
    pub(crate) fn mismatch(&self) -> Option<&str> {
        self.mismatch.as_deref()
    }

    /// The world of each link, and each world's gravity.
    pub(crate) fn world_layout(&self) -> (Vec<usize>, Vec<Vec3<f64>>) {
        let mut of = vec![0; self.links.len()];
        for (k, &(start, _)) in self.worlds.iter().enumerate() {
            let end = self.worlds.get(k + 1).map_or(of.len(), |w| w.0);
            of[start..end].fill(k);
        }
        let g = self
            .worlds
            .iter()
            .map(|w| w.1.unwrap_or(self.gravity))
            .collect();
        (of, g)
    }
}

/// Where an articulation's links, coordinates and velocities are in the model's arrays.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ArticulationInfo {
    /// Its links (its root first).
    pub links: Range<usize>,
    /// Its coordinates in `q`.
    pub q: Range<usize>,
    /// Its velocities in `qd`.
    pub dofs: Range<usize>,
    /// Where its mass-matrix block (row-major, `dofs.len()` squared) starts.
    pub m_offset: usize,
}

/// Where a world's links, articulations, coordinates and velocities are in the model's arrays
/// (each a contiguous range).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct WorldInfo {
    /// Its links.
    pub links: Range<usize>,
    /// Its articulations.
    pub articulations: Range<usize>,
    /// Its coordinates in `q`.
    pub q: Range<usize>,
    /// Its velocities in `qd`.
    pub dofs: Range<usize>,
    /// Its actuators (their controls in
    /// [`ArticulationControl::ctrl`](super::ArticulationControl)).
    pub actuators: Range<usize>,
}

/// A link of the model: names, joint and where its joint's coordinates are.
#[derive(Clone, Debug, PartialEq)]
pub struct LinkInfo {
    /// The link's name.
    pub name: String,
    /// Its joint's name.
    pub joint: String,
    /// Its joint's kind.
    pub kind: JointType,
    /// Its parent (`None`: the world).
    pub parent: Option<usize>,
    /// Its joint's coordinates in `q`.
    pub q: Range<usize>,
    /// Its joint's velocities in `qd`.
    pub dofs: Range<usize>,
    /// The articulation it belongs to.
    pub articulation: usize,
}

/// Articulated bodies ready to simulate: the topology as index arrays for the kernels, the
/// joints and the mass properties. Build with [`ArticulationBuilder`], or load with
/// [`urdf`](super::urdf) or [`mjcf`](super::mjcf).
///
/// The links are ordered parents first. Every array the kernels read is a field, so a
/// parameter (a mass, an inertia, a joint placement) can require grad and be optimized.
///
/// Arrays are handles: a `clone()` of the model shares its parameter arrays with the original
/// (an edit through one shows in both, as an optimizer's parameters should). For an independent
/// model, finalize the builder again.
#[derive(Clone, Debug)]
pub struct Articulations<R: Real> {
    /// The links.
    pub links: Vec<LinkInfo>,
    /// The articulations.
    pub articulations: Vec<ArticulationInfo>,
    /// The worlds ([`ArticulationBuilder::add_world`]; one unless it added more). Worlds
    /// never interact: one launch steps them all, and a world's results are bitwise the same
    /// whatever the number, order and content of the others and the thread count.
    pub worlds: Vec<WorldInfo>,
    /// Per link: its world.
    pub link_world: Array<u32>,
    /// Per coordinate: its world.
    pub q_world: Array<u32>,
    /// Per velocity: its world.
    pub dof_world: Array<u32>,
    /// Number of coordinates.
    pub n_q: usize,
    /// Number of velocities (degrees of freedom).
    pub n_dof: usize,
    /// Gravity per world (m/s^2): a parameter like the others (it can require grad).
    pub gravity: Array<Vec3<R>>,
    /// Stiffness of the joint limits.
    pub limit_ke: R,
    /// Damping of the joint limits while violated.
    pub limit_kd: R,
    /// Whether a step keeps a time-constant limit's time constant at least twice its `dt`
    /// ([`ArticulationBuilder::limit_refsafe`]).
    pub limit_refsafe: bool,
    /// Whether a step integrates the joint damping implicitly
    /// ([`ArticulationBuilder::implicit_damping`]).
    pub implicit_damping: bool,
    /// How a step integrates ([`ArticulationBuilder::integrator`]).
    pub integrator: ArticulationIntegrator,
    /// Whether a fluid acts ([`ArticulationBuilder::fluid`]); its density (kg/m^3), viscosity
    /// (Pa s) and wind (m/s) are one-element arrays, which can require gradients.
    pub fluid_on: bool,
    /// See [`fluid_on`](Self::fluid_on).
    pub fluid_density: Array<R>,
    /// See [`fluid_on`](Self::fluid_on).
    pub fluid_viscosity: Array<R>,
    /// See [`fluid_on`](Self::fluid_on).
    pub wind: Array<Vec3<R>>,
    /// Per link with mass: the link, its centre of mass (link frame), principal axes (a
    /// rotation in the link frame) and the full sides of its inertia box, for the fluid.
    pub fluid_link: Array<u32>,
    /// See [`fluid_link`](Self::fluid_link).
    pub fluid_com: Array<Vec3<R>>,
    /// See [`fluid_link`](Self::fluid_link).
    pub fluid_rot: Array<Quat<R>>,
    /// See [`fluid_link`](Self::fluid_link).
    pub fluid_box: Array<Vec3<R>>,
    /// Per link with gravity compensation ([`LinkDesc::gravcomp`]): the link.
    pub gravcomp_link: Array<u32>,
    /// See [`gravcomp_link`](Self::gravcomp_link): the fraction of the link's weight (its
    /// `mass` entry, read at each step) compensated. Can require gradients.
    pub gravcomp: Array<R>,
    /// The initial configuration ([`Articulations::state`] starts there): each joint's
    /// [`Joint::initial`], or zeros and identity quaternions.
    pub q0: Vec<R>,
    /// Per link: its chain from the root to itself, `chain[chain_start[l]..chain_start[l+1]]`.
    pub chain_start: Array<u32>,
    /// See `chain_start`.
    pub chain: Array<u32>,
    /// Per link: itself then its descendants, `subtree[subtree_start[l]..subtree_start[l+1]]`.
    pub subtree_start: Array<u32>,
    /// See `subtree_start`.
    pub subtree: Array<u32>,
    /// Per link: its joint's kind (`JointType` code).
    pub joint_type: Array<u32>,
    /// Per link: its joint's first coordinate.
    pub q_start: Array<u32>,
    /// Per link, and one past the end: its joint's first velocity.
    pub qd_start: Array<u32>,
    /// Per link: the joint frame in the parent's frame at `q = 0` (m).
    pub joint_pos: Array<Vec3<R>>,
    /// Its rotation.
    pub joint_rot: Array<Quat<R>>,
    /// Per link: the joint's unit axis (joint frame).
    pub joint_axis: Array<Vec3<R>>,
    /// Per link: mass (kg).
    pub mass: Array<R>,
    /// Per link: centre of mass in the link frame (m).
    pub com: Array<Vec3<R>>,
    /// Per link: inertia about the centre of mass, link axes (kg m^2).
    pub inertia: Array<Mat33<R>>,
    /// Per velocity: its link.
    pub dof_link: Array<u32>,
    /// Per velocity: its index within its joint.
    pub dof_index: Array<u32>,
    /// Per velocity: its coordinate, for revolute and prismatic joints.
    pub dof_q: Array<u32>,
    /// Per velocity: 1 for revolute and prismatic joints.
    pub dof_scalar: Array<u32>,
    /// Per velocity: its articulation's first velocity.
    pub dof_art_start: Array<u32>,
    /// Per velocity: where its row of the mass matrix starts.
    pub dof_m_row: Array<u32>,
    /// Per velocity: armature.
    pub armature: Array<R>,
    /// Per velocity: viscous damping.
    pub damping: Array<R>,
    /// Per velocity: the passive spring's stiffness (revolute and prismatic joints).
    pub stiffness: Array<R>,
    /// Per velocity: the passive spring's rest position.
    pub spring_ref: Array<R>,
    /// Per velocity: PD position gain.
    pub kp: Array<R>,
    /// Per velocity: PD velocity gain.
    pub kv: Array<R>,
    /// Per velocity: a time-constant limit's stiffness and damping at full impedance, `m /
    /// (dmax tc zeta)^2` and `2 m / (dmax tc)` ([`Joint::limit_time_constant`], `m` is
    /// [`limit_m`](Self::limit_m)); 0 for the other joints, whose limits use `limit_ke`,
    /// `limit_kd`.
    pub limit_k: Array<R>,
    /// See [`limit_k`](Self::limit_k).
    pub limit_b: Array<R>,
    /// Per velocity: the joint's inertia as a time-constant limit sees it, `1 / (M^-1)[d][d]`
    /// at the neutral configuration (MuJoCo's `1 / dof_invweight0`): it scales the limit's
    /// regularization (see [`Joint::limit_time_constant`]).
    pub limit_m: Array<R>,
    /// Per velocity: the limit's impedance `(dmin, dmax, width)` ([`Joint::limit_impedance`]).
    pub limit_imp: Array<Vec3<R>>,
    /// Per velocity: lower limit (`-inf` when none).
    pub lower: Array<R>,
    /// Per velocity: upper limit (`inf` when none).
    pub upper: Array<R>,
    /// Length of the mass-matrix array (the sum of the blocks' sizes).
    pub m_len: usize,
    /// Every contact shape of the links, as particles touch them.
    pub shapes: super::contact::LinkShapes<R>,
    /// Per contact sphere: its link.
    pub contact_link: Array<u32>,
    /// Per contact sphere: its centre in the link frame (m).
    pub contact_pos: Array<Vec3<R>>,
    /// Per contact sphere: its radius (m).
    pub contact_radius: Array<R>,
    /// Per contact sphere: its friction coefficient (the larger of the ground's and its
    /// shape's; [`ContactShape::friction`]). Can require gradients.
    pub contact_mu: Array<R>,
    /// Per ground contact point of a cylinder or an ellipsoid
    /// ([`ArticulationBuilder::support_contacts`]): its link.
    pub support_link: Array<u32>,
    /// Per such point: its [`support_offset`](super::contact::support_offset) variant.
    pub support_variant: Array<u32>,
    /// Per such point: its shape's centre in the link frame (m).
    pub support_pos: Array<Vec3<R>>,
    /// Per such point: its shape's rotation in the link frame.
    pub support_rot: Array<Quat<R>>,
    /// Per such point: its shape's size (m; an ellipsoid's semi-axes, a cylinder's radius and
    /// half-length).
    pub support_size: Array<Vec3<R>>,
    /// Per such point: its friction coefficient, as `contact_mu`. Can require gradients.
    pub support_mu: Array<R>,
    /// The ground and its contact law (`None`: no contact). Its `mu` was read when the model
    /// was built: the friction the kernels use is in `contact_mu`, `support_mu`,
    /// `capsule_pair_mu`, `box_pair_mu` and `cylinder_pair_mu`.
    pub ground: Option<GroundContact<R>>,
    /// Per sphere or capsule that touches another link's shapes (and per edge of a box that
    /// touches another box, of radius 0): its link, the ends of its axis in the link frame
    /// (m), its radius (m). Set when [`ArticulationBuilder::link_contact`] is.
    pub seg_link: Array<u32>,
    /// See `seg_link`.
    pub seg_a: Array<Vec3<R>>,
    /// See `seg_link`.
    pub seg_b: Array<Vec3<R>>,
    /// See `seg_link`.
    pub seg_radius: Array<R>,
    /// Per box that touches another link's shapes: its link, centre and rotation in the link
    /// frame, half extents (m).
    pub box_link: Array<u32>,
    /// See `box_link`.
    pub box_pos: Array<Vec3<R>>,
    /// See `box_link`.
    pub box_rot: Array<Quat<R>>,
    /// See `box_link`.
    pub box_half: Array<Vec3<R>>,
    /// Pairs of segments that touch (indices into `seg_*`), with the ground's law.
    pub capsule_pairs: Array<[u32; 2]>,
    /// Per pair in `capsule_pairs`: its friction coefficient (the larger of its two shapes';
    /// [`ContactShape::friction`]). Can require gradients.
    pub capsule_pair_mu: Array<R>,
    /// Pairs of a segment and a box that touch (indices into `seg_*` and `box_*`).
    pub box_pairs: Array<[u32; 2]>,
    /// Per link: 1 if it is fixed to the world (its root welded to it by fixed joints), else
    /// 0. An implicit step takes the friction of a contact pair with one side fixed as a
    /// damper on the other side's link ([`GroundContact::implicit_friction`]). Empty when no
    /// pair has a fixed side.
    pub link_fixed: Array<u32>,
    /// Per pair in `box_pairs`: its friction coefficient, as `capsule_pair_mu`.
    pub box_pair_mu: Array<R>,
    /// Per cylinder that touches another link's spheres or capsules: its link, centre and
    /// rotation in the link frame, radius and half-length (m; then 0).
    pub cylinder_link: Array<u32>,
    /// See `cylinder_link`.
    pub cylinder_pos: Array<Vec3<R>>,
    /// See `cylinder_link`.
    pub cylinder_rot: Array<Quat<R>>,
    /// See `cylinder_link`.
    pub cylinder_size: Array<Vec3<R>>,
    /// Pairs of a segment (a sphere or capsule) and a cylinder that touch (indices into
    /// `seg_*` and `cylinder_*`).
    pub cylinder_pairs: Array<[u32; 2]>,
    /// Per pair in `cylinder_pairs`: its friction coefficient, as `capsule_pair_mu`.
    pub cylinder_pair_mu: Array<R>,
    /// Per muscle: origin link and point, insertion link and point, `f_max`, `l_opt`,
    /// `tendon_slack`, `v_max` (see [`Muscle`]).
    pub muscle_origin_link: Array<u32>,
    /// See `muscle_origin_link`.
    pub muscle_origin_pos: Array<Vec3<R>>,
    /// See `muscle_origin_link`.
    pub muscle_insertion_link: Array<u32>,
    /// See `muscle_origin_link`.
    pub muscle_insertion_pos: Array<Vec3<R>>,
    /// See `muscle_origin_link`.
    pub muscle_f_max: Array<R>,
    /// See `muscle_origin_link`.
    pub muscle_l_opt: Array<R>,
    /// See `muscle_origin_link`.
    pub muscle_tendon_slack: Array<R>,
    /// See `muscle_origin_link`.
    pub muscle_v_max: Array<R>,
    /// Muscle names.
    pub muscle_names: Vec<String>,
    /// Per actuator ([`Actuator`]): where its joints start in `act_dof`, `act_coord` and
    /// `act_coef` (one more entry than actuators).
    pub act_start: Array<u32>,
    /// Per joint of an actuator: its degree of freedom, its coordinate in `q` and its
    /// coefficient in the actuator's length (can require gradients).
    pub act_dof: Array<u32>,
    /// See `act_dof`.
    pub act_coord: Array<u32>,
    /// See `act_dof`.
    pub act_coef: Array<R>,
    /// Per actuator: gear, gain and bias (constant, length and speed terms), and which
    /// ranges clamp (bit 0 the control, bit 1 the force) to what. The real-valued ones can
    /// require gradients.
    pub act_gear: Array<R>,
    /// See `act_gear`.
    pub act_gain: Array<Vec3<R>>,
    /// See `act_gear`.
    pub act_bias: Array<Vec3<R>>,
    /// See `act_gear`.
    pub act_limited: Array<u32>,
    /// See `act_gear`.
    pub act_ctrl_lo: Array<R>,
    /// See `act_gear`.
    pub act_ctrl_hi: Array<R>,
    /// See `act_gear`.
    pub act_force_lo: Array<R>,
    /// See `act_gear`.
    pub act_force_hi: Array<R>,
    /// Actuator names.
    pub actuator_names: Vec<String>,
    /// Per passive tendon ([`TendonSpring`]): where its joints start in `tendon_dof`,
    /// `tendon_coord` and `tendon_coef` (one more entry than tendons).
    pub tendon_start: Array<u32>,
    /// Per joint of a passive tendon: its degree of freedom, coordinate and coefficient.
    pub tendon_dof: Array<u32>,
    /// See `tendon_dof`.
    pub tendon_coord: Array<u32>,
    /// See `tendon_dof`.
    pub tendon_coef: Array<R>,
    /// Per passive tendon: stiffness, damping and rest lengths (resolved: the length at the
    /// joints' spring references where none was given). Can require gradients.
    pub tendon_stiffness: Array<R>,
    /// See `tendon_stiffness`.
    pub tendon_damping: Array<R>,
    /// See `tendon_stiffness`.
    pub tendon_rest_lo: Array<R>,
    /// See `tendon_stiffness`.
    pub tendon_rest_hi: Array<R>,
}

impl<R: Real> Articulations<R> {
    /// The index of the link called `name`.
    pub fn link(&self, name: &str) -> Option<usize> {
        self.links.iter().position(|l| l.name == name)
    }

    /// The index of the link whose joint is called `name`.
    pub fn joint(&self, name: &str) -> Option<usize> {
        self.links.iter().position(|l| l.joint == name)
    }

    /// Number of links.
    pub fn n_links(&self) -> usize {
        self.links.len()
    }

    /// Number of worlds.
    pub fn n_worlds(&self) -> usize {
        self.worlds.len()
    }
}

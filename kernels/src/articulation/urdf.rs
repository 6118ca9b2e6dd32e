//! Reading URDF robots.
//!
//! The physics of URDF is read: `<link>` with `<inertial>` (`<origin xyz rpy>`, `<mass>`,
//! `<inertia>`); `<joint>` of type `revolute`, `continuous`, `prismatic`, `fixed` and
//! `floating`, with `<origin>`, `<parent>`, `<child>`, `<axis>`, `<limit lower upper>` (required
//! for `revolute` and `prismatic`, as URDF says; equal bounds leave the joint free, as MuJoCo
//! reads them) and `<dynamics damping>` (a non-zero
//! `friction` is an error unless [`UrdfOptions::ignore_friction`] leaves it out). `<visual>`,
//! `<collision>`, `<material>`, `<gazebo>` and `<transmission>` carry nothing the dynamics
//! uses and are passed over. Anything else (a
//! `planar` joint, `<mimic>`, an unknown element or attribute) is an error naming the element
//! and its line, as are a missing parent or child, a link with two parents, a cycle, a
//! non-finite number, a zero or negative mass and an inertia that is not positive
//! semi-definite.
//!
//! The root link is welded to the world, or floats on a free joint with
//! [`UrdfOptions::floating_base`]. A link without `<inertial>` has no mass.
//!
//! ```
//! use adflex_kernels::articulation::urdf;
//! let robot = r#"<robot name="pendulum">
//!   <link name="base"/>
//!   <link name="pole">
//!     <inertial><origin xyz="0 0 -0.5"/><mass value="1"/>
//!       <inertia ixx="0.01" ixy="0" ixz="0" iyy="0.01" iyz="0" izz="0.001"/></inertial>
//!   </link>
//!   <joint name="hinge" type="continuous">
//!     <parent link="base"/><child link="pole"/><axis xyz="0 1 0"/>
//!   </joint>
//! </robot>"#;
//! let builder = urdf::parse(robot, &urdf::UrdfOptions::default()).unwrap();
//! let model = builder.finalize::<f64>().unwrap();
//! assert_eq!(model.n_dof, 1);
//!
//! // Mistakes name the element and the line.
//! let bad = robot.replace("value=\"1\"", "value=\"-1\"");
//! let err = urdf::parse(&bad, &urdf::UrdfOptions::default()).unwrap_err();
//! assert_eq!(err.line, Some(4));
//! assert!(err.to_string().contains("negative"), "{err}");
//! ```

use std::collections::HashMap;
use std::path::Path;

use adflex_runtime::{Mat33, Quat, Vec3};
use roxmltree::Node;

use super::build::{check_inertial, check_mass};
use super::contact::GeomShape;
use super::model::{
    axis_angle, ArticulationBuilder, ArticulationError, Inertial, Joint, LinkId, Pose,
};
use super::xml::{self, children, Source};

/// How to read a URDF file.
#[derive(Clone, Debug, Default)]
pub struct UrdfOptions {
    /// Put the root link on a free joint (a floating base) instead of welding it to the world.
    pub floating_base: bool,
    /// Read `<collision>` geometry as contact shapes: `<sphere>`, `<box>`, `<capsule radius
    /// length>` and `<cylinder radius length>` (along z; a cylinder touches the ground,
    /// particles, spheres and capsules); a `<mesh>` is then an error naming it. Default
    /// false: no contact shapes (most robots' collision geometry is meshes). Set the
    /// builder's `ground` for them to touch, and `link_contact` for links to touch each other
    /// by MuJoCo's rules (see [`contact`](super::contact): a link touches a parent fixed to
    /// the world; `exclude_contact` excludes a pair).
    pub collisions: bool,
    /// Order the children of each link by their joints' names, as Pinocchio does (through
    /// urdfdom, which keeps joints in a map by name), instead of in document order, as MuJoCo
    /// does. The order is that of the links, joints and so of `q` and `qd`; it matters only for
    /// a link with several children. Default false (document order).
    pub pinocchio_order: bool,
    /// Leave out a joint's Coulomb friction (`<dynamics friction>`), as Pinocchio's dynamics
    /// do (it stores the value; `aba` and `rnea` do not apply it). adflex does not simulate
    /// joint friction (MuJoCo reads it as `frictionloss`, a constraint of its solver), so by
    /// default (false) a non-zero `friction` is an error naming the joint's line: a robot
    /// would silently move without it.
    pub ignore_friction: bool,
}

/// Reads the URDF file at `path` into a builder (add more, set gravity, then finalize).
pub fn load(
    path: impl AsRef<Path>,
    options: &UrdfOptions,
) -> Result<ArticulationBuilder, ArticulationError> {
    let path = path.as_ref();
    let text = xml::read(path)?;
    parse_named(&text, Some(&path.display().to_string()), options)
}

/// Reads URDF text into a builder.
pub fn parse(text: &str, options: &UrdfOptions) -> Result<ArticulationBuilder, ArticulationError> {
    parse_named(text, None, options)
}

/// The rotation of URDF's `rpy`: about the fixed x, then y, then z axes.
pub fn rpy(r: f64, p: f64, y: f64) -> Quat<f64> {
    axis_angle(&Vec3::z(), y) * axis_angle(&Vec3::y(), p) * axis_angle(&Vec3::x(), r)
}

struct UrdfJoint<'a, 'i> {
    node: Node<'a, 'i>,
    parent: String,
    joint: Joint,
}

fn parse_named(
    text: &str,
    file: Option<&str>,
    options: &UrdfOptions,
) -> Result<ArticulationBuilder, ArticulationError> {
    let doc = xml::parse(text, file)?;
    let src = Source {
        file: file.map(str::to_string),
        doc: &doc,
        lines: None,
    };
    let robot = doc.root_element();
    if robot.tag_name().name() != "robot" {
        return Err(src.error(robot, "the root element of a URDF file must be <robot>"));
    }
    let items = children(
        &src,
        robot,
        &["link", "joint"],
        &["material", "gazebo", "transmission"],
    )?;
    // Links, in document order.
    let mut links: Vec<(Node, String, Inertial)> = Vec::new();
    let mut index: HashMap<String, usize> = HashMap::new();
    for n in items.iter().filter(|n| n.tag_name().name() == "link") {
        src.only_attributes(*n, &["name", "type"])?;
        let name = src.required(*n, "name")?.to_string();
        if index.insert(name.clone(), links.len()).is_some() {
            return Err(src.error(*n, "a second link with this name"));
        }
        let inertial = link_inertial(&src, *n)?;
        links.push((*n, name, inertial));
    }
    // Joints, by child.
    let mut by_child: HashMap<usize, UrdfJoint> = HashMap::new();
    let mut names: HashMap<String, ()> = HashMap::new();
    for n in items.iter().filter(|n| n.tag_name().name() == "joint") {
        let uj = joint(&src, *n, options.ignore_friction)?;
        if names.insert(uj.joint.name.clone(), ()).is_some() {
            return Err(src.error(*n, "a second joint with this name"));
        }
        let child = n
            .children()
            .find(|c| c.has_tag_name("child"))
            .ok_or_else(|| src.error(*n, "needs a <child link=\"...\"/>"))?;
        src.only_attributes(child, &["link"])?;
        let child_name = src.required(child, "link")?;
        let &c = index.get(child_name).ok_or_else(|| {
            src.error(
                *n,
                format!("its child link \"{child_name}\" is not defined"),
            )
        })?;
        if !index.contains_key(&uj.parent) {
            return Err(src.error(
                *n,
                format!("its parent link \"{}\" is not defined", uj.parent),
            ));
        }
        if uj.parent == child_name {
            return Err(src.error(*n, "its parent and child are the same link"));
        }
        if by_child.insert(c, uj).is_some() {
            return Err(src.error(
                *n,
                format!("link \"{child_name}\" is the child of a second joint (a URDF is a tree)"),
            ));
        }
    }
    // The root: the one link that is no joint's child.
    let roots: Vec<usize> = (0..links.len())
        .filter(|l| !by_child.contains_key(l))
        .collect();
    let root = match roots.as_slice() {
        [r] => *r,
        [] if links.is_empty() => return Err(src.error(robot, "has no <link>")),
        [] => return Err(src.error(robot, "every link has a parent: the joints form a cycle")),
        [a, b, ..] => {
            return Err(src.error(
                links[*b].0,
                format!(
                    "has no parent, and neither has link \"{}\": a URDF is one tree (join them \
                     with a joint)",
                    links[*a].1
                ),
            ))
        }
    };
    let mut b = ArticulationBuilder::new();
    let mut id: Vec<Option<LinkId>> = vec![None; links.len()];
    let root_joint = if options.floating_base {
        Joint::free().name(format!("{}_root", links[root].1))
    } else {
        Joint::fixed().name(format!("{}_root", links[root].1))
    };
    id[root] = Some(b.add_link(links[root].1.clone(), None, root_joint, links[root].2));
    let mut kids: HashMap<usize, Vec<usize>> = HashMap::new();
    let mut order: Vec<(&str, usize, usize)> = by_child
        .iter()
        .map(|(&c, j)| {
            let name = if options.pinocchio_order {
                j.joint.name.as_str()
            } else {
                ""
            };
            (name, j.node.range().start, c)
        })
        .collect();
    order.sort();
    for (_, _, c) in order {
        kids.entry(index[&by_child[&c].parent]).or_default().push(c);
    }
    // Depth first, children in document order (MuJoCo's order of joints) or by their joints'
    // names (Pinocchio's).
    let mut stack: Vec<usize> = kids.get(&root).cloned().unwrap_or_default();
    stack.reverse();
    while let Some(c) = stack.pop() {
        let uj = &by_child[&c];
        let p = index[&uj.parent];
        id[c] = Some(b.add_link(links[c].1.clone(), id[p], uj.joint.clone(), links[c].2));
        if let Some(k) = kids.get(&c) {
            stack.extend(k.iter().rev());
        }
    }
    if let Some(l) = id.iter().position(Option::is_none) {
        return Err(src.error(
            links[l].0,
            "is on a cycle of joints, not on the tree under the root",
        ));
    }
    if options.collisions {
        for (l, (node, _, _)) in links.iter().enumerate() {
            let link = id[l].expect("every link is on the tree");
            for c in node.children().filter(|c| c.has_tag_name("collision")) {
                collision(&src, c, link, &mut b)?;
            }
        }
    }
    Ok(b)
}

/// A `<collision>`'s geometry as contact shapes on `link`.
fn collision(
    src: &Source,
    c: Node,
    link: LinkId,
    b: &mut ArticulationBuilder,
) -> Result<(), ArticulationError> {
    children(src, c, &["origin", "geometry"], &[])?;
    let pose = origin(src, c)?;
    let g = c
        .children()
        .find(|n| n.has_tag_name("geometry"))
        .ok_or_else(|| src.error(c, "needs a <geometry>"))?;
    let shapes = children(
        src,
        g,
        &["sphere", "box", "capsule", "cylinder", "mesh"],
        &[],
    )?;
    let Some(&shape) = shapes.first() else {
        return Err(src.error(g, "needs a shape"));
    };
    let positive = |name: &str| -> Result<f64, ArticulationError> {
        match src.number(shape, name)? {
            Some(v) if v > 0.0 => Ok(v),
            _ => Err(src.error(shape, format!("needs a positive `{name}`"))),
        }
    };
    let geom = match shape.tag_name().name() {
        "sphere" => GeomShape::Sphere(positive("radius")?),
        "box" => {
            let size = src
                .vec3(shape, "size")?
                .filter(|v| v.iter().all(|&x| x > 0.0))
                .ok_or_else(|| src.error(shape, "needs a positive `size`"))?;
            GeomShape::Box(size * 0.5)
        }
        "capsule" => GeomShape::Capsule(positive("radius")?, 0.5 * positive("length")?),
        "cylinder" => GeomShape::Cylinder(positive("radius")?, 0.5 * positive("length")?),
        other => {
            return Err(src.error(
                shape,
                format!(
                    "<{other}> is not supported as a contact shape (sphere, box, capsule, \
                     cylinder); read the robot with UrdfOptions::collisions = false for no \
                     contact shapes"
                ),
            ))
        }
    };
    b.add_contact_shape(link, &pose, &geom);
    Ok(())
}

fn origin(src: &Source, node: Node) -> Result<Pose, ArticulationError> {
    match node.children().find(|c| c.has_tag_name("origin")) {
        None => Ok(Pose::identity()),
        Some(o) => {
            src.only_attributes(o, &["xyz", "rpy"])?;
            let xyz = src.vec3(o, "xyz")?.unwrap_or_else(Vec3::zeros);
            let r = src.vec3(o, "rpy")?.unwrap_or_else(Vec3::zeros);
            Ok(Pose::new(xyz, rpy(r.x, r.y, r.z)))
        }
    }
}

fn link_inertial(src: &Source, link: Node) -> Result<Inertial, ArticulationError> {
    let known = ["inertial"];
    let items = children(src, link, &known, &["visual", "collision"])?;
    let Some(&n) = items.first() else {
        return Ok(Inertial::massless());
    };
    if items.len() > 1 {
        return Err(src.error(items[1], "a second <inertial> in one link"));
    }
    children(src, n, &["origin", "mass", "inertia"], &[])?;
    let pose = origin(src, n)?;
    let mass_node = n
        .children()
        .find(|c| c.has_tag_name("mass"))
        .ok_or_else(|| src.error(n, "needs <mass value=\"...\"/>"))?;
    src.only_attributes(mass_node, &["value"])?;
    let mass = src
        .number(mass_node, "value")?
        .ok_or_else(|| src.error(mass_node, "needs the attribute `value`"))?;
    check_mass(mass, "a link").map_err(|m| src.error(mass_node, m))?;
    let i_node = n
        .children()
        .find(|c| c.has_tag_name("inertia"))
        .ok_or_else(|| src.error(n, "needs <inertia ixx ixy ixz iyy iyz izz/>"))?;
    src.only_attributes(i_node, &["ixx", "ixy", "ixz", "iyy", "iyz", "izz"])?;
    let mut v = [0.0; 6];
    for (k, name) in ["ixx", "ixy", "ixz", "iyy", "iyz", "izz"]
        .iter()
        .enumerate()
    {
        v[k] = src
            .number(i_node, name)?
            .ok_or_else(|| src.error(i_node, format!("needs the attribute `{name}`")))?;
    }
    let i = Mat33::new(v[0], v[1], v[2], v[1], v[3], v[4], v[2], v[4], v[5]);
    let inertial = Inertial::new(mass, Vec3::zeros(), i).transformed(&pose);
    check_inertial(&inertial).map_err(|m| src.error(i_node, m))?;
    Ok(inertial)
}

fn joint<'a, 'i>(
    src: &Source,
    n: Node<'a, 'i>,
    ignore_friction: bool,
) -> Result<UrdfJoint<'a, 'i>, ArticulationError> {
    src.only_attributes(n, &["name", "type"])?;
    let name = src.required(n, "name")?.to_string();
    children(
        src,
        n,
        &["origin", "parent", "child", "axis", "limit", "dynamics"],
        &["calibration", "safety_controller"],
    )?;
    let axis = match n.children().find(|c| c.has_tag_name("axis")) {
        None => Vec3::x(),
        Some(a) => {
            src.only_attributes(a, &["xyz"])?;
            let v = src
                .vec3(a, "xyz")?
                .ok_or_else(|| src.error(a, "needs the attribute `xyz`"))?;
            if v.norm() < 1e-12 {
                return Err(src.error(a, "the axis is zero"));
            }
            v
        }
    };
    let kind = src.required(n, "type")?;
    let mut j = match kind {
        "revolute" | "continuous" => Joint::revolute(axis),
        "prismatic" => Joint::prismatic(axis),
        "fixed" => Joint::fixed(),
        "floating" => Joint::free(),
        other => {
            return Err(src.error(
                n,
                format!(
                    "joint type `{other}` is not supported (revolute, continuous, prismatic, \
                     fixed, floating)"
                ),
            ))
        }
    };
    j = j.name(name).origin(origin(src, n)?);
    let limit = n.children().find(|c| c.has_tag_name("limit"));
    if limit.is_none() && (kind == "revolute" || kind == "prismatic") {
        // URDF requires it (urdfdom, and so ROS and Pinocchio, refuse the file); reading the
        // joint as unlimited would guess.
        return Err(src.error(
            n,
            format!(
                "a {kind} joint needs a `<limit lower upper effort velocity>` (URDF requires                  it){}",
                match kind {
                    "revolute" => "; an unlimited hinge is type `continuous`",
                    _ => "",
                }
            ),
        ));
    }
    if let Some(l) = limit {
        // `effort` and `velocity` are the actuator's bounds, which the dynamics do not use.
        src.only_attributes(l, &["lower", "upper", "effort", "velocity"])?;
        if kind == "revolute" || kind == "prismatic" {
            let lo = src.number(l, "lower")?.unwrap_or(0.0);
            let hi = src.number(l, "upper")?.unwrap_or(0.0);
            if lo > hi {
                return Err(src.error(l, format!("lower {lo} > upper {hi}")));
            }
            // Equal bounds leave the joint free, as MuJoCo reads them (it warns "limit
            // ignored"); Pinocchio stores them but does not simulate limits.
            if lo < hi {
                j = j.limits(lo, hi);
            }
        }
    }
    if let Some(d) = n.children().find(|c| c.has_tag_name("dynamics")) {
        src.only_attributes(d, &["damping", "friction"])?;
        let damping = src.number(d, "damping")?.unwrap_or(0.0);
        if damping < 0.0 {
            return Err(src.error(d, format!("damping {damping} is negative")));
        }
        let friction = src.number(d, "friction")?.unwrap_or(0.0);
        if friction < 0.0 {
            return Err(src.error(d, format!("friction {friction} is negative")));
        }
        if friction != 0.0 && !ignore_friction {
            return Err(src.error(
                d,
                "joint friction is not simulated; remove `friction`, or read the robot with \
                 UrdfOptions::ignore_friction to leave it out (as Pinocchio's dynamics do)",
            ));
        }
        j = j.damping(damping);
    }
    let parent = n
        .children()
        .find(|c| c.has_tag_name("parent"))
        .ok_or_else(|| src.error(n, "needs a <parent link=\"...\"/>"))?;
    src.only_attributes(parent, &["link"])?;
    Ok(UrdfJoint {
        node: n,
        parent: src.required(parent, "link")?.to_string(),
        joint: j,
    })
}

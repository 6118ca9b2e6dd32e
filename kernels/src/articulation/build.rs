//! Checking a description and laying out the model's arrays.

use adflex_runtime::prelude::*;

use super::contact::{ContactShape, GeomShape, LinkShapes};
use super::model::{
    ArticulationBuilder, ArticulationError, ArticulationInfo, ArticulationIntegrator,
    Articulations, Inertial, JointType, LinkId, LinkInfo, Pose, WorldInfo,
};

impl ArticulationBuilder {
    /// Checks the description and builds the model.
    ///
    /// Errors name the link or joint: a parent added after its child or missing, a
    /// non-finite number, a negative mass, an inertia that is not symmetric positive
    /// semi-definite, a zero axis or quaternion, limits
    /// with `lower > upper`, a negative damping, armature or gain, and a joint whose motion
    /// moves no mass (the mass matrix would be singular).
    pub fn finalize<R: Real>(&self) -> Result<Articulations<R>, ArticulationError> {
        finalize(self)
    }
}

fn err(element: String, message: impl Into<String>) -> ArticulationError {
    ArticulationError::new(element, message)
}

fn finite3(v: &Vec3<f64>) -> bool {
    v.iter().all(|x| x.is_finite())
}

/// Checks mass properties: finite, mass >= 0, inertia symmetric positive semi-definite. (The
/// triangle inequality of the principal moments, which a real body satisfies, is not
/// required: CAD exports often break it slightly, and the dynamics stay well defined.)
pub(crate) fn check_inertial(i: &Inertial) -> Result<(), String> {
    if !i.mass.is_finite() || !finite3(&i.com) || !i.inertia.iter().all(|x| x.is_finite()) {
        return Err("mass, centre of mass and inertia must be finite".into());
    }
    if i.mass < 0.0 {
        return Err(format!("mass {} is negative", i.mass));
    }
    let scale = i.inertia.abs().max().max(f64::MIN_POSITIVE);
    if (i.inertia - i.inertia.transpose()).abs().max() > 1e-9 * scale {
        return Err("inertia is not symmetric".into());
    }
    let e = i.inertia.symmetric_eigenvalues();
    let tol = 1e-9 * scale;
    if e.iter().any(|&x| x < -tol) {
        return Err(format!(
            "inertia is not positive semi-definite (principal moments {:.6e}, {:.6e}, {:.6e})",
            e[0], e[1], e[2]
        ));
    }
    if i.mass == 0.0 && i.inertia.abs().max() > 0.0 {
        return Err("a massless link has an inertia; give it a mass or no inertia".into());
    }
    Ok(())
}

/// A mass read from a file: an element that gives one must give a positive one (`what`, "a
/// link" or "a body", without mass has none).
pub(crate) fn check_mass(mass: f64, what: &str) -> Result<(), String> {
    if mass > 0.0 {
        return Ok(());
    }
    Err(format!(
        "mass {mass} is {}: {what} without mass has no <inertial>",
        if mass < 0.0 { "negative" } else { "zero" }
    ))
}

pub(crate) fn finalize<R: Real>(
    b: &ArticulationBuilder,
) -> Result<Articulations<R>, ArticulationError> {
    let links = b.links();
    let n = links.len();
    let name = |l: usize| format!("link \"{}\"", links[l].name);
    let joint_name = |l: usize| {
        let j = &links[l].joint.name;
        if j.is_empty() {
            links[l].name.clone()
        } else {
            j.clone()
        }
    };
    if let Some(m) = b.mismatch() {
        return Err(err("worlds".into(), m));
    }
    let (world_of, gravity) = b.world_layout();
    for (k, g) in gravity.iter().enumerate() {
        if !finite3(g) {
            return Err(err(format!("gravity of world {k}"), "must be finite"));
        }
    }
    if !(b.limit_ke >= 0.0 && b.limit_kd >= 0.0 && b.limit_ke.is_finite() && b.limit_kd.is_finite())
    {
        return Err(err(
            "limit_ke/limit_kd".into(),
            "must be finite and non-negative",
        ));
    }
    // Checks, in the order the links were added.
    for (l, d) in links.iter().enumerate() {
        if let Some(p) = d.parent {
            if p.0 >= l {
                return Err(err(
                    name(l),
                    format!(
                        "its parent (link {}) must be added before it (parents first)",
                        p.0
                    ),
                ));
            }
            if world_of[p.0] != world_of[l] {
                return Err(err(
                    name(l),
                    format!(
                        "it is in world {} and its parent {} in world {}: worlds do not share \
                         links (add the whole robot with `add_world`)",
                        world_of[l],
                        name(p.0),
                        world_of[p.0]
                    ),
                ));
            }
        }
        check_inertial(&d.inertial).map_err(|m| err(name(l), m))?;
        if !d.gravcomp.is_finite() {
            return Err(err(
                name(l),
                format!("gravcomp {} must be finite", d.gravcomp),
            ));
        }
        let j = &d.joint;
        let je = || format!("joint \"{}\"", joint_name(l));
        let q = j.origin.rot;
        if !finite3(&j.origin.pos) || !q.coords.iter().all(|x| x.is_finite()) {
            return Err(err(je(), "origin must be finite"));
        }
        if q.norm() < 1e-12 {
            return Err(err(je(), "origin's quaternion has norm 0"));
        }
        if j.kind.is_scalar() && (!finite3(&j.axis) || j.axis.norm() < 1e-12) {
            return Err(err(je(), "axis must be finite and non-zero"));
        }
        for (v, what) in [
            (j.damping, "damping"),
            (j.armature, "armature"),
            (j.kp, "kp"),
            (j.kv, "kv"),
            (j.stiffness, "stiffness"),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(err(
                    je(),
                    format!("{what} {v} must be finite and non-negative"),
                ));
            }
        }
        if !j.spring_ref.is_finite() {
            return Err(err(je(), "spring_ref must be finite"));
        }
        if j.stiffness > 0.0 && !j.kind.is_scalar() {
            return Err(err(
                je(),
                "a spring (stiffness) applies to revolute and prismatic joints only",
            ));
        }
        if !j.initial.is_empty() {
            let quat = j.initial.len().saturating_sub(4);
            if j.initial.len() != j.kind.nq() || j.initial.iter().any(|x| !x.is_finite()) {
                return Err(err(
                    je(),
                    format!(
                        "initial coordinates: {} finite numbers needed, {:?} given",
                        j.kind.nq(),
                        j.initial
                    ),
                ));
            }
            if j.kind.nq() > 1 && j.initial[quat..].iter().map(|x| x * x).sum::<f64>() < 1e-24 {
                return Err(err(je(), "initial quaternion has norm 0"));
            }
        }
        if let Some((lo, hi)) = j.limits {
            if !j.kind.is_scalar() {
                return Err(err(
                    je(),
                    "limits apply to revolute and prismatic joints only",
                ));
            }
            if lo.is_nan() || hi.is_nan() || lo > hi {
                return Err(err(
                    je(),
                    format!("limits [{lo}, {hi}]: lower must be <= upper"),
                ));
            }
        }
        let (dmin, dmax, width) = j.limit_impedance;
        if !(0.0 < dmin && dmin <= dmax && dmax < 1.0 && width.is_finite() && width > 0.0) {
            return Err(err(
                je(),
                format!(
                    "limit impedance ({dmin}, {dmax}, {width}): 0 < dmin <= dmax < 1 and a \
                     positive width"
                ),
            ));
        }
        if let Some((tc, zeta)) = j.limit_time {
            if !(tc.is_finite() && tc > 0.0 && zeta.is_finite() && zeta > 0.0) {
                return Err(err(
                    je(),
                    format!(
                        "limit time constant {tc} and damping ratio {zeta} must be finite and \
                         positive"
                    ),
                ));
            }
        }
        if d.parent.is_some() && j.kind == JointType::Free {
            // Allowed (a floating child), but rare: nothing to check.
        }
    }

    if let Some(g) = &b.ground {
        g.check().map_err(|m| err("ground".into(), m))?;
    }
    if let Some(f) = &b.fluid {
        let ok = |x: f64| x.is_finite() && x >= 0.0;
        if !(ok(f.density) && ok(f.viscosity) && f.wind.iter().all(|x| x.is_finite())) {
            return Err(err(
                "fluid".into(),
                format!(
                    "density {} and viscosity {} must be finite and non-negative, the wind {:?} \
                     finite",
                    f.density, f.viscosity, f.wind
                ),
            ));
        }
    }
    for (k, c) in b.contact_shapes().iter().enumerate() {
        if c.link.0 >= n {
            return Err(err(
                format!("contact shape {k}"),
                format!("link {} does not exist", c.link.0),
            ));
        }
        let sizes_ok = match c.shape {
            GeomShape::Sphere(r) => r.is_finite() && r >= 0.0,
            GeomShape::Capsule(r, h) => r.is_finite() && r >= 0.0 && h.is_finite() && h >= 0.0,
            GeomShape::Box(half) | GeomShape::Ellipsoid(half) => {
                finite3(&half) && half.iter().all(|&x| x > 0.0)
            }
            GeomShape::Cylinder(r, h) => r.is_finite() && r > 0.0 && h.is_finite() && h > 0.0,
            GeomShape::Plane => false,
        };
        if let Some(mu) = c.friction.filter(|mu| !(mu.is_finite() && *mu >= 0.0)) {
            return Err(err(
                format!("contact shape {k} ({:?}) on {}", c.shape, name(c.link.0)),
                format!("friction {mu} must be finite and non-negative"),
            ));
        }
        let rot = c.pose.rot.norm();
        if !(finite3(&c.pose.pos) && sizes_ok && (rot - 1.0).abs() < 1e-6) {
            return Err(err(
                format!("contact shape {k} ({:?}) on {}", c.shape, name(c.link.0)),
                "its pose must be finite with a unit quaternion, a sphere's or capsule's \
                 radius and half-length finite and non-negative, a cylinder's positive, a \
                 box's half extents and an ellipsoid's semi-axes finite and positive",
            ));
        }
    }
    for (k, &(x, y)) in b.excluded_contacts().iter().enumerate() {
        if x.0 >= n || y.0 >= n {
            return Err(err(
                format!("excluded contact {k}"),
                format!("link {} does not exist", x.0.max(y.0)),
            ));
        }
    }
    for (k, m) in b.muscles().iter().enumerate() {
        let e = || format!("muscle \"{}\" ({k})", m.name);
        if m.origin.0 .0 >= n || m.insertion.0 .0 >= n {
            return Err(err(e(), "its origin or insertion link does not exist"));
        }
        if world_of[m.origin.0 .0] != world_of[m.insertion.0 .0] {
            return Err(err(e(), "its origin and insertion are in different worlds"));
        }
        if !(finite3(&m.origin.1) && finite3(&m.insertion.1)) {
            return Err(err(e(), "attachment points must be finite"));
        }
        for (v, what, positive) in [
            (m.f_max, "f_max", false),
            (m.l_opt, "l_opt", true),
            (m.tendon_slack, "tendon_slack", false),
            (m.v_max, "v_max", true),
        ] {
            if !(v.is_finite() && (v > 0.0 || (!positive && v == 0.0))) {
                return Err(err(
                    e(),
                    format!(
                        "{what} {v} must be finite and {}",
                        if positive { "positive" } else { "non-negative" }
                    ),
                ));
            }
        }
        if m.origin.0 == m.insertion.0 {
            return Err(err(
                e(),
                "origin and insertion are on the same link: it would pull on nothing",
            ));
        }
    }
    check_actuators(b, &world_of)?;
    // Topology: articulations are the trees under each root; links stay in the order given
    // (parents first), grouped by tree.
    let mut root_of = vec![0usize; n];
    for l in 0..n {
        root_of[l] = match links[l].parent {
            None => l,
            Some(p) => root_of[p.0],
        };
    }
    // Each tree's links in the order given, trees in the order of their roots.
    let mut tree_links: Vec<Vec<usize>> = vec![Vec::new(); n];
    for l in 0..n {
        tree_links[root_of[l]].push(l);
    }
    let order: Vec<usize> = tree_links.into_iter().flatten().collect();
    let mut new_index = vec![0usize; n];
    for (i, &l) in order.iter().enumerate() {
        new_index[l] = i;
    }
    let parent: Vec<Option<usize>> = order
        .iter()
        .map(|&l| links[l].parent.map(|p| new_index[p.0]))
        .collect();

    // Coordinates and velocities, link by link.
    let (mut q_start, mut qd_start) = (Vec::with_capacity(n), Vec::with_capacity(n + 1));
    let (mut nq, mut nv) = (0usize, 0usize);
    let mut neutral = Vec::new();
    for &l in &order {
        let k = links[l].joint.kind;
        q_start.push(nq as u32);
        qd_start.push(nv as u32);
        nq += k.nq();
        nv += k.nv();
        let init = &links[l].joint.initial;
        if !init.is_empty() {
            let mut v = init.clone();
            if k.nq() > 1 {
                let quat = &mut v[k.nq() - 4..];
                let n = quat.iter().map(|x| x * x).sum::<f64>().sqrt();
                quat.iter_mut().for_each(|x| *x /= n);
            }
            neutral.extend(v);
            continue;
        }
        match k {
            JointType::Ball => neutral.extend([0.0, 0.0, 0.0, 1.0]),
            JointType::Free => neutral.extend([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]),
            _ => neutral.extend(vec![0.0; k.nq()]),
        }
    }
    qd_start.push(nv as u32);

    // Chains (root first) and subtrees (self first, then descendants in order).
    let mut chain_start = vec![0u32];
    let mut chain = Vec::new();
    for i in 0..n {
        let mut c = vec![i as u32];
        let mut p = parent[i];
        while let Some(j) = p {
            c.push(j as u32);
            p = parent[j];
        }
        c.reverse();
        chain.extend(c);
        chain_start.push(chain.len() as u32);
    }
    // A tree's links are contiguous: a subtree is searched for in its own tree only.
    let mut tree_end = vec![n; n];
    for i in (0..n.saturating_sub(1)).rev() {
        tree_end[i] = if parent[i + 1].is_none() {
            i + 1
        } else {
            tree_end[i + 1]
        };
    }
    let mut subtree_start = vec![0u32];
    let mut subtree = Vec::new();
    for (i, &end) in tree_end.iter().enumerate() {
        subtree.push(i as u32);
        for j in i + 1..end {
            let mut p = parent[j];
            while let Some(k) = p {
                if k == i {
                    subtree.push(j as u32);
                    break;
                }
                p = parent[k];
            }
        }
        subtree_start.push(subtree.len() as u32);
    }

    // Articulations.
    let mut arts: Vec<ArticulationInfo> = Vec::new();
    let mut art_of = vec![0usize; n];
    let mut m_len = 0;
    for (i, p) in parent.iter().enumerate() {
        if p.is_none() {
            arts.push(ArticulationInfo {
                links: i..i,
                q: q_start[i] as usize..q_start[i] as usize,
                dofs: qd_start[i] as usize..qd_start[i] as usize,
                m_offset: 0,
            });
        }
        let a = arts.len() - 1;
        art_of[i] = a;
        let info = &mut arts[a];
        info.links.end = i + 1;
        info.q.end = q_start[i] as usize + links[order[i]].joint.kind.nq();
        info.dofs.end = qd_start[i + 1] as usize;
    }
    for a in &mut arts {
        a.m_offset = m_len;
        m_len += a.dofs.len() * a.dofs.len();
    }

    // Per velocity.
    let mut dof = DofArrays::default();
    for (i, &l) in order.iter().enumerate() {
        let j = &links[l].joint;
        let art = &arts[art_of[i]];
        let (lo, hi) = j.limits.unwrap_or((f64::NEG_INFINITY, f64::INFINITY));
        for k in 0..j.kind.nv() {
            let d = qd_start[i] as usize + k;
            dof.link.push(i as u32);
            dof.index.push(k as u32);
            dof.q.push(if j.kind.is_scalar() { q_start[i] } else { 0 });
            dof.scalar.push(j.kind.is_scalar() as u32);
            dof.art_start.push(art.dofs.start as u32);
            dof.m_row
                .push((art.m_offset + (d - art.dofs.start) * art.dofs.len()) as u32);
            dof.armature.push(j.armature);
            dof.damping.push(j.damping);
            dof.stiffness.push(j.stiffness);
            dof.spring_ref.push(j.spring_ref);
            dof.kp.push(j.kp);
            dof.kv.push(j.kv);
            dof.lower.push(lo);
            dof.upper.push(hi);
            // Per unit inertia here; `scale_limits` multiplies by the joint's.
            let (dmin, dmax, width) = j.limit_impedance;
            let (k, b) = match j.limit_time {
                Some((tc, zeta)) => (1.0 / (dmax * tc * zeta).powi(2), 2.0 / (dmax * tc)),
                None => (0.0, 0.0),
            };
            dof.limit_k.push(k);
            dof.limit_b.push(b);
            dof.limit_m.push(1.0);
            dof.limit_imp.push(Vec3::new(dmin, dmax, width));
        }
    }

    let contact = link_contact_pairs(b, (&order, &new_index), &parent, &world_of)?;
    let ground_spheres = b.contacts();
    let supports = b.support_contacts();
    let r = |x: f64| R::lit(x);
    let v3 = |v: &Vec3<f64>| Vec3::new(r(v.x), r(v.y), r(v.z));
    let rs = |xs: &[f64]| Array::from_vec(xs.iter().map(|&x| r(x)).collect::<Vec<R>>());
    let quat = |q: &Quat<f64>| Quat::new(r(q.w), r(q.i), r(q.j), r(q.k));
    // The fluid's inertia boxes, per link with mass, in the model's link order.
    let boxes = super::fluid::inertia_boxes(order.iter().map(|&l| &links[l].inertial));
    // Worlds: contiguous in the new order too (trees never span worlds, roots keep their order).
    let link_world: Vec<usize> = order.iter().map(|&l| world_of[l]).collect();
    let mut worlds: Vec<WorldInfo> = (0..gravity.len())
        .map(|_| WorldInfo {
            links: n..n,
            articulations: arts.len()..arts.len(),
            q: nq..nq,
            dofs: nv..nv,
            actuators: 0..0,
        })
        .collect();
    let (mut q_world, mut dof_world) = (vec![0u32; nq], vec![0u32; nv]);
    for (i, &w) in link_world.iter().enumerate() {
        let l = &links[order[i]];
        let q0 = q_start[i] as usize;
        let (d0, d1) = (qd_start[i] as usize, qd_start[i + 1] as usize);
        q_world[q0..q0 + l.joint.kind.nq()].fill(w as u32);
        dof_world[d0..d1].fill(w as u32);
        let info = &mut worlds[w];
        if info.links.start == n {
            *info = WorldInfo {
                links: i..i,
                articulations: art_of[i]..art_of[i],
                q: q0..q0,
                dofs: d0..d0,
                actuators: 0..0,
            };
        }
        info.links.end = i + 1;
        info.articulations.end = art_of[i] + 1;
        info.q.end = q0 + l.joint.kind.nq();
        info.dofs.end = d1;
    }
    // An empty world sits where the next one starts.
    for k in (0..worlds.len()).rev() {
        if worlds[k].links.start == n {
            if let Some(next) = worlds.get(k + 1).cloned() {
                worlds[k] = WorldInfo {
                    links: next.links.start..next.links.start,
                    articulations: next.articulations.start..next.articulations.start,
                    q: next.q.start..next.q.start,
                    dofs: next.dofs.start..next.dofs.start,
                    actuators: 0..0,
                };
            }
        }
    }
    debug_assert!(link_world.windows(2).all(|p| p[0] <= p[1]));
    // Each world's actuators (grouped by world, as `check_actuators` made sure).
    let act_world: Vec<usize> = b
        .actuators()
        .iter()
        .map(|a| world_of[a.transmission[0].0 .0])
        .collect();
    for (w, info) in worlds.iter_mut().enumerate() {
        let before = act_world.iter().filter(|&&x| x < w).count();
        info.actuators = before..before + act_world.iter().filter(|&&x| x == w).count();
    }
    // Actuators' and passive tendons' joints, flattened.
    let flatten = |lists: Vec<&[(LinkId, f64)]>| {
        let mut t = Transmissions {
            start: vec![0],
            ..Default::default()
        };
        for joints in lists {
            for &(l, c) in joints {
                t.dof.push(qd_start[new_index[l.0]]);
                t.coord.push(q_start[new_index[l.0]]);
                t.coef.push(c);
            }
            t.start.push(t.dof.len() as u32);
        }
        t
    };
    let act = flatten(b.actuators().iter().map(|a| &a.transmission[..]).collect());
    let ten = flatten(b.tendon_springs().iter().map(|t| &t.joints[..]).collect());
    // A tendon's rest length is its length at the joints' spring references unless given (as
    // MuJoCo's, from `qpos_spring`).
    let rest: Vec<(f64, f64)> = (0..b.tendon_springs().len())
        .map(|k| {
            let (k0, k1) = (ten.start[k] as usize, ten.start[k + 1] as usize);
            let l0: f64 = (k0..k1)
                .map(|j| ten.coef[j] * dof.spring_ref[ten.dof[j] as usize])
                .sum();
            b.tendon_springs()[k].rest.unwrap_or((l0, l0))
        })
        .collect();
    let infos = order
        .iter()
        .enumerate()
        .map(|(i, &l)| LinkInfo {
            name: links[l].name.clone(),
            joint: joint_name(l),
            kind: links[l].joint.kind,
            parent: parent[i],
            q: q_start[i] as usize..q_start[i] as usize + links[l].joint.kind.nq(),
            dofs: qd_start[i] as usize..qd_start[i + 1] as usize,
            articulation: art_of[i],
        })
        .collect();
    let model = Articulations {
        links: infos,
        articulations: arts,
        n_q: nq,
        n_dof: nv,
        worlds,
        link_world: Array::from_vec(link_world.iter().map(|&w| w as u32).collect()),
        q_world: Array::from_vec(q_world),
        dof_world: Array::from_vec(dof_world),
        gravity: Array::from_vec(gravity.iter().map(v3).collect()),
        limit_ke: r(b.limit_ke),
        limit_kd: r(b.limit_kd),
        fluid_on: b.fluid.is_some(),
        limit_refsafe: b.limit_refsafe,
        implicit_damping: b.implicit_damping,
        integrator: b.integrator,
        fluid_density: rs(&[b.fluid.map_or(0.0, |f| f.density)]),
        fluid_viscosity: rs(&[b.fluid.map_or(0.0, |f| f.viscosity)]),
        wind: Array::from_vec(vec![v3(&b.fluid.map_or(Vec3::zeros(), |f| f.wind))]),
        fluid_link: Array::from_vec(boxes.iter().map(|x| x.link).collect()),
        fluid_com: Array::from_vec(boxes.iter().map(|x| v3(&x.com)).collect()),
        fluid_rot: Array::from_vec(boxes.iter().map(|x| quat(&x.rot)).collect()),
        fluid_box: Array::from_vec(boxes.iter().map(|x| v3(&x.sides)).collect()),
        gravcomp_link: Array::from_vec(
            (0..n)
                .filter(|&i| links[order[i]].gravcomp != 0.0)
                .map(|i| i as u32)
                .collect(),
        ),
        gravcomp: rs(&order
            .iter()
            .map(|&l| links[l].gravcomp)
            .filter(|&g| g != 0.0)
            .collect::<Vec<_>>()),
        q0: neutral.iter().map(|&x| r(x)).collect(),
        chain_start: Array::from_vec(chain_start),
        chain: Array::from_vec(chain),
        subtree_start: Array::from_vec(subtree_start),
        subtree: Array::from_vec(subtree),
        joint_type: Array::from_vec(order.iter().map(|&l| links[l].joint.kind.code()).collect()),
        q_start: Array::from_vec(q_start),
        qd_start: Array::from_vec(qd_start),
        joint_pos: Array::from_vec(
            order
                .iter()
                .map(|&l| v3(&links[l].joint.origin.pos))
                .collect(),
        ),
        joint_rot: Array::from_vec(
            order
                .iter()
                .map(|&l| {
                    let q = links[l].joint.origin.rot.normalize();
                    Quat::new(r(q.w), r(q.i), r(q.j), r(q.k))
                })
                .collect(),
        ),
        joint_axis: Array::from_vec(
            order
                .iter()
                .map(|&l| {
                    let a = &links[l].joint.axis;
                    v3(&if a.norm() > 0.0 {
                        a.normalize()
                    } else {
                        Vec3::z()
                    })
                })
                .collect(),
        ),
        mass: rs(&order
            .iter()
            .map(|&l| links[l].inertial.mass)
            .collect::<Vec<_>>()),
        com: Array::from_vec(order.iter().map(|&l| v3(&links[l].inertial.com)).collect()),
        inertia: Array::from_vec(
            order
                .iter()
                .map(|&l| links[l].inertial.inertia.map(r))
                .collect(),
        ),
        dof_link: Array::from_vec(dof.link),
        dof_index: Array::from_vec(dof.index),
        dof_q: Array::from_vec(dof.q),
        dof_scalar: Array::from_vec(dof.scalar),
        dof_art_start: Array::from_vec(dof.art_start),
        dof_m_row: Array::from_vec(dof.m_row),
        armature: rs(&dof.armature),
        damping: rs(&dof.damping),
        stiffness: rs(&dof.stiffness),
        spring_ref: rs(&dof.spring_ref),
        kp: rs(&dof.kp),
        kv: rs(&dof.kv),
        lower: rs(&dof.lower),
        upper: rs(&dof.upper),
        limit_k: rs(&dof.limit_k),
        limit_b: rs(&dof.limit_b),
        limit_m: rs(&dof.limit_m),
        limit_imp: Array::from_vec(dof.limit_imp.iter().map(v3).collect()),
        m_len,
        shapes: LinkShapes::new(b.contact_shapes(), |l| new_index[l]),
        contact_link: Array::from_vec(
            ground_spheres
                .iter()
                .map(|c| new_index[c.0 .0] as u32)
                .collect(),
        ),
        contact_pos: Array::from_vec(ground_spheres.iter().map(|c| v3(&c.1)).collect()),
        contact_radius: rs(&ground_spheres.iter().map(|c| c.2).collect::<Vec<_>>()),
        contact_mu: rs(&ground_spheres.iter().map(|c| c.3).collect::<Vec<_>>()),
        support_link: Array::from_vec(supports.iter().map(|c| new_index[c.0 .0] as u32).collect()),
        support_variant: Array::from_vec(supports.iter().map(|c| c.2).collect()),
        support_pos: Array::from_vec(supports.iter().map(|c| v3(&c.1.pose.pos)).collect()),
        support_rot: Array::from_vec(supports.iter().map(|c| quat(&c.1.pose.rot)).collect()),
        support_size: Array::from_vec(supports.iter().map(|c| v3(&c.1.support_size())).collect()),
        support_mu: rs(&supports.iter().map(|c| c.3).collect::<Vec<_>>()),
        ground: b.ground.map(|g| g.to()),
        muscle_origin_link: Array::from_vec(
            b.muscles()
                .iter()
                .map(|m| new_index[m.origin.0 .0] as u32)
                .collect(),
        ),
        muscle_origin_pos: Array::from_vec(b.muscles().iter().map(|m| v3(&m.origin.1)).collect()),
        muscle_insertion_link: Array::from_vec(
            b.muscles()
                .iter()
                .map(|m| new_index[m.insertion.0 .0] as u32)
                .collect(),
        ),
        muscle_insertion_pos: Array::from_vec(
            b.muscles().iter().map(|m| v3(&m.insertion.1)).collect(),
        ),
        muscle_f_max: rs(&b.muscles().iter().map(|m| m.f_max).collect::<Vec<_>>()),
        muscle_l_opt: rs(&b.muscles().iter().map(|m| m.l_opt).collect::<Vec<_>>()),
        muscle_tendon_slack: rs(&b
            .muscles()
            .iter()
            .map(|m| m.tendon_slack)
            .collect::<Vec<_>>()),
        muscle_v_max: rs(&b.muscles().iter().map(|m| m.v_max).collect::<Vec<_>>()),
        muscle_names: b.muscles().iter().map(|m| m.name.clone()).collect(),
        act_start: Array::from_vec(act.start),
        act_dof: Array::from_vec(act.dof),
        act_coord: Array::from_vec(act.coord),
        act_coef: rs(&act.coef),
        act_gear: rs(&b.actuators().iter().map(|a| a.gear).collect::<Vec<_>>()),
        act_gain: Array::from_vec(
            b.actuators()
                .iter()
                .map(|a| v3(&Vec3::from(a.gain)))
                .collect(),
        ),
        act_bias: Array::from_vec(
            b.actuators()
                .iter()
                .map(|a| v3(&Vec3::from(a.bias)))
                .collect(),
        ),
        act_limited: Array::from_vec(
            b.actuators()
                .iter()
                .map(|a| a.ctrl_range.is_some() as u32 + 2 * a.force_range.is_some() as u32)
                .collect(),
        ),
        act_ctrl_lo: rs(&b
            .actuators()
            .iter()
            .map(|a| a.ctrl_range.map_or(0.0, |r| r.0))
            .collect::<Vec<_>>()),
        act_ctrl_hi: rs(&b
            .actuators()
            .iter()
            .map(|a| a.ctrl_range.map_or(0.0, |r| r.1))
            .collect::<Vec<_>>()),
        act_force_lo: rs(&b
            .actuators()
            .iter()
            .map(|a| a.force_range.map_or(0.0, |r| r.0))
            .collect::<Vec<_>>()),
        act_force_hi: rs(&b
            .actuators()
            .iter()
            .map(|a| a.force_range.map_or(0.0, |r| r.1))
            .collect::<Vec<_>>()),
        actuator_names: b.actuators().iter().map(|a| a.name.clone()).collect(),
        tendon_start: Array::from_vec(ten.start),
        tendon_dof: Array::from_vec(ten.dof),
        tendon_coord: Array::from_vec(ten.coord),
        tendon_coef: rs(&ten.coef),
        tendon_stiffness: rs(&b
            .tendon_springs()
            .iter()
            .map(|t| t.stiffness)
            .collect::<Vec<_>>()),
        tendon_damping: rs(&b
            .tendon_springs()
            .iter()
            .map(|t| t.damping)
            .collect::<Vec<_>>()),
        tendon_rest_lo: rs(&rest.iter().map(|r| r.0).collect::<Vec<_>>()),
        tendon_rest_hi: rs(&rest.iter().map(|r| r.1).collect::<Vec<_>>()),
        seg_link: Array::from_vec(contact.segs.iter().map(|s| s.0).collect()),
        seg_a: Array::from_vec(contact.segs.iter().map(|s| v3(&s.1)).collect()),
        seg_b: Array::from_vec(contact.segs.iter().map(|s| v3(&s.2)).collect()),
        seg_radius: rs(&contact.segs.iter().map(|s| s.3).collect::<Vec<_>>()),
        box_link: Array::from_vec(contact.boxes.iter().map(|c| c.0).collect()),
        box_pos: Array::from_vec(contact.boxes.iter().map(|c| v3(&c.1.pos)).collect()),
        box_rot: Array::from_vec(
            contact
                .boxes
                .iter()
                .map(|c| {
                    let q = c.1.rot;
                    Quat::new(r(q.w), r(q.i), r(q.j), r(q.k))
                })
                .collect(),
        ),
        box_half: Array::from_vec(contact.boxes.iter().map(|c| v3(&c.2)).collect()),
        capsule_pairs: Array::from_vec(contact.capsule_pairs),
        capsule_pair_mu: rs(&contact.capsule_pair_mu),
        box_pairs: Array::from_vec(contact.box_pairs),
        link_fixed: Array::from_vec(contact.link_fixed),
        box_pair_mu: rs(&contact.box_pair_mu),
        cylinder_link: Array::from_vec(contact.cylinders.iter().map(|c| c.0).collect()),
        cylinder_pos: Array::from_vec(contact.cylinders.iter().map(|c| v3(&c.1.pos)).collect()),
        cylinder_rot: Array::from_vec(contact.cylinders.iter().map(|c| quat(&c.1.rot)).collect()),
        cylinder_size: Array::from_vec(contact.cylinders.iter().map(|c| v3(&c.2)).collect()),
        cylinder_pairs: Array::from_vec(contact.cylinder_pairs),
        cylinder_pair_mu: rs(&contact.cylinder_pair_mu),
    };
    if model.integrator == ArticulationIntegrator::ImplicitFast {
        model
            .check_implicit_fast()
            .map_err(|e| err("integrator ImplicitFast".into(), e.to_string()))?;
    }
    let m0 = check_mass_matrix(&model)?;
    scale_limits(&model, &m0);
    Ok(model)
}

/// The joints of actuators or passive tendons, flattened: each one's start, then per joint
/// its degree of freedom, coordinate and coefficient.
#[derive(Default)]
struct Transmissions {
    start: Vec<u32>,
    dof: Vec<u32>,
    coord: Vec<u32>,
    coef: Vec<f64>,
}

/// Refuses joints (of an actuator or a tendon) that are none, on a missing link, not revolute
/// or prismatic, in several worlds or with a coefficient that is not finite.
fn check_joints(
    joints: &[(LinkId, f64)],
    links: &[super::model::LinkDesc],
    world_of: &[usize],
) -> Result<(), String> {
    if joints.is_empty() {
        return Err("it acts on no joint".into());
    }
    for &(l, c) in joints {
        let Some(link) = links.get(l.0) else {
            return Err(format!("link {} does not exist", l.0));
        };
        if !link.joint.kind.is_scalar() {
            return Err(format!(
                "it acts on joint \"{}\", a {:?} joint: only revolute and prismatic joints",
                link.joint.name, link.joint.kind
            ));
        }
        if world_of[l.0] != world_of[joints[0].0 .0] || !c.is_finite() {
            return Err(format!(
                "joint \"{}\" (coefficient {c}): a tendon's joints are in one world, with \
                 finite coefficients",
                link.joint.name
            ));
        }
    }
    Ok(())
}

/// Refuses an actuator on bad joints ([`check_joints`]), with a parameter that is not finite
/// or a range whose lower end is above its upper, or added among another world's actuators;
/// and a passive tendon on bad joints or with a negative or non-finite parameter.
fn check_actuators(b: &ArticulationBuilder, world_of: &[usize]) -> Result<(), ArticulationError> {
    let links = b.links();
    for (k, t) in b.tendon_springs().iter().enumerate() {
        let what = || format!("tendon spring \"{}\" ({k})", t.name);
        check_joints(&t.joints, links, world_of).map_err(|m| err(what(), m))?;
        let rest_ok = t
            .rest
            .is_none_or(|r| r.0.is_finite() && r.1.is_finite() && r.0 <= r.1);
        let params_ok = [t.stiffness, t.damping]
            .iter()
            .all(|&x| x >= 0.0 && x.is_finite());
        if !(params_ok && rest_ok) {
            return Err(err(
                what(),
                format!(
                    "stiffness {} and damping {} must be finite and non-negative, the rest \
                     lengths {:?} finite with lower <= upper",
                    t.stiffness, t.damping, t.rest
                ),
            ));
        }
    }
    let mut last_world = 0;
    for (k, a) in b.actuators().iter().enumerate() {
        let what = format!("actuator \"{}\" ({k})", a.name);
        let e = |why: String| Err(err(what.clone(), why));
        if let Err(m) = check_joints(&a.transmission, links, world_of) {
            return e(m);
        }
        let params = [a.gear].into_iter().chain(a.gain).chain(a.bias);
        if !params.into_iter().all(f64::is_finite) {
            return e(format!(
                "gear {}, gain {:?} and bias {:?} must be finite",
                a.gear, a.gain, a.bias
            ));
        }
        for (range, name) in [(a.ctrl_range, "ctrl_range"), (a.force_range, "force_range")] {
            if let Some((lo, hi)) = range {
                if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                    return e(format!(
                        "{name} ({lo}, {hi}) must be finite with lower <= upper"
                    ));
                }
            }
        }
        let w = world_of[a.transmission[0].0 .0];
        if w < last_world {
            return e(format!(
                "it acts in world {w} but comes after an actuator of world {last_world}: add a \
                 world's actuators before the next world's"
            ));
        }
        last_world = w;
    }
    Ok(())
}

/// Scales the time-constant limits' per-unit stiffness and damping by each joint's inertia
/// as a limit sees it, `1 / (M^-1)[d][d]` at the neutral configuration (MuJoCo's
/// `dof_invweight0`): a joint deep in a chain or on a floating base moves more easily than
/// its diagonal entry of `M` says. `m` is the mass matrix there.
fn scale_limits<R: Real>(model: &Articulations<R>, m: &[R]) {
    for a in &model.articulations {
        let n = a.dofs.len();
        let block = nalgebra::DMatrix::from_fn(n, n, |i, j| m[a.m_offset + i * n + j].to_f64());
        // Positive definite (checked just before).
        let Some(inv) = block.cholesky().map(|c| c.inverse()) else {
            continue;
        };
        for i in 0..n {
            let d = a.dofs.start + i;
            let inertia = R::lit(1.0 / inv[(i, i)]);
            model.limit_k.set(d, model.limit_k.get(d) * inertia);
            model.limit_b.set(d, model.limit_b.get(d) * inertia);
            model.limit_m.set(d, inertia);
        }
    }
}

#[derive(Default)]
struct DofArrays {
    link: Vec<u32>,
    index: Vec<u32>,
    q: Vec<u32>,
    scalar: Vec<u32>,
    art_start: Vec<u32>,
    m_row: Vec<u32>,
    armature: Vec<f64>,
    damping: Vec<f64>,
    stiffness: Vec<f64>,
    spring_ref: Vec<f64>,
    kp: Vec<f64>,
    kv: Vec<f64>,
    lower: Vec<f64>,
    upper: Vec<f64>,
    limit_k: Vec<f64>,
    limit_b: Vec<f64>,
    limit_m: Vec<f64>,
    limit_imp: Vec<Vec3<f64>>,
}

/// A joint whose motion moves no mass makes the mass matrix singular: found from the
/// diagonal at the neutral configuration (and the Cholesky factorization). Returns the mass
/// matrix there.
fn check_mass_matrix<R: Real>(model: &Articulations<R>) -> Result<Vec<R>, ArticulationError> {
    let mut tape = Tape::new();
    let q = Array::from_vec(model.q0.clone());
    let m = model.mass_matrix(&mut tape, &q).to_vec();
    for a in &model.articulations {
        let n = a.dofs.len();
        for i in 0..n {
            let d = m[a.m_offset + i * n + i].to_f64();
            if !(d > 0.0) {
                let l = model.dof_link.get(a.dofs.start + i) as usize;
                return Err(err(
                    format!("joint \"{}\"", model.links[l].joint),
                    "its motion moves no mass or inertia (the mass matrix is singular); \
                     give the links it carries mass, or the joint an armature",
                ));
            }
        }
    }
    super::dynamics::factor_all(model, &m).map_err(|(art, _)| {
        let l = model.articulations[art].links.start;
        err(
            format!("articulation of link \"{}\"", model.links[l].name),
            "its mass matrix is singular at the neutral configuration (two joints move the \
             same way, or a joint moves no mass); add mass or armature",
        )
    })?;
    Ok(m)
}

/// The links' contact geometry: segments (link, ends, radius), boxes (link, pose, half
/// extents), cylinders (link, pose, radius and half-length) and the pairs that touch with
/// their friction, in the model's link order.
#[derive(Default)]
struct LinkContacts {
    segs: Vec<(u32, Vec3<f64>, Vec3<f64>, f64)>,
    boxes: Vec<(u32, Pose, Vec3<f64>)>,
    capsule_pairs: Vec<[u32; 2]>,
    capsule_pair_mu: Vec<f64>,
    box_pairs: Vec<[u32; 2]>,
    box_pair_mu: Vec<f64>,
    cylinders: Vec<(u32, Pose, Vec3<f64>)>,
    cylinder_pairs: Vec<[u32; 2]>,
    cylinder_pair_mu: Vec<f64>,
    /// See [`Articulations::link_fixed`].
    link_fixed: Vec<u32>,
}

/// The pairs of contact shapes that touch (when `link_contact` is set): in one world, on
/// links not welded together nor joined directly (after welding) nor excluded, with filters
/// that touch (`order` and `new_index`: the model's link order and its inverse). A box's
/// edges become segments (radius 0) for its pairs with other boxes.
fn link_contact_pairs(
    b: &ArticulationBuilder,
    (order, new_index): (&[usize], &[usize]),
    parent: &[Option<usize>],
    world_of: &[usize],
) -> Result<LinkContacts, ArticulationError> {
    let mut out = LinkContacts::default();
    if !b.link_contact {
        return Ok(out);
    }
    if b.ground.is_none() {
        return Err(err(
            "link_contact".into(),
            "needs a ground (its contact law is the links' too; ground_filter \
             ContactFilter::NONE keeps the ground itself from touching anything)",
        ));
    }
    // Welded groups: a link joined to its parent by a fixed joint is part of its parent's,
    // and a root on a fixed joint is part of the world (`WORLD`).
    const WORLD: usize = usize::MAX;
    let links = b.links();
    let mut weld: Vec<usize> = vec![0; parent.len()];
    for i in 0..parent.len() {
        // Parents come first in the model's order (`order[i]`: link `i`'s builder index).
        weld[i] = match (parent[i], links[order[i]].joint.kind) {
            (Some(p), JointType::Fixed) => weld[p],
            (None, JointType::Fixed) => WORLD,
            _ => i,
        };
    }
    let weld_parent = |w: usize| parent[w].map(|p| weld[p]);
    // MuJoCo's rules: nothing fixed to the world touches anything else fixed to it; welded
    // links never touch; a child never touches its parent (after welding) unless one of them
    // is the world; excluded pairs of links never touch.
    let excluded: std::collections::HashSet<(usize, usize)> = b
        .excluded_contacts()
        .iter()
        .map(|&(x, y)| {
            let (x, y) = (new_index[x.0], new_index[y.0]);
            (x.min(y), x.max(y))
        })
        .collect();
    let touch = |x: &ContactShape, y: &ContactShape| {
        let (lx, ly) = (new_index[x.link.0], new_index[y.link.0]);
        let (wx, wy) = (weld[lx], weld[ly]);
        let family = wx != WORLD
            && wy != WORLD
            && (weld_parent(wx) == Some(wy) || weld_parent(wy) == Some(wx));
        wx != wy
            && !family
            && !excluded.contains(&(lx.min(ly), lx.max(ly)))
            && x.filter.touches(&y.filter)
    };
    let shapes = b.contact_shapes();
    let mut seg_of = vec![None; shapes.len()];
    let mut box_of = vec![None; shapes.len()];
    let mut edges_of: Vec<Option<usize>> = vec![None; shapes.len()];
    let mut cyl_of = vec![None; shapes.len()];
    let link_of = |c: &ContactShape| new_index[c.link.0] as u32;
    // Shapes of different worlds never touch: pairs are searched for world by world.
    let mut by_world = vec![Vec::new(); world_of.iter().max().map_or(0, |w| w + 1)];
    for (k, c) in shapes.iter().enumerate() {
        by_world[world_of[c.link.0]].push(k);
    }
    for (i, j) in by_world.iter().flat_map(|w| {
        w.iter()
            .enumerate()
            .flat_map(move |(a, &i)| w[a + 1..].iter().map(move |&j| (i, j)))
    }) {
        let (x, y) = (&shapes[i], &shapes[j]);
        {
            if !touch(x, y) {
                continue;
            }
            let mut seg = |k: usize, out: &mut LinkContacts| -> u32 {
                *seg_of[k].get_or_insert_with(|| {
                    let (a, e, r) = shapes[k].segment().expect("a sphere or capsule");
                    out.segs.push((link_of(&shapes[k]), a, e, r));
                    out.segs.len() - 1
                }) as u32
            };
            let mut bx = |k: usize, out: &mut LinkContacts| -> u32 {
                *box_of[k].get_or_insert_with(|| {
                    let GeomShape::Box(half) = shapes[k].shape else {
                        unreachable!("a box")
                    };
                    out.boxes.push((link_of(&shapes[k]), shapes[k].pose, half));
                    out.boxes.len() - 1
                }) as u32
            };
            let cylinder = |c: &ContactShape| matches!(c.shape, GeomShape::Cylinder(..));
            let with_segment =
                |c: &ContactShape, o: &ContactShape| cylinder(c) && o.segment().is_some();
            let round = |c: &ContactShape| !c.ground_supports().is_empty();
            if (round(x) || round(y)) && !with_segment(x, y) && !with_segment(y, x) {
                let shape = |k: usize| {
                    let c = &shapes[k];
                    format!(
                        "contact shape {k} ({:?}) on \"{}\"",
                        c.shape, links[c.link.0].name
                    )
                };
                return Err(err(
                    format!("{} and {}", shape(i), shape(j)),
                    "would touch, and a cylinder touches only the ground, particles, spheres \
                     and capsules, an ellipsoid only the ground; exclude the pair \
                     (ArticulationBuilder::exclude_contact, MJCF <exclude>), give the shapes \
                     filters that do not touch (MJCF contype and conaffinity), set \
                     link_contact to false, or use a capsule or box",
                ));
            }
            let mu = b.contact_friction(x, Some(y));
            let mut cyl = |k: usize, out: &mut LinkContacts| -> u32 {
                *cyl_of[k].get_or_insert_with(|| {
                    let c = &shapes[k];
                    out.cylinders.push((link_of(c), c.pose, c.support_size()));
                    out.cylinders.len() - 1
                }) as u32
            };
            if cylinder(x) || cylinder(y) {
                let (s, c) = if cylinder(x) { (j, i) } else { (i, j) };
                let pair = [seg(s, &mut out), cyl(c, &mut out)];
                out.cylinder_pairs.push(pair);
                out.cylinder_pair_mu.push(mu);
                continue;
            }
            match (x.segment().is_some(), y.segment().is_some()) {
                (true, true) => {
                    let pair = [seg(i, &mut out), seg(j, &mut out)];
                    out.capsule_pairs.push(pair);
                    out.capsule_pair_mu.push(mu);
                }
                (true, false) => {
                    let pair = [seg(i, &mut out), bx(j, &mut out)];
                    out.box_pairs.push(pair);
                    out.box_pair_mu.push(mu);
                }
                (false, true) => {
                    let pair = [seg(j, &mut out), bx(i, &mut out)];
                    out.box_pairs.push(pair);
                    out.box_pair_mu.push(mu);
                }
                (false, false) => {
                    // Each box's edges against the other box: crossing edges touch, and a
                    // corner inside the other box sinks the three edges that meet there.
                    for (c, o) in [(i, j), (j, i)] {
                        let first = *edges_of[c].get_or_insert_with(|| {
                            let GeomShape::Box(half) = shapes[c].shape else {
                                unreachable!("a box")
                            };
                            let start = out.segs.len();
                            for (a, e) in shapes[c].edges(&half) {
                                out.segs.push((link_of(&shapes[c]), a, e, 0.0));
                            }
                            start
                        });
                        let other = bx(o, &mut out);
                        for k in 0..12 {
                            out.box_pairs.push([(first + k) as u32, other]);
                            out.box_pair_mu.push(mu);
                        }
                    }
                }
            }
        }
    }
    // Which links are fixed to the world, if a pair has one on one side.
    let fixed: Vec<u32> = weld.iter().map(|&w| u32::from(w == WORLD)).collect();
    let one_fixed = |la: u32, lb: u32| fixed[la as usize] + fixed[lb as usize] == 1;
    let seg_link = |s: u32| out.segs[s as usize].0;
    let against_fixed = out
        .capsule_pairs
        .iter()
        .any(|&[s, t]| one_fixed(seg_link(s), seg_link(t)))
        || out
            .box_pairs
            .iter()
            .any(|&[s, k]| one_fixed(seg_link(s), out.boxes[k as usize].0))
        || out
            .cylinder_pairs
            .iter()
            .any(|&[s, k]| one_fixed(seg_link(s), out.cylinders[k as usize].0));
    if against_fixed {
        out.link_fixed = fixed;
    }
    Ok(out)
}

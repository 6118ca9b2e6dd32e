//! Actuators as MuJoCo's: a control `ctrl` turned into a force on one joint.
//!
//! An [`Actuator`] with gear `g` on a hinge or slide joint has the length `l = g q` and the
//! speed `v = g qd` (`q`, `qd` its joint's coordinate and velocity); on a fixed tendon, a
//! combination `sum_i c_i q_i` of such joints' coordinates (MuJoCo's `<fixed>` tendon), it
//! has `l = g sum_i c_i q_i` and `v = g sum_i c_i qd_i`. Its control is clamped
//! to `ctrl_range` when it has one, and its force is
//! `f = (gain[0] + gain[1] l + gain[2] v) ctrl + bias[0] + bias[1] l + bias[2] v`,
//! clamped to `force_range` when it has one; the joint gets the generalized force `g f` (each
//! joint of a tendon `g c_i f`).
//! This is MuJoCo's general actuator without activation dynamics (`dyntype="none"`, affine
//! gain and bias), which MuJoCo's shortcuts are:
//!
//! | MJCF | gain | bias |
//! |---|---|---|
//! | `<motor>` | `(1, 0, 0)` | `(0, 0, 0)` |
//! | `<position kp kv>` | `(kp, 0, 0)` | `(0, -kp, -kv)` |
//! | `<velocity kv>` | `(kv, 0, 0)` | `(0, 0, -kv)` |
//! | `<general gainprm biasprm>` | `gainprm` (`gaintype="affine"`) or its first | `biasprm` |
//!
//! The force is explicit in the step, as in MuJoCo's Euler and RK4 integrators; its speed terms
//! join the solve with [`ArticulationIntegrator::ImplicitFast`](super::ArticulationIntegrator),
//! as in MuJoCo's `implicitfast`. The controls are
//! [`ArticulationControl::ctrl`](super::ArticulationControl), one per actuator in the order
//! they were added (each world's together, [`WorldInfo::actuators`](super::WorldInfo)); they
//! and every actuator parameter of the model can require gradients.
//!
//! ```
//! use adflex_kernels::articulation::*;
//! use adflex_runtime::prelude::*;
//!
//! let mut b = ArticulationBuilder::new();
//! b.gravity = Vec3::zeros();
//! let l = b.add_link("pole", None, Joint::revolute(Vec3::y()),
//!     Inertial::sphere(1.0, 0.1, Vec3::new(0.5, 0.0, 0.0)));
//! // A servo to ctrl: kp = 10, kv = 2.
//! b.add_actuator(Actuator::position(l, 10.0, 2.0).ctrl_range(-1.0, 1.0));
//! let model = b.finalize::<f64>().unwrap();
//! let control = ArticulationControl {
//!     ctrl: Array::from_vec(vec![0.5]),
//!     ..model.control()
//! };
//! let mut s = model.state();
//! for _ in 0..4000 {
//!     s = model.step(&mut Tape::new(), &s, Some(&control), 1e-3).unwrap();
//! }
//! assert!((s.q.get(0) - 0.5).abs() < 1e-3);
//! ```

use adflex_macros::diff_kernel;
use adflex_runtime::prelude::*;

use super::pose::LinkId;

/// An actuator on the joint of one link (see the [module](self) for its force).
#[derive(Clone, Debug, PartialEq)]
pub struct Actuator {
    /// Name, for errors (empty if none).
    pub name: String,
    /// What it drives: joints (of links; revolute or prismatic) and their coefficients in
    /// the length, `[(link, 1.0)]` for one joint, several for a fixed tendon.
    pub transmission: Vec<(LinkId, f64)>,
    /// The gear `g`: length `g q`, generalized force `g f`.
    pub gear: f64,
    /// The gain's constant, length and speed terms.
    pub gain: [f64; 3],
    /// The bias's constant, length and speed terms.
    pub bias: [f64; 3],
    /// The control's range (`None`: not clamped).
    pub ctrl_range: Option<(f64, f64)>,
    /// The force's range (`None`: not clamped).
    pub force_range: Option<(f64, f64)>,
}

impl Actuator {
    /// A motor on the joint of `link`: force `ctrl` (gear 1).
    pub fn motor(link: LinkId) -> Self {
        Actuator {
            name: String::new(),
            transmission: vec![(link, 1.0)],
            gear: 1.0,
            gain: [1.0, 0.0, 0.0],
            bias: [0.0; 3],
            ctrl_range: None,
            force_range: None,
        }
    }

    /// A position servo: force `kp (ctrl - l) - kv v`.
    pub fn position(link: LinkId, kp: f64, kv: f64) -> Self {
        Actuator {
            gain: [kp, 0.0, 0.0],
            bias: [0.0, -kp, -kv],
            ..Actuator::motor(link)
        }
    }

    /// A velocity servo: force `kv (ctrl - v)`.
    pub fn velocity(link: LinkId, kv: f64) -> Self {
        Actuator {
            gain: [kv, 0.0, 0.0],
            bias: [0.0, 0.0, -kv],
            ..Actuator::motor(link)
        }
    }

    /// On a fixed tendon instead of one joint: length `sum_i c_i q_i` of the joints of
    /// `joints` (links and coefficients `c_i`).
    pub fn fixed_tendon(self, joints: Vec<(LinkId, f64)>) -> Self {
        Actuator {
            transmission: joints,
            ..self
        }
    }

    /// With this gear.
    pub fn gear(self, gear: f64) -> Self {
        Actuator { gear, ..self }
    }

    /// With the control clamped to `[lower, upper]`.
    pub fn ctrl_range(self, lower: f64, upper: f64) -> Self {
        Actuator {
            ctrl_range: Some((lower, upper)),
            ..self
        }
    }

    /// With the force clamped to `[lower, upper]`.
    pub fn force_range(self, lower: f64, upper: f64) -> Self {
        Actuator {
            force_range: Some((lower, upper)),
            ..self
        }
    }

    /// With this name.
    pub fn named(self, name: impl Into<String>) -> Self {
        Actuator {
            name: name.into(),
            ..self
        }
    }
}

/// A passive fixed tendon (MuJoCo's `<fixed stiffness damping springlength>`): with length
/// `l = sum_i c_i q_i` and speed `v = sum_i c_i qd_i` of its joints, the force
/// `f = -stiffness (l - rest.1) - damping v` above `rest.1`, `-stiffness (l - rest.0) -
/// damping v` below `rest.0` and `-damping v` between (a dead band when the two differ); each
/// joint gets `c_i f`. Both are explicit in the step, as in MuJoCo, except the damping under
/// [`ArticulationIntegrator::ImplicitFast`](super::ArticulationIntegrator), which joins the
/// solve (MuJoCo's `implicitfast`).
#[derive(Clone, Debug, PartialEq)]
pub struct TendonSpring {
    /// Name, for errors (empty if none).
    pub name: String,
    /// Its joints (of links; revolute or prismatic) and their coefficients `c_i`.
    pub joints: Vec<(LinkId, f64)>,
    /// Stiffness (N/m or N m/rad per unit of length), non-negative.
    pub stiffness: f64,
    /// Damping, non-negative.
    pub damping: f64,
    /// The rest lengths, lower and upper (`None`: the length at the joints' spring references,
    /// [`Joint::stiffness`](super::Joint::stiffness)'s, as MuJoCo's default).
    pub rest: Option<(f64, f64)>,
}

/// Passive tendon `tid` on the joints `k` in `start[tid]..start[tid + 1]` (as
/// [`articulation_actuators`]'): adds `coef[k] f` to `act_tau[dof[k]]`, `f` the force of
/// [`TendonSpring`] with `stiffness`, `damping`, `rest_lo`, `rest_hi`.
#[diff_kernel]
pub fn articulation_tendon_springs<R: Real>(
    start: &Array<u32>,
    dof: &Array<u32>,
    coord: &Array<u32>,
    coef: &Array<R>,
    stiffness: &Array<R>,
    damping: &Array<R>,
    rest_lo: &Array<R>,
    rest_hi: &Array<R>,
    q: &Array<R>,
    qd: &Array<R>,
    act_tau: &Array<R>,
) {
    let t = tid();
    let k0 = start[t] as usize;
    let k1 = start[t + 1] as usize;
    let mut l = stiffness[t] * 0.0;
    let mut v = stiffness[t] * 0.0;
    for k in k0..k1 {
        l = l + coef[k] * q[coord[k] as usize];
        v = v + coef[k] * qd[dof[k] as usize];
    }
    let mut f = -damping[t] * v;
    if l > rest_hi[t] {
        f = f - stiffness[t] * (l - rest_hi[t]);
    }
    if l < rest_lo[t] {
        f = f - stiffness[t] * (l - rest_lo[t]);
    }
    for k in k0..k1 {
        act_tau.atomic_add(dof[k] as usize, coef[k] * f);
    }
}

/// Actuator `tid` on the degrees of freedom `dof[k]` (coordinates `coord[k]`) with
/// coefficients `coef[k]`, `k` in `start[tid]..start[tid + 1]`: adds `gear coef[k] f` to
/// `act_tau[dof[k]]`, `f` the module's force. `limited` has bit 0 for a clamped control (to
/// `ctrl_lo`, `ctrl_hi`) and bit 1 for a clamped force (to `force_lo`, `force_hi`).
///
/// `damping[tid]` gets the actuator's damping as the implicit integrator sees it (MuJoCo's
/// `implicitfast`): `-d f / d v` times `gear^2`, zero while the force is at a limit of its
/// range (as MuJoCo, which skips a clamped actuator).
#[diff_kernel]
pub fn articulation_actuators<R: Real>(
    start: &Array<u32>,
    dof: &Array<u32>,
    coord: &Array<u32>,
    coef: &Array<R>,
    gear: &Array<R>,
    gain: &Array<Vec3<R>>,
    bias: &Array<Vec3<R>>,
    limited: &Array<u32>,
    ctrl_lo: &Array<R>,
    ctrl_hi: &Array<R>,
    force_lo: &Array<R>,
    force_hi: &Array<R>,
    ctrl: &Array<R>,
    q: &Array<R>,
    qd: &Array<R>,
    act_tau: &Array<R>,
    damping: &Array<R>,
) {
    let t = tid();
    let g = gear[t];
    let k0 = start[t] as usize;
    let k1 = start[t + 1] as usize;
    let mut l = g * 0.0;
    let mut v = g * 0.0;
    for k in k0..k1 {
        l = l + coef[k] * q[coord[k] as usize];
        v = v + coef[k] * qd[dof[k] as usize];
    }
    l = g * l;
    v = g * v;
    let mut c = ctrl[t];
    if limited[t] % 2 == 1 {
        c = clamp(c, ctrl_lo[t], ctrl_hi[t]);
    }
    let k = gain[t];
    let b = bias[t];
    let mut f = (k.x + k.y * l + k.z * v) * c + b.x + b.y * l + b.z * v;
    let mut free = 1;
    if limited[t] / 2 == 1 {
        if f <= force_lo[t] || f >= force_hi[t] {
            free = 0;
        }
        f = clamp(f, force_lo[t], force_hi[t]);
    }
    for k in k0..k1 {
        act_tau.atomic_add(dof[k] as usize, g * coef[k] * f);
    }
    if free == 1 {
        damping[t] = -(k.z * c + b.z) * g * g;
    }
}

/// Implicit velocity coupling `tid` (MuJoCo's `implicitfast`): a damping `damping[tid]` on
/// the combination `sum_k coef[k] qd[dof[k]]`, `k` in `start[tid]..start[tid + 1]` (a tendon's
/// or an actuator's joints, of one articulation), adds `h damping coef[i] coef[j]` to the mass
/// matrix's entry `(dof[i], dof[j])` (rows at `m_row`, blocks from `art_start`), so that the
/// step solves with `M - h df/dqd`.
#[diff_kernel]
pub fn articulation_implicit_damping<R: Real>(
    start: &Array<u32>,
    dof: &Array<u32>,
    coef: &Array<R>,
    damping: &Array<R>,
    art_start: &Array<u32>,
    m_row: &Array<u32>,
    h: R,
    m: &Array<R>,
) {
    let t = tid();
    let k0 = start[t] as usize;
    let k1 = start[t + 1] as usize;
    let s = damping[t] * h;
    for i in k0..k1 {
        let di = dof[i] as usize;
        let row = m_row[di] as usize;
        let first = art_start[di] as usize;
        for j in k0..k1 {
            let dj = dof[j] as usize;
            m.atomic_add(row + dj - first, s * coef[i] * coef[j]);
        }
    }
}

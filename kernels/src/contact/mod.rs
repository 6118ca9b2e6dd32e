//! Contact: particles against the ground plane, against each other (with a uniform-grid broad
//! phase), and against analytic shapes (sphere, box, capsule SDFs). All are penalty forces
//! with the smoothed Coulomb friction of dFlex.

pub mod ground;
pub mod law;
pub mod particle;
pub mod shapes;

//! Optimization with the tape's gradients.

//! physics kernels

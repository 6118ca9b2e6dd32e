//! Looking at a simulation: export a rollout to files other tools open (PLY / OBJ sequences,
//! USD), draw it (PNG, animated GIF), and plot an optimization's loss curve.

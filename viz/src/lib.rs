//! Looking at a simulation: export a rollout to files other tools open (PLY / OBJ sequences,
//! USD), draw it (PNG, animated GIF), and plot an optimization's loss curve.
//!
//! Everything here takes a [`Model`](adflex_kernels::Model) and one or more
//! [`State`](adflex_kernels::State)s, reads their arrays on the host (`to_vec`) and writes
//! files; nothing touches a tape or needs a system library, a GPU or a font.
//!
//! - [`export`]: frames as PLY or OBJ meshes (Blender, MeshLab, ParaView), a whole rollout as
//!   one USD ASCII stage (Omniverse, Blender, usdview).
//! - [`gltf`]: a whole rollout as one animated binary glTF 2.0 file (Blender, web viewers).
//! - [`render`]: pictures drawn on the CPU with `tiny-skia`: a PNG of one state, an animated
//!   GIF of a rollout, or the raw pixels.
//! - [`overlay`]: targets, trails, a ghost of the first guess, colours by a value with a
//!   colour bar, captions, drawn over those pictures.
//! - [`plot`]: line charts with `plotters`, SVG or PNG: a loss curve, or several named curves.
//!
//! ```
//! use adflex_kernels::prelude::*;
//! use adflex_runtime::Tape;
//! use adflex_kernels::scenes::cloth;
//! use adflex_viz::{export, render};
//!
//! // A small cloth, 20 steps, keeping every state.
//! let scene = cloth::build::<f64>(4);
//! let mut tape = Tape::new();
//! let mut states = vec![scene.initial.clone()];
//! for _ in 0..20 {
//!     let s = SemiImplicitEuler
//!         .step(&scene.model, &mut tape, states.last().unwrap(), None, 1e-3)
//!         .unwrap();
//!     states.push(s);
//! }
//! let dir = std::env::temp_dir().join(format!("adflex-viz-doc-lib-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! export::write_usda(dir.join("cloth.usda"), &scene.model, &states, 60.0).unwrap();
//! let opts = render::RenderOptions::default();
//! render::render_png(dir.join("cloth.png"), &scene.model, states.last().unwrap(), &opts).unwrap();
//! # std::fs::remove_dir_all(&dir).ok();
//! ```

use std::path::{Path, PathBuf};

mod color;
pub mod export;
pub mod gltf;
pub mod overlay;
pub mod plot;
pub mod points;
mod raster;
pub mod render;
mod scene;

/// What can go wrong writing a file. Every variant that concerns a file names its path.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Creating or writing the file (or its directory) failed.
    #[error("cannot write {}: {source}", path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// There was nothing to write: an empty list of states, losses or curves.
    #[error("nothing to write to {}: {what}", path.display())]
    Empty {
        /// The file or directory that was not written.
        path: PathBuf,
        /// What was empty.
        what: &'static str,
    },
    /// Encoding the picture or the chart failed.
    #[error("cannot encode {}: {message}", path.display())]
    Encode {
        /// The file.
        path: PathBuf,
        /// What the encoder said.
        message: String,
    },
    /// The options cannot give a picture (a zero or too large size, a non-finite camera).
    #[error("invalid options: {0}")]
    Invalid(String),
}

/// `Result` with this crate's [`Error`].
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    /// The file or directory the error concerns, if any.
    ///
    /// ```
    /// use adflex_viz::Error;
    /// let e = Error::Empty { path: "a.ply".into(), what: "no states" };
    /// assert_eq!(e.path().unwrap(), std::path::Path::new("a.ply"));
    /// ```
    pub fn path(&self) -> Option<&Path> {
        match self {
            Error::Io { path, .. } | Error::Empty { path, .. } | Error::Encode { path, .. } => {
                Some(path)
            }
            Error::Invalid(_) => None,
        }
    }

    pub(crate) fn io(path: &Path, source: std::io::Error) -> Self {
        Error::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

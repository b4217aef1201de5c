//! Reconstruction for Periscope: 3D Gaussian Transient Rendering (3D-GTR), relay
//! geometry, virtual confocal synthesis and the conventional solvers.
//!
//! This crate depends on no other crate of the workspace: it works in hidden path
//! length on transients whose first and last legs the daemon has already removed, so
//! it can reconstruct stored or public captures as well as live ones. It reads and
//! writes y-tal HDF5 captures itself ([`io::ytal`]: the community's interchange format
//! and the public datasets converted to it), so a library user reconstructs a capture
//! file without the daemon.
#![warn(missing_docs)]

pub mod adaptive;
pub mod gpu;
pub mod gtr;
pub mod io;
pub mod linalg;
pub mod relay;
pub mod roi;
pub mod simd;
pub mod solver;
pub mod special;
pub mod synth;
pub mod transient;
pub mod volume;

pub use roi::{RoiBox, RoiError};
pub use transient::{C0, Pair, TimeAxis, TransientError, TransientSet};
pub use volume::{DepthAxis, DepthMap, Volume, VolumeGrid};

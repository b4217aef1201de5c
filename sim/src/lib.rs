//! The simulated NLOS instrument: galvo firmware on a pseudo-terminal, a TDC device
//! behind the USB transport, and the scene physics (relay and hidden meshes, ray
//! casting, first- and third-bounce transients, SPAD noise) that feeds them.
//!
//! Its light transport is mesh-based and independent of the 3D-GTR renderer in
//! `periscope-recon`, so reconstructions judged on simulated data are not the model
//! tested against itself.
#![warn(missing_docs)]

pub mod bvh;
pub mod detector;
pub mod devices;
pub mod mesh;
pub mod scene;
pub mod shapes;
pub mod transport;
pub mod truth;

pub use detector::{Detector, sample_counts};
pub use mesh::Mesh;
pub use scene::{RawScene, Scene, SceneError};
pub use transport::{Instrument, SpotPair, SurfaceHit, World};

//! 3D Gaussian Transient Rendering: the forward model, its analytic gradient, and the
//! optimiser that fits primitives to measured transients.
pub mod init;
pub mod kernel;
mod lanes;
pub mod model;
pub mod optim;
pub mod ply;
pub mod render;
pub mod train;

pub use init::Init;
#[cfg(feature = "gpu")]
pub(crate) use kernel::SIGMA_FLOOR_BINS;
pub use kernel::{Kernel, Loss, PhysicalGrad, RenderOptions, render_pair};
pub use model::{GaussianCloud, MapSlopes, ModelError, Primitive, RawGrads, ScaleBounds};
pub use optim::{AdamW, AdamWSettings, GroupSettings, Schedule};
pub use ply::write_ply;
pub use render::{batch_loss, batch_loss_grad, batch_loss_grad_gpu, render_pairs, render_set};
pub use train::{
    AverageBatch, CancelToken, CoarseFit, Convergence, DENSIFY_ROUNDS, DensifySettings, GAIN_START,
    GAIN_STEP, GROW_FROM, LiveModel, LossChoice, PairGains, PruneSettings, SEPARATION_BINS, SNAPSHOT_MAX,
    SurfacePrior, TrainConfig, TrainError, TrainEvent, TrainSummary, Trainer, default_initial_scale,
    default_target_scale, densify, densify_after, estimate_background, estimate_pair_gains, first_negative,
    gain_groups, gain_start_epoch, resolvable_separation, starting_primitives,
};

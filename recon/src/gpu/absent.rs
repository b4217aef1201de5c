//! The GPU path's interface in a build without the `gpu` feature. No [`Gpu`] can be
//! made here ([`Gpu::open`] says why), so the routines below can never be called; they
//! keep the callers' code the same in both builds.
use std::convert::Infallible;

use super::{BatchGradient, DeviceInfo, GpuError, Optimiser, Resident, Step, Steps};
use crate::gtr::{Kernel, RenderOptions};
use crate::transient::{Pair, TimeAxis};
use crate::volume::VolumeGrid;

/// An open GPU: none exists in this build.
pub struct Gpu {
    never: Infallible,
}

impl std::fmt::Debug for Gpu {
    fn fmt(&self, _: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.never {}
    }
}

impl Gpu {
    /// Always [`GpuError::NotBuilt`].
    pub fn open(_allow_software: bool) -> Result<Gpu, GpuError> {
        Err(GpuError::NotBuilt)
    }

    /// What the outputs record of this GPU.
    pub fn device_info(&self) -> DeviceInfo {
        match self.never {}
    }
}

/// The GPU build's `render_pairs`.
pub fn render_pairs(
    gpu: &Gpu,
    _: &[Kernel],
    _: &[Pair],
    _: &TimeAxis,
    _: &RenderOptions,
) -> Result<Vec<f32>, GpuError> {
    match gpu.never {}
}

/// The GPU build's `batch_gradient`.
pub fn batch_gradient(
    gpu: &Gpu,
    _: &[Kernel],
    _: &[Pair],
    _: &[f32],
    _: &[[f32; 4]],
    _: &TimeAxis,
    _: &RenderOptions,
) -> Result<BatchGradient, GpuError> {
    match gpu.never {}
}

/// The GPU build's `backproject`.
#[allow(clippy::too_many_arguments)]
pub fn backproject(
    gpu: &Gpu,
    _: &[([f32; 3], [f32; 3])],
    _: &[Vec<f32>],
    _: usize,
    _: &VolumeGrid,
    _: &TimeAxis,
    _: usize,
    _: f64,
) -> Result<Vec<f32>, GpuError> {
    match gpu.never {}
}

/// The GPU build's `fit_steps`.
#[allow(clippy::too_many_arguments)]
pub fn fit_steps(
    gpu: &Gpu,
    _: &[Kernel],
    _: &mut Resident,
    _: &Optimiser,
    _: usize,
    _: &mut dyn FnMut(usize) -> Step,
    _: &TimeAxis,
    _: &RenderOptions,
    _: Option<(usize, &[[f64; 2]])>,
    _: &dyn Fn() -> bool,
) -> Result<Steps, GpuError> {
    match gpu.never {}
}

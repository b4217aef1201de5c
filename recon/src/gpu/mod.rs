//! The reconstruction on a GPU: the 3D-GTR fit's step (forward render, residuals and
//! analytic backward pass), the virtual confocal synthesis and filtered
//! backprojection as WGSL compute shaders, run through [`wgpu`] on whatever Vulkan,
//! Metal or DX12 adapter the machine has.
//!
//! The CPU path stays the reference and the default where no adapter is found
//! ([`ComputeDevice::Auto`]). Every GPU routine here is tested against its CPU
//! counterpart within a stated f32 tolerance; without a hardware GPU those tests run on
//! Mesa's software Vulkan (lavapipe, Debian's `mesa-vulkan-drivers`), and they say
//! plainly when no adapter at all is found and they skip.
//!
//! Why wgpu rather than CubeCL/burn: the kernels are a few small, hand-written shaders
//! with an analytic gradient, no autodiff or tensor algebra to borrow, and wgpu is the layer those build on,
//! maintained by the same community, with no code generation between our source and
//! the driver.
//!
//! All of it is behind the crate's `gpu` feature (on by default). A build without it
//! (the fuzz crate's) keeps this module's interface, but no GPU can be opened there:
//! `gpu` is refused with [`GpuError::NotBuilt`] and `auto` runs on the CPU.
#[cfg(not(feature = "gpu"))]
mod absent;
#[cfg(feature = "gpu")]
mod backproject;
#[cfg(feature = "gpu")]
mod fit;
#[cfg(feature = "gpu")]
mod render;
mod resident;

use std::sync::{Arc, OnceLock};

#[cfg(not(feature = "gpu"))]
pub use absent::{Gpu, backproject, batch_gradient, fit_steps, render_pairs};
#[cfg(feature = "gpu")]
pub use backproject::backproject;
#[cfg(feature = "gpu")]
pub use fit::{batch_gradient, fit_steps};
#[cfg(feature = "gpu")]
pub use render::render_pairs;
pub use resident::{Optimiser, RAW, Resident, Step, Steps};

/// A mini-batch's loss terms and gradients, as the GPU computed them
/// ([`batch_gradient`]).
#[derive(Clone, Debug)]
pub struct BatchGradient {
    /// Each pair's weighted share of the loss, in the batch's order.
    pub losses: Vec<f32>,
    /// Each primitive's gradient with respect to its physical parameters.
    pub grads: Vec<crate::gtr::PhysicalGrad>,
}

/// Where the reconstruction's heavy work runs: `[compute] device` in a `RECON.toml`
/// (`[recon.compute]` in a plan).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ComputeDevice {
    /// A hardware GPU when one is found (discrete first), else the CPU.
    #[default]
    Auto,
    /// The CPU (the reference).
    Cpu,
    /// A GPU, or an error when none is usable. A software adapter (lavapipe) counts,
    /// with a warning: it is how CI checks the GPU path, not a way to go faster.
    Gpu,
}

impl std::fmt::Display for ComputeDevice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            ComputeDevice::Auto => "auto",
            ComputeDevice::Cpu => "cpu",
            ComputeDevice::Gpu => "gpu",
        })
    }
}

/// Why the GPU path could not run.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum GpuError {
    /// No adapter of the kind asked for.
    #[error(
        "no GPU is usable ({found}): install the GPU's Vulkan driver (or Mesa's software one, Debian's \
         `mesa-vulkan-drivers`, to check the GPU path; NVIDIA's loads only with GLVND beside it, Debian's \
         `libglvnd0` and `libglx0`, and `VK_LOADER_DEBUG=driver` shows what the Vulkan loader tried), or set \
         [compute] device = \"cpu\" or \"auto\""
    )]
    NoAdapter {
        /// The adapters seen, or "no Vulkan, Metal or DX12 adapter".
        found: String,
    },
    /// The adapter refused a device.
    #[error(
        "the GPU {adapter} refused a device: {reason}; set [compute] device = \"cpu\" to reconstruct on the CPU"
    )]
    Device {
        /// Adapter name.
        adapter: String,
        /// wgpu's reason.
        reason: String,
    },
    /// A shader or a transfer failed at run time (out of memory, a lost device).
    #[error(
        "the GPU {adapter} failed while {what}: {reason}; set [compute] device = \"cpu\" to reconstruct on the CPU"
    )]
    Run {
        /// Adapter name.
        adapter: String,
        /// What was running.
        what: &'static str,
        /// wgpu's reason.
        reason: String,
    },
    /// This build has no GPU path.
    #[error(
        "this build of Periscope has no GPU path (built without periscope-recon's `gpu` feature): \
         rebuild with it, or set [compute] device = \"cpu\" or \"auto\""
    )]
    NotBuilt,
}

/// What a run's outputs record of the device the reconstruction ran on.
#[derive(Clone, Debug, PartialEq, Eq, serde::Serialize)]
pub struct DeviceInfo {
    /// `"cpu"` or `"gpu"`.
    pub device: &'static str,
    /// Adapter name (GPU only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adapter: Option<String>,
    /// Backend, e.g. `"vulkan"` (GPU only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub backend: Option<String>,
    /// Driver and its version (GPU only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub driver: Option<String>,
    /// Whether the adapter is a software one (lavapipe, WARP).
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub software: bool,
}

impl std::fmt::Display for DeviceInfo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match &self.adapter {
            None => f.write_str("cpu"),
            Some(a) => write!(
                f,
                "gpu: {a} ({}, {}{})",
                self.backend.as_deref().unwrap_or("?"),
                self.driver.as_deref().unwrap_or("?"),
                if self.software { ", software" } else { "" }
            ),
        }
    }
}

/// An open GPU: its device, queue and compiled pipelines.
#[cfg(feature = "gpu")]
pub struct Gpu {
    device: wgpu::Device,
    queue: wgpu::Queue,
    info: wgpu::AdapterInfo,
    limits: wgpu::Limits,
    render: OnceLock<wgpu::ComputePipeline>,
    reduce: OnceLock<wgpu::ComputePipeline>,
    residual: OnceLock<wgpu::ComputePipeline>,
    backward: OnceLock<wgpu::ComputePipeline>,
    update: OnceLock<wgpu::ComputePipeline>,
    backproject: OnceLock<wgpu::ComputePipeline>,
}

/// The most workgroups of one dispatch along an axis (WebGPU's default limit, which
/// every adapter offers).
#[cfg(feature = "gpu")]
const MAX_GROUPS: usize = 65_535;

#[cfg(feature = "gpu")]
impl std::fmt::Debug for Gpu {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Gpu").field("adapter", &self.info.name).finish()
    }
}

/// Where a reconstruction computes: the CPU, or an open GPU.
#[derive(Clone, Debug, Default)]
pub enum Compute {
    /// The CPU path (the reference).
    #[default]
    Cpu,
    /// A GPU.
    Gpu(Arc<Gpu>),
}

impl PartialEq for Compute {
    fn eq(&self, other: &Self) -> bool {
        match (self, other) {
            (Compute::Cpu, Compute::Cpu) => true,
            (Compute::Gpu(a), Compute::Gpu(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
}

impl Compute {
    /// Opens what `device` asks for: [`ComputeDevice::Auto`] a hardware GPU when one is
    /// found and the CPU otherwise (never an error), [`ComputeDevice::Gpu`] the best
    /// adapter of any kind or [`GpuError::NoAdapter`]. The device is opened once per
    /// process and shared.
    pub fn open(device: ComputeDevice) -> Result<Compute, GpuError> {
        match device {
            ComputeDevice::Cpu => Ok(Compute::Cpu),
            ComputeDevice::Auto if !may_have_hardware_gpu() => {
                tracing::debug!("no GPU device node: the reconstruction runs on the CPU");
                Ok(Compute::Cpu)
            }
            ComputeDevice::Auto => match shared(false) {
                Ok(gpu) => Ok(Compute::Gpu(gpu)),
                Err(e) => {
                    tracing::debug!(reason = %e, "no hardware GPU: the reconstruction runs on the CPU");
                    Ok(Compute::Cpu)
                }
            },
            ComputeDevice::Gpu => shared(true).map(Compute::Gpu),
        }
    }

    /// The open GPU, if any.
    pub fn gpu(&self) -> Option<&Gpu> {
        match self {
            Compute::Cpu => None,
            Compute::Gpu(g) => Some(g),
        }
    }

    /// What the outputs record of this device.
    pub fn info(&self) -> DeviceInfo {
        match self {
            Compute::Cpu => DeviceInfo {
                device: "cpu",
                adapter: None,
                backend: None,
                driver: None,
                software: false,
            },
            Compute::Gpu(g) => g.device_info(),
        }
    }
}

/// Whether a hardware GPU can be here at all: on Linux, a DRM render node
/// (`/dev/dri/renderD*`: Mesa's and AMD's drivers) or an NVIDIA device node
/// (`/dev/nvidia*`); elsewhere, yes. Without one, `auto` does not load the Vulkan
/// drivers: they cost about 50 MiB of resident memory, and a software one may write
/// to standard error (Mesa's, about `XDG_RUNTIME_DIR`), which would break JSON logs.
fn may_have_hardware_gpu() -> bool {
    if !cfg!(target_os = "linux") {
        return true;
    }
    let any = |dir: &str, prefix: &str| {
        std::fs::read_dir(dir).is_ok_and(|d| {
            d.flatten()
                .any(|e| e.file_name().to_string_lossy().starts_with(prefix))
        })
    };
    any("/dev/dri", "renderD") || any("/dev", "nvidia")
}

/// The process's GPU, opened on first use: hardware only, or any adapter.
fn shared(allow_software: bool) -> Result<Arc<Gpu>, GpuError> {
    type Opened = OnceLock<Result<Arc<Gpu>, GpuError>>;
    static HARDWARE: Opened = OnceLock::new();
    static ANY: Opened = OnceLock::new();
    let cell = if allow_software { &ANY } else { &HARDWARE };
    cell.get_or_init(|| Gpu::open(allow_software).map(Arc::new))
        .clone()
}

/// How much an adapter is preferred: discrete over integrated over virtual over the
/// rest; software adapters last, and only when allowed.
#[cfg(feature = "gpu")]
fn rank(info: &wgpu::AdapterInfo, allow_software: bool) -> Option<u8> {
    match info.device_type {
        wgpu::DeviceType::DiscreteGpu => Some(4),
        wgpu::DeviceType::IntegratedGpu => Some(3),
        wgpu::DeviceType::VirtualGpu => Some(2),
        wgpu::DeviceType::Other => Some(1),
        wgpu::DeviceType::Cpu => allow_software.then_some(0),
    }
}

#[cfg(feature = "gpu")]
impl Gpu {
    /// Opens the most preferred adapter (discrete over integrated over virtual; software
    /// ones only when `allow_software`) with every limit it offers.
    pub fn open(allow_software: bool) -> Result<Gpu, GpuError> {
        Gpu::open_limited(allow_software, |l| l)
    }

    /// [`Gpu::open`] with the device's limits `limit` makes of the adapter's (tests
    /// open one with small limits, to reach what a large capture reaches on a real
    /// device).
    #[doc(hidden)]
    pub fn open_limited(
        allow_software: bool,
        limit: impl FnOnce(wgpu::Limits) -> wgpu::Limits,
    ) -> Result<Gpu, GpuError> {
        let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
        let adapters = pollster::block_on(
            instance
                .enumerate_adapters(wgpu::Backends::VULKAN | wgpu::Backends::METAL | wgpu::Backends::DX12),
        );
        let seen: Vec<String> = adapters
            .iter()
            .map(|a| {
                let i = a.get_info();
                format!("{} ({:?}, {:?})", i.name, i.backend, i.device_type)
            })
            .collect();
        let best = adapters
            .into_iter()
            .filter_map(|a| rank(&a.get_info(), allow_software).map(|r| (r, a)))
            .max_by_key(|(r, _)| *r)
            .map(|(_, a)| a);
        let Some(adapter) = best else {
            return Err(GpuError::NoAdapter {
                found: if seen.is_empty() {
                    "no Vulkan, Metal or DX12 adapter".into()
                } else {
                    format!("only software adapters: {}", seen.join(", "))
                },
            });
        };
        let info = adapter.get_info();
        let limits = limit(adapter.limits());
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("periscope-recon"),
            required_limits: limits.clone(),
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device {
            adapter: info.name.clone(),
            reason: e.to_string(),
        })?;
        // wgpu's default for an error outside an error scope is a panic; every call
        // here runs in one (`scoped`), so anything else is logged, never an abort.
        device.on_uncaptured_error(std::sync::Arc::new(|e| {
            tracing::error!(error = %e, "GPU error outside a reconstruction step");
        }));
        let gpu = Gpu {
            device,
            queue,
            info,
            limits,
            render: OnceLock::new(),
            reduce: OnceLock::new(),
            residual: OnceLock::new(),
            backward: OnceLock::new(),
            update: OnceLock::new(),
            backproject: OnceLock::new(),
        };
        if gpu.info.device_type == wgpu::DeviceType::Cpu {
            tracing::warn!(adapter = %gpu.device_info(), "the GPU path runs on a software adapter: correct, but slower than the CPU path");
        } else {
            tracing::info!(adapter = %gpu.device_info(), "GPU opened for the reconstruction");
        }
        Ok(gpu)
    }

    /// What the outputs record of this GPU.
    pub fn device_info(&self) -> DeviceInfo {
        let i = &self.info;
        DeviceInfo {
            device: "gpu",
            adapter: Some(i.name.clone()),
            backend: Some(i.backend.to_string()),
            driver: Some(format!("{} {}", i.driver, i.driver_info).trim().to_owned()),
            software: i.device_type == wgpu::DeviceType::Cpu,
        }
    }

    /// The largest storage buffer one binding may hold, bytes (a multiple of 16).
    fn max_binding(&self) -> u64 {
        (self
            .limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
            / 16)
            * 16
    }

    /// A storage buffer holding `data`.
    fn upload<T: bytemuck::Pod>(&self, label: &str, data: &[T]) -> wgpu::Buffer {
        // A zero-length binding is invalid: an empty slice gets zeros enough for any element.
        let bytes: &[u8] = if data.is_empty() {
            &[0; 256]
        } else {
            bytemuck::cast_slice(data)
        };
        self.filled(
            label,
            bytes,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        )
    }

    /// A uniform buffer holding `value`.
    fn uniform<T: bytemuck::Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.filled(label, bytemuck::bytes_of(value), wgpu::BufferUsages::UNIFORM)
    }

    /// A buffer of `usage` holding `bytes` (padded with zeros to whole words), written
    /// through the queue. Not `create_buffer_init`: it maps the new buffer and panics
    /// where the buffer could not be made (out of memory, past the device's
    /// `max_buffer_size`, a lost device), where this leaves the error to the step's
    /// error scope ([`Gpu::scoped`]), which returns it, and `auto` goes on on the CPU.
    fn filled(&self, label: &str, bytes: &[u8], usage: wgpu::BufferUsages) -> wgpu::Buffer {
        let size = bytes.len().div_ceil(4) * 4;
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size as u64,
            usage: usage | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        if size == bytes.len() {
            self.queue.write_buffer(&buffer, 0, bytes);
        } else {
            let mut padded = bytes.to_vec();
            padded.resize(size, 0);
            self.queue.write_buffer(&buffer, 0, &padded);
        }
        buffer
    }

    /// A zeroed storage buffer of `len` f32 the shaders write (wgpu zeroes new buffers).
    fn output(&self, label: &str, len: usize) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: (len.max(4) * 4) as u64,
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    }

    /// Submits `encoder`, copies `len` f32 of `buffer` back and waits for them; errors
    /// the device raised meanwhile (out of memory, validation, a lost device) come back
    /// as [`GpuError::Run`].
    fn finish(
        &self,
        what: &'static str,
        mut encoder: wgpu::CommandEncoder,
        buffer: &wgpu::Buffer,
        len: usize,
    ) -> Result<Vec<f32>, GpuError> {
        let run = |reason: String| GpuError::Run {
            adapter: self.info.name.clone(),
            what,
            reason,
        };
        let size = (len * 4) as u64;
        let read = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: size.max(16),
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        if size > 0 {
            encoder.copy_buffer_to_buffer(buffer, 0, &read, 0, size);
        }
        self.queue.submit([encoder.finish()]);
        let slice = read.slice(..);
        let (tx, rx) = std::sync::mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| run(e.to_string()))?;
        rx.recv()
            .map_err(|e| run(e.to_string()))?
            .map_err(|e| run(e.to_string()))?;
        let view = slice.get_mapped_range().map_err(|e| run(e.to_string()))?;
        let out = bytemuck::cast_slice::<u8, f32>(&view)[..len].to_vec();
        drop(view);
        read.unmap();
        Ok(out)
    }

    /// Runs `f`, turning the device's validation and out-of-memory errors raised
    /// during it into [`GpuError::Run`].
    fn scoped<T>(&self, what: &'static str, f: impl FnOnce() -> Result<T, GpuError>) -> Result<T, GpuError> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let out = f();
        let errors = [
            pollster::block_on(validation.pop()),
            pollster::block_on(oom.pop()),
        ];
        if let Some(e) = errors.into_iter().flatten().next() {
            return Err(GpuError::Run {
                adapter: self.info.name.clone(),
                what,
                reason: e.to_string(),
            });
        }
        out
    }

    /// Records one dispatch of `pipeline` over `groups` workgroups into `encoder`, with
    /// `buffers` bound to its group 0 in order (binding 0, 1, …).
    fn dispatch(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        pipeline: &wgpu::ComputePipeline,
        buffers: &[&wgpu::Buffer],
        groups: [u32; 3],
    ) {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
            .iter()
            .enumerate()
            .map(|(i, b)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: b.as_entire_binding(),
            })
            .collect();
        let group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        });
        let mut pass = encoder.begin_compute_pass(&Default::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, &group, &[]);
        pass.dispatch_workgroups(groups[0], groups[1], groups[2]);
    }

    /// A compute pipeline from WGSL `source`, entry point `main`.
    fn pipeline(&self, label: &str, source: &str) -> wgpu::ComputePipeline {
        let module = self.device.create_shader_module(wgpu::ShaderModuleDescriptor {
            label: Some(label),
            source: wgpu::ShaderSource::Wgsl(source.into()),
        });
        self.device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: None,
                module: &module,
                entry_point: Some("main"),
                compilation_options: Default::default(),
                cache: None,
            })
    }
}

/// For tests, here and in the crates that use this one.
#[doc(hidden)]
pub mod testing {
    use super::*;

    /// The GPU the tests run on (any adapter, lavapipe included), or `None` with a
    /// line saying the test skipped. `PERISCOPE_REQUIRE_GPU` makes a missing adapter a
    /// failure instead (CI sets it after installing lavapipe).
    pub fn gpu(test: &str) -> Option<Arc<Gpu>> {
        match shared(true) {
            Ok(g) => Some(g),
            Err(e) if std::env::var_os("PERISCOPE_REQUIRE_GPU").is_none() => {
                // Not `eprintln!`: libtest hides that from a test that passes.
                use std::io::Write;
                let _ = writeln!(std::io::stderr(), "SKIPPED {test}: {e}");
                None
            }
            Err(e) => panic!("{test}: PERISCOPE_REQUIRE_GPU is set but {e}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A buffer the device cannot make (here past a `max_buffer_size` set small, as a
    /// large capture's is on a real device, or out of its memory) is the step's error,
    /// which `auto` answers by going on on the CPU, not a panic: until 2026-12-07 the
    /// uploads went through `create_buffer_init`, which maps the new buffer and panics
    /// where it could not be made.
    #[test]
    fn a_buffer_past_the_devices_limit_is_the_steps_error_not_a_panic() {
        let small = |l: wgpu::Limits| wgpu::Limits {
            max_buffer_size: 1 << 12,
            max_storage_buffer_binding_size: 1 << 12,
            ..l
        };
        let gpu = match Gpu::open_limited(true, small) {
            Ok(g) => g,
            Err(e) if std::env::var_os("PERISCOPE_REQUIRE_GPU").is_none() => {
                use std::io::Write;
                let _ = writeln!(
                    std::io::stderr(),
                    "SKIPPED a_buffer_past_the_devices_limit_is_the_steps_error_not_a_panic: {e}"
                );
                return;
            }
            Err(e) => panic!("PERISCOPE_REQUIRE_GPU is set but {e}"),
        };
        let past = gpu.scoped("an upload past the limit", || {
            let _b = gpu.upload("big", &vec![1.0f32; 2048]);
            Ok(())
        });
        assert!(matches!(past, Err(GpuError::Run { .. })), "{past:?}");
        let within = gpu.scoped("an upload within it", || {
            let _b = gpu.upload("small", &[1.0f32; 16]);
            let _u = gpu.uniform("one", &[1u32, 2, 3]);
            Ok(())
        });
        assert!(within.is_ok(), "{within:?}");
    }
}

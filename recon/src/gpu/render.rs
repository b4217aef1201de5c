//! The forward render on the GPU (`render.wgsl`): [`crate::gtr::render_pairs`]'s
//! transients, in f32.
use super::{Gpu, GpuError, MAX_GROUPS};
use crate::gtr::{Kernel, RenderOptions, SIGMA_FLOOR_BINS};
use crate::transient::{Pair, TimeAxis};

/// Threads of a workgroup, and primitives per shared-memory tile.
pub(super) const TILE: usize = 256;
/// Bins each thread keeps in registers: a dispatch renders at most `TILE × PER_THREAD`
/// bins of each transient, longer ones take several.
const PER_THREAD: usize = 16;

/// The WGSL every kernel of the forward model starts with (`common.wgsl`).
pub(super) fn source(kernel: &str) -> String {
    [include_str!("common.wgsl"), kernel].concat()
}

/// The forward model's constants as `common.wgsl` reads them.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(super) struct Model {
    start: f32,
    width: f32,
    bins: u32,
    flags: u32,
    gain: f32,
    sys2: f32,
    floor2: f32,
    reach: f32,
    min_distance: f32,
    pad: [f32; 3],
}

impl Model {
    pub(super) fn new(axis: &TimeAxis, opt: &RenderOptions) -> Self {
        let floor = SIGMA_FLOOR_BINS * axis.width;
        Model {
            start: axis.start as f32,
            width: axis.width as f32,
            bins: axis.bins as u32,
            flags: u32::from(opt.use_ni) | (u32::from(opt.use_nd) << 1),
            gain: opt.gain as f32,
            sys2: (opt.sigma_sys * opt.sigma_sys) as f32,
            floor2: (floor * floor) as f32,
            reach: opt.window_sigmas as f32,
            min_distance: opt.min_distance as f32,
            pad: [0.0; 3],
        }
    }

    /// Bins a transient has.
    pub(super) fn bins(&self) -> u32 {
        self.bins
    }
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct Params {
    model: Model,
    prims: u32,
    first_pair: u32,
    bin_offset: u32,
    block_bins: u32,
    group_prims: u32,
    pairs: u32,
    pad: [u32; 2],
}

#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
struct ReduceParams {
    len: u32,
    groups: u32,
    pad: [u32; 2],
}

/// A primitive as the shaders read it: centre and albedo, the three local axes each
/// with its scale, and the scales' pairwise products.
pub(super) fn prim(k: &Kernel) -> [[f32; 4]; 5] {
    let c = |i: usize, s: f64| {
        let a = k.r.col(i);
        [a.x as f32, a.y as f32, a.z as f32, s as f32]
    };
    [
        [k.x.x as f32, k.x.y as f32, k.x.z as f32, k.rho as f32],
        c(0, k.s.x),
        c(1, k.s.y),
        c(2, k.s.z),
        [k.pi.x as f32, k.pi.y as f32, k.pi.z as f32, 0.0],
    ]
}

/// A pair as the shaders read it.
pub(super) fn pair(p: &Pair) -> [[f32; 4]; 4] {
    let v = |v: glam::DVec3| [v.x as f32, v.y as f32, v.z as f32, 0.0];
    [v(p.xi), v(p.ni), v(p.xd), v(p.nd)]
}

/// Where a forward render reads and writes: the primitives, the pairs, and the
/// target of `groups × pairs × bins` values (each group of primitives' partial
/// transients, summed into the first `pairs × bins` by [`Render::record`]).
pub(super) struct Render<'a> {
    pub prims: &'a wgpu::Buffer,
    pub count: usize,
    pub pairs: &'a wgpu::Buffer,
    pub target: &'a wgpu::Buffer,
    pub model: Model,
}

impl Render<'_> {
    /// Records the render of `n` pairs from `first` with the primitives split into
    /// `groups` workgroups each (1 for a render over many pairs; more when the pairs are
    /// too few to fill the GPU), and the sum of the groups' partials.
    pub(super) fn record(
        &self,
        gpu: &Gpu,
        encoder: &mut wgpu::CommandEncoder,
        first: usize,
        n: usize,
        groups: usize,
    ) {
        let pipeline = gpu
            .render
            .get_or_init(|| gpu.pipeline("render", &source(include_str!("render.wgsl"))));
        let bins = self.model.bins as usize;
        let tiles = self.count.div_ceil(TILE).max(1);
        let group_prims = tiles.div_ceil(groups) * TILE;
        let groups = tiles.div_ceil(group_prims / TILE);
        for offset in (0..bins).step_by(TILE * PER_THREAD) {
            let params = Params {
                model: self.model,
                prims: self.count as u32,
                first_pair: first as u32,
                bin_offset: offset as u32,
                block_bins: (TILE * PER_THREAD) as u32,
                group_prims: group_prims as u32,
                pairs: n as u32,
                pad: [0; 2],
            };
            let uniform = gpu.uniform("render parameters", &params);
            gpu.dispatch(
                encoder,
                pipeline,
                &[&uniform, self.prims, self.pairs, self.target],
                [n as u32, groups as u32, 1],
            );
        }
        if groups > 1 {
            let reduce = gpu
                .reduce
                .get_or_init(|| gpu.pipeline("reduce", include_str!("reduce.wgsl")));
            let len = n * bins;
            let params = ReduceParams {
                len: len as u32,
                groups: groups as u32,
                pad: [0; 2],
            };
            let uniform = gpu.uniform("reduce parameters", &params);
            gpu.dispatch(
                encoder,
                reduce,
                &[&uniform, self.target],
                spread(len.div_ceil(256)),
            );
        }
    }
}

/// `n` workgroups as a grid the dispatch limits allow: `[x, y, 1]` with `x·y ≥ n`
/// (the shaders number them `x + y·width`, and skip the ones past the end).
pub(super) fn spread(n: usize) -> [u32; 3] {
    let x = n.clamp(1, MAX_GROUPS);
    [x as u32, n.div_ceil(x).max(1) as u32, 1]
}

/// Renders `pairs` from `kernels` on `gpu`: `axis.bins` f32 a pair, pair by pair, the
/// values [`crate::gtr::render_pairs`] computes in f64 (to the f32 tolerance its tests
/// state).
pub fn render_pairs(
    gpu: &Gpu,
    kernels: &[Kernel],
    pairs: &[Pair],
    axis: &TimeAxis,
    opt: &RenderOptions,
) -> Result<Vec<f32>, GpuError> {
    let bins = axis.bins;
    if pairs.is_empty() || bins == 0 {
        return Ok(vec![0.0; pairs.len() * bins]);
    }
    gpu.scoped("rendering transients", || {
        let prims: Vec<[[f32; 4]; 5]> = kernels.iter().map(prim).collect();
        let geometry: Vec<[[f32; 4]; 4]> = pairs.iter().map(pair).collect();
        let prims = gpu.upload("primitives", &prims);
        let geometry = gpu.upload("pairs", &geometry);
        // Pairs in chunks whose transients fit one binding and one dispatch.
        let per_chunk = ((gpu.max_binding() / (4 * bins as u64)) as usize).clamp(1, MAX_GROUPS);
        let mut out = Vec::with_capacity(pairs.len() * bins);
        for first in (0..pairs.len()).step_by(per_chunk) {
            let n = per_chunk.min(pairs.len() - first);
            let target = gpu.output("transients", n * bins);
            let mut encoder = gpu.device.create_command_encoder(&Default::default());
            Render {
                prims: &prims,
                count: kernels.len(),
                pairs: &geometry,
                target: &target,
                model: Model::new(axis, opt),
            }
            .record(gpu, &mut encoder, first, n, 1);
            out.extend(gpu.finish("rendering transients", encoder, &target, n * bins)?);
        }
        Ok(out)
    })
}

#[cfg(test)]
mod tests {
    use glam::{DMat3, DVec3};
    use rand::{Rng, SeedableRng};

    use super::*;
    use crate::gpu::testing;

    fn kernels(n: usize, seed: u64) -> Vec<Kernel> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        (0..n)
            .map(|_| {
                let x = DVec3::new(
                    rng.random_range(-0.3..0.3),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(0.4..1.0),
                );
                let r = DMat3::from_quat(glam::DQuat::from_euler(
                    glam::EulerRot::XYZ,
                    rng.random_range(0.0..6.0),
                    rng.random_range(0.0..6.0),
                    rng.random_range(0.0..6.0),
                ));
                let s = DVec3::new(
                    rng.random_range(0.002..0.05),
                    rng.random_range(0.002..0.05),
                    rng.random_range(0.0005..0.01),
                );
                Kernel::new(x, r, s, rng.random_range(0.1..1.0))
            })
            .collect()
    }

    fn pairs(n: usize, seed: u64) -> Vec<Pair> {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        let z = DVec3::Z;
        (0..n)
            .map(|_| {
                let mut p = || DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
                Pair {
                    xi: p(),
                    ni: z,
                    xd: p(),
                    nd: z,
                }
            })
            .collect()
    }

    /// Relative L2 error of `got` against `want`, and the largest error over the peak.
    fn errors(got: &[f32], want: &[f64]) -> (f64, f64) {
        let (mut num, mut den, mut worst, mut peak) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for (&g, &w) in got.iter().zip(want) {
            let d = g as f64 - w;
            num += d * d;
            den += w * w;
            worst = worst.max(d.abs());
            peak = peak.max(w.abs());
        }
        ((num / den).sqrt(), worst / peak)
    }

    /// The GPU render agrees with the CPU's (f64) within 1e-4 relative L2 and 2e-4 of
    /// the peak anywhere, over random primitives (thin and round, every orientation)
    /// seen from random non-confocal pairs, with more bins than one dispatch block
    /// holds and a jitter, and with the cosines switched off.
    #[test]
    fn the_gpu_renders_what_the_cpu_renders() {
        let Some(gpu) = testing::gpu("the_gpu_renders_what_the_cpu_renders") else {
            return;
        };
        let kernels = kernels(300, 1);
        let pairs = pairs(24, 2);
        for (bins, opt) in [
            (512, RenderOptions::default()),
            (
                4096 + 300,
                RenderOptions {
                    sigma_sys: 0.004,
                    use_ni: false,
                    gain: 3.0,
                    ..RenderOptions::default()
                },
            ),
        ] {
            let axis = TimeAxis {
                start: 0.3,
                width: 2.6 / bins as f64,
                bins,
            };
            let mut want = vec![0.0; pairs.len() * bins];
            crate::gtr::render_pairs(&kernels, &pairs, &axis, &opt, &mut want);
            let got = render_pairs(&gpu, &kernels, &pairs, &axis, &opt).unwrap();
            assert_eq!(got.len(), want.len());
            let (l2, worst) = errors(&got, &want);
            eprintln!("bins {bins}: relative L2 {l2:.2e}, worst {worst:.2e} of the peak");
            assert!(want.iter().any(|&v| v > 0.0), "the scene is seen");
            assert!(
                l2 < 1e-4 && worst < 2e-4,
                "bins {bins}: L2 {l2:e}, worst {worst:e}"
            );
        }
    }

    /// Nothing to render renders zeros; primitives behind the relay render nothing.
    #[test]
    fn the_gpu_renders_nothing_from_nothing() {
        let Some(gpu) = testing::gpu("the_gpu_renders_nothing_from_nothing") else {
            return;
        };
        let axis = TimeAxis {
            start: 0.0,
            width: 0.01,
            bins: 64,
        };
        let pairs = pairs(3, 3);
        let opt = RenderOptions::default();
        assert_eq!(
            render_pairs(&gpu, &[], &pairs, &axis, &opt).unwrap(),
            vec![0.0; 3 * 64]
        );
        let behind: Vec<Kernel> = kernels(5, 4)
            .into_iter()
            .map(|mut k| {
                k.x.z = -k.x.z;
                k
            })
            .collect();
        assert_eq!(
            render_pairs(&gpu, &behind, &pairs, &axis, &opt).unwrap(),
            vec![0.0; 3 * 64]
        );
        assert!(render_pairs(&gpu, &behind, &[], &axis, &opt).unwrap().is_empty());
    }
}

// The fit's analytic backward pass (recon/src/gtr/kernel.rs, `Evaluation::backward`)
// in f32, after common.wgsl: one thread per primitive, every pair of the mini-batch in
// order, so each primitive's gradient is summed by one thread, with no float atomics
// and in a fixed order. Writes ∂L/∂x, ∂L/∂R (column by column), ∂L/∂s and ∂L/∂ρ, 16
// values a primitive.
struct Params {
    model: Model,
    prims: u32,
    pairs: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> prims: array<Prim>;
@group(0) @binding(2) var<storage, read> pairs: array<PairG>;
@group(0) @binding(3) var<storage, read> dl: array<f32>;
@group(0) @binding(4) var<storage, read_write> result: array<f32>;

const INV_SQRT_2PI: f32 = 0.39894228;

fn pdf(z: f32) -> f32 {
    return INV_SQRT_2PI * exp(-0.5 * z * z);
}

// ∂A⊥/∂s over A⊥'s own factor: the projected area's slope in each scale.
fn area_ds(w: vec3<f32>, a: f32, pi: vec3<f32>, s: vec3<f32>) -> vec3<f32> {
    let q = w * w * pi;
    return vec3<f32>(q.y * s.z + q.z * s.y, q.x * s.z + q.z * s.x, q.x * s.y + q.y * s.x) / a;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) n: vec3<u32>) {
    let k = id.x + id.y * n.x * 64u;
    if (k >= p.prims) {
        return;
    }
    let g = prims[k];
    let rho = g.x.w;
    let pi = g.pi.xyz;
    let s = vec3<f32>(g.c0.w, g.c1.w, g.c2.w);
    let bins = p.model.bins;
    var gx = vec3<f32>(0.0);
    var gr0 = vec3<f32>(0.0);
    var gr1 = vec3<f32>(0.0);
    var gr2 = vec3<f32>(0.0);
    var gs = vec3<f32>(0.0);
    var grho = 0.0;
    for (var j = 0u; j < p.pairs; j++) {
        let q = pairs[j];
        let e = geometry(g, q, p.model);
        if (!e.seen) {
            continue;
        }
        // Σ dl ΔΦ, Σ dl Δφ and Σ dl Δ(zφ) over the window's bins.
        let inv = 1.0 / e.sigma;
        let dz = p.model.width * inv;
        var z0 = (f32(e.lo) - e.mu) * dz;
        var p0 = pdf(z0);
        var s_cdf = 0.0;
        var s_pdf = 0.0;
        var s_zpdf = 0.0;
        for (var b = e.lo; b < e.hi; b++) {
            let z1 = (f32(b + 1u) - e.mu) * dz;
            let p1 = pdf(z1);
            let r = dl[j * bins + b];
            s_cdf += r * bin_mass(z0, z1);
            s_pdf += r * (p1 - p0);
            s_zpdf += r * (z1 * p1 - z0 * p0);
            z0 = z1;
            p0 = p1;
        }
        let amp = e.amp;
        let g_amp = s_cdf;
        let g_mu = -amp * s_pdf * inv;
        let g_sigma = -amp * s_zpdf * inv;

        // Albedo and the relay cosines.
        grho += g_amp * e.base * e.gi * e.gd;
        var g_gi = 0.0;
        if ((p.model.flags & 1u) != 0u) {
            g_gi = g_amp * e.base * rho * e.gd;
        }
        var g_gd = 0.0;
        if ((p.model.flags & 2u) != 0u) {
            g_gd = g_amp * e.base * rho * e.gi;
        }

        // Projected areas and the spread, in the local frame.
        let pi2 = pi * pi;
        let g_wi = (g_amp * amp / (e.ai * e.ai)) * (e.wi * pi2);
        let g_wd = (g_amp * amp / (e.ad * e.ad)) * (e.wd * pi2);
        let wv = e.wi + e.wd;
        let g_wv = (g_sigma * inv) * (s * s * wv);

        // Scales.
        gs += (g_amp * amp / e.ai) * area_ds(e.wi, e.ai, pi, s)
            + (g_amp * amp / e.ad) * area_ds(e.wd, e.ad, pi, s)
            + (g_sigma * inv) * (s * wv * wv);

        // Rotation: w = Rᵀu, so column j of ∂L/∂R is Σ u ∂L/∂w_j.
        let v = e.ui + e.ud;
        gr0 += e.ui * g_wi.x + e.ud * g_wd.x + v * g_wv.x;
        gr1 += e.ui * g_wi.y + e.ud * g_wd.y + v * g_wv.y;
        gr2 += e.ui * g_wi.z + e.ud * g_wd.z + v * g_wv.z;

        // Centre, through the distances and the unit directions.
        let rg_v = g.c0.xyz * g_wv.x + g.c1.xyz * g_wv.y + g.c2.xyz * g_wv.z;
        let g_ui = g.c0.xyz * g_wi.x + g.c1.xyz * g_wi.y + g.c2.xyz * g_wi.z + rg_v + g_gi * q.ni.xyz;
        let g_ud = g.c0.xyz * g_wd.x + g.c1.xyz * g_wd.y + g.c2.xyz * g_wd.z + rg_v + g_gd * q.nd.xyz;
        let g_di = -2.0 * g_amp * amp / e.di + g_mu;
        let g_dd = -2.0 * g_amp * amp / e.dd + g_mu;
        gx += g_di * e.ui + (g_ui - dot(e.ui, g_ui) * e.ui) / e.di;
        gx += g_dd * e.ud + (g_ud - dot(e.ud, g_ud) * e.ud) / e.dd;
    }
    let o = k * 16u;
    result[o + 0u] = gx.x;
    result[o + 1u] = gx.y;
    result[o + 2u] = gx.z;
    result[o + 3u] = gr0.x;
    result[o + 4u] = gr0.y;
    result[o + 5u] = gr0.z;
    result[o + 6u] = gr1.x;
    result[o + 7u] = gr1.y;
    result[o + 8u] = gr1.z;
    result[o + 9u] = gr2.x;
    result[o + 10u] = gr2.y;
    result[o + 11u] = gr2.z;
    result[o + 12u] = gs.x;
    result[o + 13u] = gs.y;
    result[o + 14u] = gs.z;
    result[o + 15u] = grho;
}

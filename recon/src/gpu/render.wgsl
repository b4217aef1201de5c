// The 3D-GTR forward render (recon/src/gtr/kernel.rs, `evaluate` and
// `Window::accumulate`) in f32: one workgroup per pair, the primitives in tiles of 256
// whose pulses the workgroup's threads compute into shared memory, then every thread
// adds the tile's pulses to the bins it owns. Bins are gathered, never scattered, so
// no float atomics are needed and the sum is deterministic.
struct Params {
    start: f32,
    width: f32,
    bins: u32,
    prims: u32,
    first_pair: u32,
    bin_offset: u32,
    block_bins: u32,
    flags: u32,
    gain: f32,
    sys2: f32,
    floor2: f32,
    reach: f32,
    min_distance: f32,
    pad0: f32,
    pad1: f32,
    pad2: f32,
}

struct Prim {
    x: vec4<f32>,
    c0: vec4<f32>,
    c1: vec4<f32>,
    c2: vec4<f32>,
    pi: vec4<f32>,
}

struct PairG {
    xi: vec4<f32>,
    ni: vec4<f32>,
    xd: vec4<f32>,
    nd: vec4<f32>,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> prims: array<Prim>;
@group(0) @binding(2) var<storage, read> pairs: array<PairG>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

const TILE: u32 = 256u;
const PER_THREAD: u32 = 16u;

var<workgroup> w_amp: array<f32, 256>;
var<workgroup> w_mu: array<f32, 256>;
var<workgroup> w_dz: array<f32, 256>;
var<workgroup> w_lo: array<u32, 256>;
var<workgroup> w_hi: array<u32, 256>;

// Q(z) = 1 − Φ(z) = erfc(z/√2)/2, with Numerical Recipes' erfc (fractional error
// under 1.2e-7), accurate in the upper tail.
fn upper_tail(z: f32) -> f32 {
    let x = abs(z) * 0.70710678;
    let t = 1.0 / (1.0 + 0.5 * x);
    let poly = -1.26551223 + t * (1.00002368 + t * (0.37409196 + t * (0.09678418 + t * (-0.18628806
        + t * (0.27886807 + t * (-1.13520398 + t * (1.48851587 + t * (-0.82215223 + t * 0.17087277))))))));
    let q = 0.5 * t * exp(-x * x + poly);
    return select(1.0 - q, q, z >= 0.0);
}

// Φ(z1) − Φ(z0) for z0 < z1, from whichever tail keeps its precision.
fn bin_mass(z0: f32, z1: f32) -> f32 {
    if (z0 >= 0.0) {
        return upper_tail(z0) - upper_tail(z1);
    }
    if (z1 <= 0.0) {
        return upper_tail(-z1) - upper_tail(-z0);
    }
    return 1.0 - upper_tail(z1) - upper_tail(-z0);
}

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let q = pairs[p.first_pair + wg.x];
    var acc: array<f32, 16>;
    for (var j = 0u; j < PER_THREAD; j++) {
        acc[j] = 0.0;
    }
    let block_end = min(p.bin_offset + p.block_bins, p.bins);
    for (var base = 0u; base < p.prims; base += TILE) {
        let k = base + t;
        var amp = 0.0;
        var mu = 0.0;
        var dz = 1.0;
        var lo = 0u;
        var hi = 0u;
        if (k < p.prims) {
            let g = prims[k];
            let to_i = g.x.xyz - q.xi.xyz;
            let to_d = g.x.xyz - q.xd.xyz;
            let di = length(to_i);
            let dd = length(to_d);
            if (di >= p.min_distance && dd >= p.min_distance) {
                let ui = to_i / di;
                let ud = to_d / dd;
                var gi = 1.0;
                if ((p.flags & 1u) != 0u) {
                    gi = dot(q.ni.xyz, ui);
                }
                var gd = 1.0;
                if ((p.flags & 2u) != 0u) {
                    gd = dot(q.nd.xyz, ud);
                }
                if (gi > 0.0 && gd > 0.0) {
                    let wi = vec3<f32>(dot(g.c0.xyz, ui), dot(g.c1.xyz, ui), dot(g.c2.xyz, ui));
                    let wd = vec3<f32>(dot(g.c0.xyz, ud), dot(g.c1.xyz, ud), dot(g.c2.xyz, ud));
                    let sv = vec3<f32>(g.c0.w, g.c1.w, g.c2.w) * (wi + wd);
                    let ai = length(g.pi.xyz * wi);
                    let ad = length(g.pi.xyz * wd);
                    let sigma = sqrt(dot(sv, sv) + p.sys2 + p.floor2);
                    let path = di + dd;
                    let r = p.reach * sigma;
                    let first = max(floor((path - r - p.start) / p.width), 0.0);
                    let last = min(ceil((path + r - p.start) / p.width), f32(p.bins));
                    if (first < last) {
                        amp = p.gain * ai * ad / (di * di * dd * dd) * g.x.w * gi * gd;
                        mu = (path - p.start) / p.width;
                        dz = p.width / sigma;
                        lo = u32(first);
                        hi = u32(last);
                    }
                }
            }
        }
        w_amp[t] = amp;
        w_mu[t] = mu;
        w_dz[t] = dz;
        w_lo[t] = lo;
        w_hi[t] = hi;
        workgroupBarrier();
        for (var j = 0u; j < PER_THREAD; j++) {
            let b = p.bin_offset + t + j * TILE;
            if (b >= block_end) {
                break;
            }
            var s = 0.0;
            for (var i = 0u; i < TILE; i++) {
                if (b >= w_lo[i] && b < w_hi[i]) {
                    let z0 = (f32(b) - w_mu[i]) * w_dz[i];
                    s += w_amp[i] * bin_mass(z0, z0 + w_dz[i]);
                }
            }
            acc[j] += s;
        }
        workgroupBarrier();
    }
    for (var j = 0u; j < PER_THREAD; j++) {
        let b = p.bin_offset + t + j * TILE;
        if (b >= block_end) {
            break;
        }
        out[wg.x * p.bins + b] = acc[j];
    }
}

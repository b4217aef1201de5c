// The 3D-GTR forward render (recon/src/gtr/kernel.rs, `evaluate` and
// `Window::accumulate`) in f32, after common.wgsl: workgroup (x, y) renders pair x
// from group y of the primitives, in tiles of 256 whose pulses the workgroup's threads
// compute into shared memory, then every thread adds the tile's pulses to the bins it
// owns. Bins are gathered, never scattered, so no float atomics are needed and the sum
// is deterministic. With several groups each writes its own partial transients, which
// reduce.wgsl sums in a fixed order.
struct Params {
    model: Model,
    prims: u32,
    first_pair: u32,
    bin_offset: u32,
    block_bins: u32,
    // Primitives of each group (a multiple of the tile), and the pairs of the dispatch
    // (the stride between groups' partial transients).
    group_prims: u32,
    pairs: u32,
    pad0: u32,
    pad1: u32,
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

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let q = pairs[p.first_pair + wg.x];
    let bins = p.model.bins;
    var acc: array<f32, 16>;
    for (var j = 0u; j < PER_THREAD; j++) {
        acc[j] = 0.0;
    }
    let block_end = min(p.bin_offset + p.block_bins, bins);
    let first = wg.y * p.group_prims;
    let end = min(first + p.group_prims, p.prims);
    for (var base = first; base < end; base += TILE) {
        let k = base + t;
        var amp = 0.0;
        var mu = 0.0;
        var dz = 1.0;
        var lo = 0u;
        var hi = 0u;
        if (k < end) {
            let e = geometry(prims[k], q, p.model);
            if (e.seen) {
                amp = e.amp;
                mu = e.mu;
                dz = p.model.width / e.sigma;
                lo = e.lo;
                hi = e.hi;
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
        out[(wg.y * p.pairs + wg.x) * bins + b] = acc[j];
    }
}

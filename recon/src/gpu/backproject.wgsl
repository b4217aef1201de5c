// Backprojection (recon/src/solver/fbp, `backproject_pairs`) in f32: one thread per
// voxel of a slab of z slices, every pair of a chunk in order, each voxel's path length,
// falloff gain and linearly interpolated bin, for one or two channels. The slab
// accumulates over the chunks of pairs, one dispatch each.
struct Params {
    nx: u32,
    ny: u32,
    channels: u32,
    pairs: u32,
    min_x: f32,
    min_y: f32,
    min_z: f32,
    inv_w: f32,
    vx: f32,
    vy: f32,
    vz: f32,
    offset: f32,
    top: f32,
    falloff: f32,
    stride: u32,
    z0: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
// Illumination and detection point of each pair, xyz of two vec4s.
@group(0) @binding(1) var<storage, read> points: array<vec4<f32>>;
// Padded histograms: `stride` bins of `channels` values a pair.
@group(0) @binding(2) var<storage, read> hist: array<f32>;
@group(0) @binding(3) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
    let plane = p.nx * p.ny;
    if (id.x >= plane) {
        return;
    }
    let ix = id.x % p.nx;
    let iy = id.x / p.nx;
    let v = vec3<f32>(
        p.min_x + (f32(ix) + 0.5) * p.vx,
        p.min_y + (f32(iy) + 0.5) * p.vy,
        p.min_z + (f32(p.z0 + id.y) + 0.5) * p.vz,
    );
    let c = p.channels;
    var a0 = 0.0;
    var a1 = 0.0;
    for (var q = 0u; q < p.pairs; q++) {
        let di = v - points[2u * q].xyz;
        let dd = v - points[2u * q + 1u].xyz;
        let ri = sqrt(dot(di, di));
        let rd = sqrt(dot(dd, dd));
        let path = ri + rd;
        let f = clamp(path * p.inv_w - p.offset, 0.0, p.top);
        // 0, not NaN, for a voxel on a confocal relay point.
        var g = (4.0 * ri * rd) / max(path * path, 1.17549435e-38);
        if (p.falloff == 0.0) {
            g = 1.0;
        } else if (p.falloff == 2.0) {
            g = g * g;
        } else if (p.falloff != 1.0) {
            g = select(0.0, pow(g, p.falloff), g > 0.0);
        }
        let below = floor(f);
        let upper = g * (f - below);
        let w0 = g - upper;
        let at = (q * p.stride + u32(below)) * c;
        a0 += w0 * hist[at] + upper * hist[at + c];
        if (c == 2u) {
            a1 += w0 * hist[at + 1u] + upper * hist[at + c + 1u];
        }
    }
    let o = (id.y * plane + id.x) * c;
    out[o] += a0;
    if (c == 2u) {
        out[o + 1u] += a1;
    }
}

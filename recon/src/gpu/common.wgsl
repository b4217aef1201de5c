// What the GPU kernels share (prepended to each shader's source): the primitive and
// pair layouts, the forward model's constants, a primitive's geometry against a pair
// (recon/src/gtr/kernel.rs, `evaluate`), and the normal distribution's tail.

// A primitive: centre and albedo, the local axes (columns of R) each with its scale,
// and the products of the other two scales.
struct Prim {
    x: vec4<f32>,
    c0: vec4<f32>,
    c1: vec4<f32>,
    c2: vec4<f32>,
    pi: vec4<f32>,
}

// A pair: illumination point and normal, detection point and normal.
struct PairG {
    xi: vec4<f32>,
    ni: vec4<f32>,
    xd: vec4<f32>,
    nd: vec4<f32>,
}

// The forward model's constants (`RenderOptions` and the time axis).
struct Model {
    start: f32,
    width: f32,
    bins: u32,
    // Bit 0: the illumination cosine; bit 1: the detection cosine.
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

// One primitive against one pair: what the forward value and its gradient share.
struct Geo {
    seen: bool,
    di: f32,
    dd: f32,
    ui: vec3<f32>,
    ud: vec3<f32>,
    wi: vec3<f32>,
    wd: vec3<f32>,
    gi: f32,
    gd: f32,
    ai: f32,
    ad: f32,
    // g A⊥i A⊥d / (di² dd²): the amplitude without ρ and the cosines.
    base: f32,
    amp: f32,
    sigma: f32,
    // The pulse's mean, in bins from the axis start, and its first and one-past-last bin.
    mu: f32,
    lo: u32,
    hi: u32,
}

fn geometry(g: Prim, q: PairG, m: Model) -> Geo {
    var e: Geo;
    e.seen = false;
    let to_i = g.x.xyz - q.xi.xyz;
    let to_d = g.x.xyz - q.xd.xyz;
    e.di = length(to_i);
    e.dd = length(to_d);
    if (e.di < m.min_distance || e.dd < m.min_distance) {
        return e;
    }
    e.ui = to_i / e.di;
    e.ud = to_d / e.dd;
    e.gi = 1.0;
    if ((m.flags & 1u) != 0u) {
        e.gi = dot(q.ni.xyz, e.ui);
    }
    e.gd = 1.0;
    if ((m.flags & 2u) != 0u) {
        e.gd = dot(q.nd.xyz, e.ud);
    }
    if (e.gi <= 0.0 || e.gd <= 0.0) {
        return e;
    }
    e.wi = vec3<f32>(dot(g.c0.xyz, e.ui), dot(g.c1.xyz, e.ui), dot(g.c2.xyz, e.ui));
    e.wd = vec3<f32>(dot(g.c0.xyz, e.ud), dot(g.c1.xyz, e.ud), dot(g.c2.xyz, e.ud));
    let sv = vec3<f32>(g.c0.w, g.c1.w, g.c2.w) * (e.wi + e.wd);
    e.ai = length(g.pi.xyz * e.wi);
    e.ad = length(g.pi.xyz * e.wd);
    e.sigma = sqrt(dot(sv, sv) + m.sys2 + m.floor2);
    let path = e.di + e.dd;
    let r = m.reach * e.sigma;
    let first = max(floor((path - r - m.start) / m.width), 0.0);
    let last = min(ceil((path + r - m.start) / m.width), f32(m.bins));
    if (!(first < last)) {
        return e;
    }
    e.base = m.gain * e.ai * e.ad / (e.di * e.di * e.dd * e.dd);
    e.amp = e.base * g.x.w * e.gi * e.gd;
    e.mu = (path - m.start) / m.width;
    e.lo = u32(first);
    e.hi = u32(last);
    e.seen = true;
    return e;
}

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

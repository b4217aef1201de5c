// The fit's optimiser step on the GPU, after common.wgsl: one thread per primitive.
// From the backward pass's 16 physical gradient values it takes the chain rule through
// the parameter maps (recon/src/gtr/model.rs, `chain_with`), the AdamW update of the
// eleven raw parameters with the rotations renormalised (recon/src/gtr/optim.rs,
// `AdamW::step_averaged`), the running mean of the iterates while averaging, and the
// primitive the next step renders (`kernel_and_slopes`), so the parameters stay on the
// GPU from step to step. Raw parameters, per primitive: θx (3), θs (3), the raw
// quaternion (w, x, y, z) and θρ.
struct Params {
    // The ROI's centre, and ln s_min in w.
    centre: vec4<f32>,
    // The ROI's half sizes, and ln s_max − ln s_min in w.
    half: vec4<f32>,
    // Each group's learning rate (schedule applied): centres, scales, rotations, albedo.
    lr: vec4<f32>,
    // Each group's decoupled weight decay.
    decay: vec4<f32>,
    beta1: f32,
    beta2: f32,
    // 1 − β1ᵗ and 1 − β2ᵗ.
    bias1: f32,
    bias2: f32,
    eps: f32,
    // 1/n for the running mean of the last n iterates; 0: no mean kept.
    mean_weight: f32,
    prims: u32,
    // The step's pairs, whose losses (after the gradients in `grads`) scale the
    // surface prior's gradient; 0: no prior.
    prior_pairs: u32,
    // The centre's coordinate the prior pulls (its depth axis): 0, 1 or 2.
    prior_axis: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> grads: array<f32>;
@group(0) @binding(2) var<storage, read_write> raw: array<f32>;
@group(0) @binding(3) var<storage, read_write> m1: array<f32>;
@group(0) @binding(4) var<storage, read_write> m2: array<f32>;
@group(0) @binding(5) var<storage, read_write> mean: array<f32>;
@group(0) @binding(6) var<storage, read_write> prims: array<Prim>;
// Entries whose gradient was not finite, skipped as the CPU's AdamW skips them.
@group(0) @binding(7) var<storage, read_write> skipped: array<atomic<u32>>;
// The surface prior's terms (recon/src/gtr/train.rs, `SurfacePrior::terms`), one a
// primitive: its column's mean depth z̄ and c, so that the step adds c · L · (z − z̄)
// to the gradient of its centre's coordinate z along `prior_axis`, L the step's loss.
@group(0) @binding(8) var<storage, read> prior: array<vec2<f32>>;

const RAW: u32 = 11u;

fn finite(x: f32) -> bool {
    return (bitcast<u32>(x) & 0x7f800000u) != 0x7f800000u;
}

// tanh, finite for every argument (|x| ≥ 10 is ±1 in f32).
fn tanh_f(x: f32) -> f32 {
    return tanh(clamp(x, -10.0, 10.0));
}

fn sigmoid(x: f32) -> f32 {
    return 1.0 / (1.0 + exp(-clamp(x, -80.0, 80.0)));
}

// ln(1 + eˣ) without losing a small eˣ to the rounding of 1 + eˣ.
fn softplus(x: f32) -> f32 {
    if (x > 30.0) {
        return x;
    }
    let e = exp(x);
    let u = 1.0 + e;
    if (u == 1.0) {
        return e;
    }
    return log(u) * e / (u - 1.0);
}

// The optimiser group of raw entry i: centres, scales, rotations, albedo.
fn group(i: u32) -> u32 {
    if (i < 3u) {
        return 0u;
    }
    if (i < 6u) {
        return 1u;
    }
    if (i < 10u) {
        return 2u;
    }
    return 3u;
}

@compute @workgroup_size(64)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) n: vec3<u32>) {
    let k = id.x + id.y * n.x * 64u;
    if (k >= p.prims) {
        return;
    }
    let o = k * RAW;
    let go = k * 16u;
    var th: array<f32, 11>;
    for (var i = 0u; i < RAW; i++) {
        th[i] = raw[o + i];
    }
    let lmin = p.centre.w;
    let lspan = p.half.w;

    // The physical gradient of the centre's coordinate along the prior's axis, with the
    // surface prior's where it is on and the step's loss is positive and finite
    // (`SurfacePrior::add_gradient`).
    let pa = min(p.prior_axis, 2u);
    var gz = grads[go + pa];
    if (p.prior_pairs > 0u) {
        var loss = 0.0;
        for (var b = 0u; b < p.prior_pairs; b++) {
            loss += grads[p.prims * 16u + b];
        }
        if (finite(loss) && loss > 0.0) {
            let z = p.centre[pa] + p.half[pa] * tanh_f(th[pa]);
            gz += prior[k].y * loss * (z - prior[k].x);
        }
    }

    // The raw gradient: the maps' slopes at the parameters this step rendered.
    var g: array<f32, 11>;
    for (var j = 0u; j < 3u; j++) {
        let t = tanh_f(th[j]);
        g[j] = select(grads[go + j], gz, j == pa) * (p.half[j] * (1.0 - t * t));
        let sg = sigmoid(th[3u + j]);
        let s = exp(lmin + lspan * sg);
        g[3u + j] = grads[go + 12u + j] * (s * lspan * sg * (1.0 - sg));
    }
    // The rotation: R(q) with q = r/‖r‖; G[m][j] (row m, column j) is ∂L/∂R.
    let r = vec4<f32>(th[6], th[7], th[8], th[9]);
    let norm = length(r);
    let q = r / norm;
    let w = q.x;
    let x = q.y;
    let y = q.z;
    let z = q.w;
    let g00 = grads[go + 3u];
    let g10 = grads[go + 4u];
    let g20 = grads[go + 5u];
    let g01 = grads[go + 6u];
    let g11 = grads[go + 7u];
    let g21 = grads[go + 8u];
    let g02 = grads[go + 9u];
    let g12 = grads[go + 10u];
    let g22 = grads[go + 11u];
    let dq = 2.0 * vec4<f32>(
        -z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21,
        y * g01 + z * g02 + y * g10 - 2.0 * x * g11 - w * g12 + z * g20 + w * g21 - 2.0 * x * g22,
        -2.0 * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - 2.0 * y * g22,
        -2.0 * z * g00 - w * g01 + x * g02 + w * g10 - 2.0 * z * g11 + y * g12 + x * g20 + y * g21,
    );
    let dr = (dq - q * dot(dq, q)) / norm;
    g[6] = dr.x;
    g[7] = dr.y;
    g[8] = dr.z;
    g[9] = dr.w;
    g[10] = grads[go + 15u] * sigmoid(th[10]);

    // AdamW, entry by entry; an entry without a finite gradient keeps its parameter
    // and moments.
    var bad = 0u;
    for (var i = 0u; i < RAW; i++) {
        let gi = g[i];
        if (!finite(gi)) {
            bad += 1u;
            continue;
        }
        let grp = group(i);
        let a = p.beta1 * m1[o + i] + (1.0 - p.beta1) * gi;
        let b = p.beta2 * m2[o + i] + (1.0 - p.beta2) * gi * gi;
        let step = (a / p.bias1) / (sqrt(b / p.bias2) + p.eps);
        th[i] = th[i] - p.lr[grp] * (step + p.decay[grp] * th[i]);
        m1[o + i] = a;
        m2[o + i] = b;
    }
    if (bad > 0u) {
        atomicAdd(&skipped[0], bad);
    }
    // The rotation back to unit length, or the identity where it collapsed.
    let rn = sqrt(th[6] * th[6] + th[7] * th[7] + th[8] * th[8] + th[9] * th[9]);
    if (finite(rn) && rn > 1e-12) {
        for (var i = 6u; i < 10u; i++) {
            th[i] = th[i] / rn;
        }
    } else {
        th[6] = 1.0;
        th[7] = 0.0;
        th[8] = 0.0;
        th[9] = 0.0;
    }
    for (var i = 0u; i < RAW; i++) {
        raw[o + i] = th[i];
    }
    if (p.mean_weight > 0.0) {
        for (var i = 0u; i < RAW; i++) {
            mean[o + i] = mean[o + i] + (th[i] - mean[o + i]) * p.mean_weight;
        }
    }

    // The primitive the next step renders.
    var c: vec3<f32>;
    var s: vec3<f32>;
    for (var j = 0u; j < 3u; j++) {
        c[j] = p.centre[j] + p.half[j] * tanh_f(th[j]);
        s[j] = exp(lmin + lspan * sigmoid(th[3u + j]));
    }
    let qw = th[6];
    let qx = th[7];
    let qy = th[8];
    let qz = th[9];
    let x2 = qx + qx;
    let y2 = qy + qy;
    let z2 = qz + qz;
    let xx = qx * x2;
    let xy = qx * y2;
    let xz = qx * z2;
    let yy = qy * y2;
    let yz = qy * z2;
    let zz = qz * z2;
    let wx = qw * x2;
    let wy = qw * y2;
    let wz = qw * z2;
    prims[k] = Prim(
        vec4<f32>(c, softplus(th[10])),
        vec4<f32>(1.0 - (yy + zz), xy + wz, xz - wy, s.x),
        vec4<f32>(xy - wz, 1.0 - (xx + zz), yz + wx, s.y),
        vec4<f32>(xz + wy, yz - wx, 1.0 - (xx + yy), s.z),
        vec4<f32>(s.y * s.z, s.x * s.z, s.x * s.y, 0.0),
    );
}

// The fit's data term and its gradient for a rendered mini-batch
// (recon/src/gtr/render.rs, `residuals`): workgroup x takes pair x, each thread a
// stride of its bins, writing ∂L/∂τ̂ for each bin and the pair's share of the loss,
// summed over the workgroup in a fixed tree order.
struct Params {
    bins: u32,
    // 0: L2, 1: the Poisson deviance against the rate τ̂ + background.
    loss: u32,
    // Where the pairs' losses go in `result`.
    loss_at: u32,
    pad0: u32,
    background: f32,
    pad1: f32,
    pad2: f32,
    pad3: f32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read> model: array<f32>;
@group(0) @binding(2) var<storage, read> data: array<f32>;
// Per pair: its weight (over the batch size), its gain in the model, and the first
// and end bin its recording covers (whole numbers; outside them no data term).
@group(0) @binding(3) var<storage, read> weights: array<vec4<f32>>;
@group(0) @binding(4) var<storage, read_write> dl: array<f32>;
@group(0) @binding(5) var<storage, read_write> result: array<f32>;

const THREADS: u32 = 256u;

var<workgroup> part: array<f32, 256>;

@compute @workgroup_size(256)
fn main(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) t: u32) {
    let w = weights[wg.x].x;
    let gain = weights[wg.x].y;
    let first = u32(weights[wg.x].z);
    let end = u32(weights[wg.x].w);
    var sum = 0.0;
    for (var b = t; b < p.bins; b += THREADS) {
        let i = wg.x * p.bins + b;
        if (b < first || b >= end) {
            dl[i] = 0.0;
            continue;
        }
        let m = gain * model[i];
        let d = data[i];
        var l = 0.0;
        var g = 0.0;
        if (p.loss == 0u) {
            let r = m - d;
            l = r * r;
            g = 2.0 * r;
        } else {
            // The model is a sum of non-negative terms; the floor guards the logarithm
            // against round-off below zero.
            let rate = max(m + p.background, 1.17549435e-38);
            var log_term = 0.0;
            if (d > 0.0) {
                log_term = d * log(d / rate);
            }
            l = 2.0 * (log_term - d + rate);
            g = 2.0 * (1.0 - d / rate);
        }
        dl[i] = w * g * gain;
        sum += w * l;
    }
    part[t] = sum;
    workgroupBarrier();
    for (var half = THREADS / 2u; half > 0u; half /= 2u) {
        if (t < half) {
            part[t] += part[t + half];
        }
        workgroupBarrier();
    }
    if (t == 0u) {
        result[p.loss_at + wg.x] = part[0];
    }
}

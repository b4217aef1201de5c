// Sums `groups` partial arrays of `len` values each (group g at g·len), in group order,
// into the first: the forward render's partial transients, one array per group of
// primitives, become the transients.
struct Params {
    len: u32,
    groups: u32,
    pad0: u32,
    pad1: u32,
}

@group(0) @binding(0) var<uniform> p: Params;
@group(0) @binding(1) var<storage, read_write> values: array<f32>;

@compute @workgroup_size(256)
fn main(@builtin(global_invocation_id) id: vec3<u32>, @builtin(num_workgroups) n: vec3<u32>) {
    let i = id.x + id.y * n.x * 256u;
    if (i >= p.len) {
        return;
    }
    var s = values[i];
    for (var g = 1u; g < p.groups; g++) {
        s += values[g * p.len + i];
    }
    values[i] = s;
}

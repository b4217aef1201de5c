//! Hierarchical backprojection of phasor-filtered histograms: fast factorised
//! backprojection's idea (Basu and Bresler's for CT, Ulander's for SAR) adapted to
//! arbitrary illumination/detection pairs. On a small box of voxels, pairs whose path
//! lengths change alike across the box carry the same information there, and can be
//! summed into one before they are backprojected.
//!
//! The volume is split recursively into boxes down to leaves ([`leaf_shape`]). For
//! each leaf, with centre v, every pair's path-length gradient
//! k = (v − x_i)/|v − x_i| + (v − x_d)/|v − x_d| is computed, and the pairs whose k fall
//! in one cell of a grid are merged into one: a representative pair r at the members'
//! mean points, whose histogram is the sum of the members' histograms, each shifted by
//! its path length at v minus r's, ℓ_p(v) − ℓ_r(v). Across the leaf a member is then read
//! at a path length off by
//!
//! e_p(x) = [ℓ_p(x) − ℓ_p(v)] − [ℓ_r(x) − ℓ_r(v)],
//!
//! zero at v and about (k_p − k_r)·(x − v) elsewhere. A group is merged only when a
//! bound on |e_p| over the leaf (its Taylor terms, [`Tree::merge_group`]) stays within
//! `path-error` phasor wavelengths for every member; otherwise its pairs stay apart.
//! The leaf then backprojects its merged and unmerged pairs with the exact path's row
//! arithmetic (the carrier interpolated linearly between bins, times the voxel's part
//! of the falloff weight; a member's part enters as its ratio to r's at v).
//!
//! The shift is done in baseband: the phasor histogram is a carrier e^{iωℓ}
//! (ω = 2π/λ) times a slow envelope, so a member read part of a bin off is the linear
//! interpolation of the envelope, with the carrier's phase put back exactly: a two-tap
//! complex filter whose taps are fixed for the whole window.
//!
//! The work is in the merging: every leaf visits every pair. So the groups of all the
//! leaves of a box one level up are planned from the pairs' geometry first, and the
//! histograms then read once for all of them, pair after pair (their windows overlap
//! in path length), in the real and imaginary parts apart so the adds vectorise.
//! Merging on larger boxes as well, to pass merged pairs down, was tried and merged
//! less: the larger box's merges spent the error budget the leaves' merges need
//! (docs/recon.md, "A hierarchical backprojection").
use glam::DVec3;
use rayon::prelude::*;

use crate::transient::{TimeAxis, TransientSet};
use crate::volume::VolumeGrid;

/// The most voxels along each side of a leaf box, and the fewest.
const LEAF_MAX: usize = 16;
const LEAF_MIN: usize = 4;

/// A leaf's half extent along each axis, at most, in phasor wavelengths. On 8,000 pairs
/// from one laser point into 128 × 128 × 64 voxels (λ = 3.8 cm, voxels of 7.8 mm
/// laterally), leaves of 16 × 16 × 16 voxels (half extents 1.5 λ) ran in 3.0 s,
/// 16 × 8 × 8 in 3.5 s, 16 × 4 × 4 in 9.7 s and 32 × 16 × 16 in 10.9 s (the exact
/// path 11.5–15.9 s in the same runs): a larger leaf is visited by the pairs fewer times, a smaller one
/// lets more of them merge.
const LEAF_HALF_WAVELENGTHS: f64 = 1.6;

/// The leaf boxes' voxels along x, y and z for `grid` and wavelength `lambda`: per
/// axis the largest power of two from [`LEAF_MIN`] to [`LEAF_MAX`] whose half extent
/// stays within [`LEAF_HALF_WAVELENGTHS`].
fn leaf_shape(grid: &VolumeGrid, lambda: f64) -> [usize; 3] {
    let voxel = grid.voxel();
    std::array::from_fn(|a| {
        let mut edge = LEAF_MAX;
        while edge > LEAF_MIN && 0.5 * (edge - 1) as f64 * voxel[a] > LEAF_HALF_WAVELENGTHS * lambda {
            edge /= 2;
        }
        edge
    })
}

/// A box of voxels, index ranges `lo..hi` along x, y and z.
#[derive(Clone, Copy, Debug)]
struct Block {
    lo: [usize; 3],
    hi: [usize; 3],
}

impl Block {
    fn len(&self) -> usize {
        (0..3).map(|a| self.hi[a] - self.lo[a]).product()
    }

    fn is_leaf(&self, leaf: [usize; 3]) -> bool {
        (0..3).all(|a| self.hi[a] - self.lo[a] <= leaf[a])
    }

    /// Levels of splitting below this box to its leaves.
    fn levels(&self, leaf: [usize; 3]) -> u32 {
        (0..3)
            .map(|a| {
                (self.hi[a] - self.lo[a])
                    .div_ceil(leaf[a])
                    .next_power_of_two()
                    .trailing_zeros()
            })
            .max()
            .unwrap_or(0)
    }

    /// The children: every side longer than a leaf halved (at a multiple of the leaf).
    fn children(&self, leaf: [usize; 3]) -> Vec<Block> {
        let cuts: [Vec<(usize, usize)>; 3] = std::array::from_fn(|a| {
            let (lo, hi) = (self.lo[a], self.hi[a]);
            let leaves = (hi - lo).div_ceil(leaf[a]);
            if leaves <= 1 {
                vec![(lo, hi)]
            } else {
                let mid = lo + leaves.div_ceil(2) * leaf[a];
                vec![(lo, mid), (mid, hi)]
            }
        });
        let mut out = Vec::with_capacity(8);
        for &(z0, z1) in &cuts[2] {
            for &(y0, y1) in &cuts[1] {
                for &(x0, x1) in &cuts[0] {
                    out.push(Block {
                        lo: [x0, y0, z0],
                        hi: [x1, y1, z1],
                    });
                }
            }
        }
        out
    }
}

/// One source: a pair's points (or a merged group's representative) and its complex
/// histogram on the global bin index, with one zero bin at each end.
#[derive(Clone, Copy)]
struct Source<'a> {
    xi: DVec3,
    xd: DVec3,
    /// Global bin index of `data[0]`.
    start: isize,
    /// Each bin with the next, as the leaves read them.
    data: &'a [[f32; 4]],
    /// The same bins' real and imaginary parts apart (the merges read these); empty
    /// for a merged source, which is never merged again.
    re: &'a [f32],
    im: &'a [f32],
}

/// A pair's two legs seen from a box's centre v: their unit directions and lengths.
struct Legs {
    ui: DVec3,
    di: f64,
    ud: DVec3,
    dd: f64,
}

impl Legs {
    fn at(v: DVec3, xi: DVec3, xd: DVec3) -> Self {
        let (a, b) = (v - xi, v - xd);
        let (di, dd) = (
            a.length().max(f64::MIN_POSITIVE),
            b.length().max(f64::MIN_POSITIVE),
        );
        Self {
            ui: a / di,
            di,
            ud: b / dd,
            dd,
        }
    }

    /// The path length's gradient.
    fn k(&self) -> DVec3 {
        self.ui + self.ud
    }

    /// The voxel's part of the falloff weight, 4·d_i·d_d/ℓ² (1 on a confocal pair).
    fn falloff_part(&self) -> f64 {
        4.0 * self.di * self.dd / ((self.di + self.dd) * (self.di + self.dd))
    }
}

/// What the recursion shares.
struct Tree<'a> {
    grid: &'a VolumeGrid,
    axis: TimeAxis,
    lead: usize,
    falloff: f64,
    /// The carrier's phase per bin, 2π·width/λ.
    phase_per_bin: f64,
    /// The largest path-length error a merge may leave, metres.
    tolerance: f64,
    /// The leaf boxes' voxels along x, y and z ([`leaf_shape`]).
    shape: [usize; 3],
}

/// How many merges the recursion made, for the log.
#[derive(Default, Clone, Copy)]
pub(super) struct TreeStats {
    /// Sources backprojected over all leaves, and leaves.
    pub leaf_sources: usize,
    pub leaves: usize,
}

impl<'a> Tree<'a> {
    /// The recursion over `grid` for histograms on `axis` with `lead` bins of padding,
    /// a phasor `wavelength` and merges within `tolerance` metres of path length.
    fn new(
        grid: &'a VolumeGrid,
        axis: &TimeAxis,
        lead: usize,
        falloff: f64,
        wavelength: f64,
        tolerance: f64,
    ) -> Self {
        Tree {
            grid,
            axis: *axis,
            lead,
            falloff,
            phase_per_bin: 2.0 * std::f64::consts::PI * axis.width / wavelength,
            tolerance,
            shape: leaf_shape(grid, wavelength),
        }
    }
}

impl Tree<'_> {
    /// The global fractional bin index of path length `l`: bin `j` of a filtered
    /// histogram (with its `lead` bins of padding) is centred at
    /// `start + (j − lead + ½)·width`.
    fn index(&self, l: f64) -> f64 {
        (l - self.axis.start) / self.axis.width - 0.5 + self.lead as f64
    }

    fn centre(&self, b: &Block) -> DVec3 {
        let (min, voxel) = (self.grid.min(), self.grid.voxel());
        DVec3::from_array(std::array::from_fn(|a| {
            min[a] + 0.5 * (b.lo[a] + b.hi[a]) as f64 * voxel[a]
        }))
    }

    /// Backprojects `sources` over box `b`: the leaves' values, each with its box.
    fn node(&self, b: Block, sources: &[Source<'_>]) -> Vec<Leaf> {
        if b.levels(self.shape) > 1 {
            return b
                .children(self.shape)
                .into_par_iter()
                .flat_map_iter(|child| self.node(child, sources))
                .collect();
        }
        // The leaves' groups from the pairs' geometry; then one pass over the sources
        // in order that adds each into every leaf's group it belongs to, so a
        // histogram is read once for all the leaves.
        let leaves = if b.is_leaf(self.shape) {
            vec![b]
        } else {
            b.children(self.shape)
        };
        let planned: Vec<(Vec<GroupPlan>, Vec<Planned>)> =
            leaves.par_iter().map(|leaf| self.merge(leaf, sources)).collect();
        let mut visits: Vec<(u32, u16, u32, u32)> = Vec::new();
        for (c, (groups, _)) in planned.iter().enumerate() {
            for (g, group) in groups.iter().enumerate() {
                for (m, member) in group.members.iter().enumerate() {
                    visits.push((member.source, c as u16, g as u32, m as u32));
                }
            }
        }
        visits.par_sort_unstable();
        let mut data: Vec<Vec<(Vec<f32>, Vec<f32>)>> = planned
            .iter()
            .map(|(groups, _)| {
                groups
                    .iter()
                    .map(|g| (vec![0.0f32; g.len], vec![0.0f32; g.len]))
                    .collect()
            })
            .collect();
        crate::simd::dispatch(Accumulate {
            visits: &visits,
            planned: &planned,
            sources,
            data: &mut data,
        });
        let doubled: Vec<Vec<Vec<[f32; 4]>>> = data
            .into_par_iter()
            .map(|groups| groups.into_iter().map(|(re, im)| double(&re, &im)).collect())
            .collect();
        leaves
            .into_par_iter()
            .zip(planned.into_par_iter().zip(doubled.par_iter()))
            .map(|(leaf, ((groups, plan), merged))| {
                let mine: Vec<Source<'_>> = plan
                    .into_iter()
                    .map(|p| match p {
                        Planned::Keep(i) => sources[i],
                        Planned::Merged(g) => Source {
                            xi: groups[g].xi,
                            xd: groups[g].xd,
                            start: groups[g].start,
                            data: &merged[g],
                            re: &[],
                            im: &[],
                        },
                    })
                    .collect();
                Leaf {
                    block: leaf,
                    values: self.leaf(&leaf, &mine),
                    sources: mine.len(),
                }
            })
            .collect()
    }

    /// Groups `sources` for leaf `b` by their path-length gradient at its centre, and
    /// plans a merge of each group whose members all stay within the tolerance.
    /// Returns the planned merges and the leaf's sources in order (a kept source by
    /// its index, a merged one by its place among the merges).
    fn merge(&self, b: &Block, sources: &[Source<'_>]) -> (Vec<GroupPlan>, Vec<Planned>) {
        let v = self.centre(b);
        let (half, diagonal) = self.half_extents(b);
        // Cells whose gradients differ by up to half the tolerance over the box's
        // half-diagonal: the other half is left to the position of k within its cell,
        // and to the quadratic and cubic terms.
        let cell = 0.5 * self.tolerance / diagonal.max(f64::MIN_POSITIVE);
        let geo: Vec<Legs> = sources.iter().map(|s| Legs::at(v, s.xi, s.xd)).collect();
        let key = |g: &Legs| -> u64 {
            // |k| ≤ 2, so each coordinate's cell number fits 21 bits for cells down to
            // 2⁻¹⁸; finer cells than that merge nothing anyway.
            let q = |c: f64| (((c + 2.0) / cell).floor().clamp(0.0, 2_097_151.0)) as u64;
            let k = g.k();
            q(k.x) << 42 | q(k.y) << 21 | q(k.z)
        };
        let mut keyed: Vec<(u64, u32)> = geo.iter().enumerate().map(|(i, g)| (key(g), i as u32)).collect();
        keyed.sort_unstable();
        let mut arena = Vec::new();
        let mut plan = Vec::with_capacity(sources.len());
        for group in keyed.chunk_by(|a, b| a.0 == b.0) {
            if group.len() == 1 {
                plan.push(Planned::Keep(group[0].1 as usize));
                continue;
            }
            let members: Vec<(u32, &Source<'_>, &Legs)> = group
                .iter()
                .map(|&(_, i)| (i, &sources[i as usize], &geo[i as usize]))
                .collect();
            match self.merge_group(&members, v, half, diagonal) {
                Some(g) => {
                    plan.push(Planned::Merged(arena.len()));
                    arena.push(g);
                }
                None => plan.extend(group.iter().map(|&(_, i)| Planned::Keep(i as usize))),
            }
        }
        (arena, plan)
    }

    /// The box's half extents between its outermost voxel centres, and their length.
    fn half_extents(&self, b: &Block) -> (DVec3, f64) {
        let voxel = self.grid.voxel();
        let half = DVec3::from_array(std::array::from_fn(|a| {
            0.5 * (b.hi[a] - b.lo[a] - 1) as f64 * voxel[a]
        }));
        (half, half.length())
    }

    /// One group's planned merge (its representative, window and members' taps), or
    /// `None` when a member would leave more than the tolerance ([`error_bound`]).
    fn merge_group(
        &self,
        members: &[(u32, &Source<'_>, &Legs)],
        v: DVec3,
        half: DVec3,
        diagonal: f64,
    ) -> Option<GroupPlan> {
        let n = members.len() as f64;
        let xi = members.iter().map(|(_, s, _)| s.xi).sum::<DVec3>() / n;
        let xd = members.iter().map(|(_, s, _)| s.xd).sum::<DVec3>() / n;
        let r = Legs::at(v, xi, xd);
        let kr = r.k();
        for (_, _, g) in members {
            if error_bound(g, &r, half, diagonal) > self.tolerance {
                return None;
            }
        }
        // r's path lengths over the box lie within ℓ(v) ± (|k|·|δ| + the quadratic
        // term's |δ|²·Σ 1/d).
        let lr_v = r.di + r.dd;
        let reach = kr.length() * diagonal + diagonal * diagonal * (1.0 / r.di + 1.0 / r.dd);
        let j0 = self.index(lr_v - reach).floor() as isize - 1;
        let j1 = self.index(lr_v + reach).floor() as isize + 2;
        // One zero bin at each end, as every source's histogram.
        let start = j0 - 1;
        let len = (j1 - j0 + 3) as usize;
        let gain_r = r.falloff_part();
        let w = self.axis.width;
        let phi = self.phase_per_bin;
        let members = members
            .iter()
            .map(|&(source, s, g)| {
                let shift = (g.di + g.dd - lr_v) / w;
                let m = shift.floor();
                let t = shift - m;
                let ratio = g.falloff_part() / gain_r.max(f64::MIN_POSITIVE);
                let a = match self.falloff {
                    0.0 => 1.0,
                    1.0 => ratio,
                    2.0 => ratio * ratio,
                    p => ratio.powf(p),
                };
                // The member at global index j + shift, in baseband: the envelope's
                // linear interpolation with the carrier's phase restored,
                // (1 − t)·e^{iφt}·h[j + m] + t·e^{−iφ(1 − t)}·h[j + m + 1].
                Member {
                    source,
                    base: start + m as isize - s.start,
                    c0: cis(a * (1.0 - t), phi * t),
                    c1: cis(a * t, -phi * (1.0 - t)),
                }
            })
            .collect();
        Some(GroupPlan {
            xi,
            xd,
            start,
            len,
            members,
        })
    }

    /// The exact path's arithmetic over one leaf: every source, every voxel, each row
    /// along x through the exact path's row functions.
    fn leaf(&self, b: &Block, sources: &[Source<'_>]) -> Vec<[f32; 2]> {
        let mut out = vec![[0.0f32; 2]; b.len()];
        crate::simd::dispatch(LeafWork {
            tree: self,
            block: b,
            sources,
            out: &mut out,
        });
        out
    }
}

/// One leaf of [`Tree::leaf`], run under [`crate::simd::dispatch`].
struct LeafWork<'a, 'b> {
    tree: &'b Tree<'b>,
    block: &'b Block,
    sources: &'b [Source<'a>],
    out: &'b mut [[f32; 2]],
}

impl crate::simd::Work for LeafWork<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) {
        let LeafWork {
            tree,
            block: b,
            sources,
            out,
        } = self;
        let (min, voxel) = (tree.grid.min(), tree.grid.voxel());
        let coord = |a: usize, i: usize| (min[a] + (i as f64 + 0.5) * voxel[a]) as f32;
        let xs: Vec<f32> = (b.lo[0]..b.hi[0]).map(|i| coord(0, i)).collect();
        let nx = xs.len();
        let (mut index, mut gain) = (vec![0.0f32; nx], vec![1.0f32; nx]);
        let (mut bin, mut weights) = (vec![0i32; nx], vec![[0.0f32; 2]; nx]);
        let inv_w = (1.0 / tree.axis.width) as f32;
        for s in sources {
            let (xi, xd) = (s.xi.as_vec3(), s.xd.as_vec3());
            // The local fractional index is path·inv_w − offset.
            let offset = (s.start as f64 - tree.index(0.0)) as f32;
            let top = (s.data.len() - 1) as f32;
            let mut rows = out.chunks_exact_mut(nx);
            for iz in b.lo[2]..b.hi[2] {
                let z = coord(2, iz);
                for iy in b.lo[1]..b.hi[1] {
                    let y = coord(1, iy);
                    let byi = (z - xi.z) * (z - xi.z) + (y - xi.y) * (y - xi.y);
                    let byd = (z - xd.z) * (z - xd.z) + (y - xd.y) * (y - xd.y);
                    super::path_row(
                        &xs,
                        byi,
                        byd,
                        xi.x,
                        xd.x,
                        inv_w,
                        offset,
                        top,
                        tree.falloff,
                        &mut index,
                        &mut gain,
                    );
                    super::weights_row(&index, &gain, &mut bin, &mut weights);
                    if let Some(row) = rows.next() {
                        super::gather_row(row, &bin, &weights, s.data);
                    }
                }
            }
        }
    }
}

/// A bound on |e_p(x)| = |[ℓ_p(x) − ℓ_p(v)] − [ℓ_r(x) − ℓ_r(v)]| over a box with
/// centre v, half extents `half` and half-diagonal `diagonal`, for member legs `p` and
/// representative legs `r` seen from v. With δ = x − v, the Taylor terms: the linear
/// Σ_a |k_p − k_r|_a·h_a; the quadratic |δ|²/2·‖H_p − H_r‖, each leg's Hessian
/// (I − uuᵀ)/d differing by at most |1/d_p − 1/d_r| + 2|u_p − u_r|/d; and the cubic
/// remainder, a leg's third derivatives being at most 3/d² where the box comes nearest
/// its point (/6 each, for two legs of two pairs: |δ|³·Σ 1/d²). Infinite for a box
/// that comes within twice its half-diagonal of a point.
fn error_bound(p: &Legs, r: &Legs, half: DVec3, diagonal: f64) -> f64 {
    let linear = ((p.k() - r.k()).abs() * half).element_sum();
    let (di, dd) = (p.di.min(r.di), p.dd.min(r.dd));
    let hessian = (1.0 / p.di - 1.0 / r.di).abs()
        + 2.0 * p.ui.distance(r.ui) / di
        + (1.0 / p.dd - 1.0 / r.dd).abs()
        + 2.0 * p.ud.distance(r.ud) / dd;
    // A box that reaches within its half-diagonal of a point: no bound worth having.
    if di <= 2.0 * diagonal || dd <= 2.0 * diagonal {
        return f64::INFINITY;
    }
    let (ni, nd) = (di - diagonal, dd - diagonal);
    let cubic = diagonal.powi(3) * (1.0 / (ni * ni) + 1.0 / (nd * nd));
    linear + 0.5 * diagonal * diagonal * hessian + cubic
}

/// A leaf's sums, and how many sources it backprojected.
struct Leaf {
    block: Block,
    values: Vec<[f32; 2]>,
    sources: usize,
}

/// A child's source: one of the parent's, or a merged one (its histogram is the next
/// in the merge's list).
enum Planned {
    Keep(usize),
    Merged(usize),
}

/// A merged group: its representative, its window (global start, length with the
/// zero bin at each end), and how each member is added in.
struct GroupPlan {
    xi: DVec3,
    xd: DVec3,
    start: isize,
    len: usize,
    members: Vec<Member>,
}

/// A member of a group: its source, the offset from the window's index to its own,
/// and the two taps.
struct Member {
    source: u32,
    base: isize,
    c0: [f32; 2],
    c1: [f32; 2],
}

/// The pass of [`Tree::node`] that adds every member into its group's window, in
/// the order of `visits` (by source), under [`crate::simd::dispatch`].
struct Accumulate<'a, 'b> {
    visits: &'b [(u32, u16, u32, u32)],
    planned: &'b [(Vec<GroupPlan>, Vec<Planned>)],
    sources: &'b [Source<'a>],
    data: &'b mut [Vec<(Vec<f32>, Vec<f32>)>],
}

impl crate::simd::Work for Accumulate<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) {
        for &(_, c, g, m) in self.visits {
            let member = &self.planned[c as usize].0[g as usize].members[m as usize];
            let (re, im) = &mut self.data[c as usize][g as usize];
            add_shifted(re, im, member, &self.sources[member.source as usize]);
        }
    }
}

/// Adds `member` (whose histogram is `s`'s) into a group's window `(re, im)`:
/// window index o reads the member's o + base and the next. Only the interior (the
/// two ends stay zero) and what the member holds.
#[inline(always)]
fn add_shifted(re: &mut [f32], im: &mut [f32], member: &Member, s: &Source<'_>) {
    let Member { base, c0, c1, .. } = *member;
    let o_lo = (-base).max(1);
    let o_hi = (s.re.len() as isize - 2 - base).min(re.len() as isize - 2);
    if o_hi < o_lo {
        return;
    }
    let (o_lo, n) = (o_lo as usize, (o_hi - o_lo + 1) as usize);
    let i = (base + o_lo as isize) as usize;
    let (h0r, h1r) = (&s.re[i..i + n], &s.re[i + 1..i + n + 1]);
    let (h0i, h1i) = (&s.im[i..i + n], &s.im[i + 1..i + n + 1]);
    let (dr, di) = (&mut re[o_lo..o_lo + n], &mut im[o_lo..o_lo + n]);
    for k in 0..n {
        dr[k] += c0[0] * h0r[k] - c0[1] * h0i[k] + c1[0] * h1r[k] - c1[1] * h1i[k];
        di[k] += c0[0] * h0i[k] + c0[1] * h0r[k] + c1[0] * h1i[k] + c1[1] * h1r[k];
    }
}

/// A window as the leaves read it, each bin with the next.
fn double(re: &[f32], im: &[f32]) -> Vec<[f32; 4]> {
    (0..re.len())
        .map(|o| {
            let next = |v: &[f32]| v.get(o + 1).copied().unwrap_or_default();
            [re[o], im[o], next(re), next(im)]
        })
        .collect()
}

/// `r·e^{iθ}` as `[re, im]` in f32.
fn cis(r: f64, theta: f64) -> [f32; 2] {
    let (s, c) = theta.sin_cos();
    [(r * c) as f32, (r * s) as f32]
}

/// Backprojects the phasor-filtered `hists` (real and imaginary parts interleaved,
/// `lead` bins of padding each side) of `set` onto `grid` through the hierarchy, with
/// merges leaving at most `tolerance` metres of path-length error. Returns the two
/// sums per voxel and what the hierarchy did.
pub(super) fn backproject_tree(
    set: &TransientSet,
    grid: &VolumeGrid,
    falloff: f64,
    hists: Vec<Vec<f32>>,
    lead: usize,
    wavelength: f64,
    tolerance: f64,
) -> (Vec<[f32; 2]>, TreeStats) {
    // Each histogram with one zero bin before and after, each bin with the next.
    let complex = super::doubled::<2, 4>(&hists);
    // And the real and imaginary parts apart, with the same zero bin at each end.
    let split: Vec<(Vec<f32>, Vec<f32>)> = hists
        .par_iter()
        .map(|h| {
            let part = |c: usize| {
                let mut v = Vec::with_capacity(h.len() / 2 + 2);
                v.push(0.0);
                v.extend(h.iter().skip(c).step_by(2));
                v.push(0.0);
                v
            };
            (part(0), part(1))
        })
        .collect();
    // The two layouts replace the histograms.
    drop(hists);
    let sources: Vec<Source<'_>> = set
        .pairs()
        .iter()
        .zip(complex.iter().zip(&split))
        .map(|(p, (data, (re, im)))| Source {
            xi: p.xi,
            xd: p.xd,
            start: -1,
            data,
            re,
            im,
        })
        .collect();
    let tree = Tree::new(grid, set.axis(), lead, falloff, wavelength, tolerance);
    let root = Block {
        lo: [0; 3],
        hi: grid.shape,
    };
    let leaves = tree.node(root, &sources);
    let [nx, ny, _] = grid.shape;
    let mut data = vec![[0.0f32; 2]; grid.len()];
    let mut stats = TreeStats::default();
    for Leaf {
        block: b,
        values,
        sources,
    } in &leaves
    {
        stats.leaves += 1;
        stats.leaf_sources += sources;
        let mut o = 0;
        for iz in b.lo[2]..b.hi[2] {
            for iy in b.lo[1]..b.hi[1] {
                for ix in b.lo[0]..b.hi[0] {
                    data[(iz * ny + iy) * nx + ix] = values[o];
                    o += 1;
                }
            }
        }
    }
    (data, stats)
}

/// Leaves whose merges [`merged_fraction`] plans, at most.
const SAMPLE_LEAVES: usize = 16;

/// The share of the pairs a leaf would still backproject after its merges, the mean
/// over up to [`SAMPLE_LEAVES`] leaves spread evenly through the volume (every n-th
/// leaf of a depth-first walk). Planning reads no histogram, so this costs
/// about a thousandth of the backprojection it decides on.
pub(super) fn merged_fraction(set: &TransientSet, grid: &VolumeGrid, wavelength: f64, tolerance: f64) -> f64 {
    if set.is_empty() {
        return 1.0;
    }
    let sources: Vec<Source<'_>> = set
        .pairs()
        .iter()
        .map(|p| Source {
            xi: p.xi,
            xd: p.xd,
            start: -1,
            data: &[],
            re: &[],
            im: &[],
        })
        .collect();
    // Planning reads neither the padding nor the falloff's exponent.
    let tree = Tree::new(grid, set.axis(), 0, 1.0, wavelength, tolerance);
    let mut leaves = Vec::new();
    let mut open = vec![Block {
        lo: [0; 3],
        hi: grid.shape,
    }];
    while let Some(b) = open.pop() {
        if b.is_leaf(tree.shape) {
            leaves.push(b);
        } else {
            open.extend(b.children(tree.shape));
        }
    }
    let n = leaves.len().min(SAMPLE_LEAVES);
    let kept: usize = (0..n)
        .into_par_iter()
        .map(|i| {
            let leaf = leaves[(2 * i + 1) * leaves.len() / (2 * n)];
            tree.merge(&leaf, &sources).1.len()
        })
        .sum();
    kept as f64 / (n * sources.len()) as f64
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::transient::Pair;
    use rand::{Rng, SeedableRng};
    use rand_chacha::ChaCha8Rng;

    #[test]
    fn the_error_bound_holds_over_the_box() {
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let mut ratios = Vec::new();
        for _ in 0..400 {
            let v = DVec3::new(
                rng.random_range(-0.4..0.4),
                rng.random_range(-0.4..0.4),
                rng.random_range(0.3..1.2),
            );
            let half = DVec3::new(
                rng.random_range(0.005..0.08),
                rng.random_range(0.005..0.08),
                rng.random_range(0.005..0.08),
            );
            let wall = |rng: &mut ChaCha8Rng| {
                DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0)
            };
            let (ri, rd) = (wall(&mut rng), wall(&mut rng));
            let near = |c: DVec3, rng: &mut ChaCha8Rng| {
                c + DVec3::new(rng.random_range(-0.06..0.06), rng.random_range(-0.06..0.06), 0.0)
            };
            let (pi, pd) = (near(ri, &mut rng), near(rd, &mut rng));
            let bound = error_bound(&Legs::at(v, pi, pd), &Legs::at(v, ri, rd), half, half.length());
            let l = |x: DVec3, a: DVec3, b: DVec3| x.distance(a) + x.distance(b);
            let e = |x: DVec3| (l(x, pi, pd) - l(v, pi, pd)) - (l(x, ri, rd) - l(v, ri, rd));
            let mut worst = 0.0f64;
            for c in 0..8 {
                let corner = DVec3::new(
                    if c & 1 == 0 { -1.0 } else { 1.0 },
                    if c & 2 == 0 { -1.0 } else { 1.0 },
                    if c & 4 == 0 { -1.0 } else { 1.0 },
                );
                worst = worst.max(e(v + corner * half).abs());
            }
            for _ in 0..200 {
                let u = DVec3::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                );
                worst = worst.max(e(v + u * half).abs());
            }
            assert!(
                worst <= bound,
                "error {worst} m over the box exceeds the bound {bound} m (centre {v}, half {half})"
            );
            if bound.is_finite() {
                ratios.push(bound / worst.max(1e-12));
            }
        }
        // And not so loose that it would stop every merge: the median bound is within
        // a few times the worst error it bounds.
        ratios.sort_by(f64::total_cmp);
        let median = ratios[ratios.len() / 2];
        assert!(
            median < 4.0,
            "the bound is {median} times the error at the median"
        );
    }

    #[test]
    fn one_laser_points_pairs_merge_many_to_one() {
        // One laser point, 2,000 detection points at random on a 1 m wall, into
        // 64 × 64 × 32 voxels: the two-torso kind of capture, where the pairs'
        // gradients form a two-parameter family and most of them merge on a leaf.
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let axis = TimeAxis {
            start: 0.8,
            width: 0.0096,
            bins: 256,
        };
        let mut set = TransientSet::new(axis).unwrap();
        let xi = DVec3::new(-0.3, 0.1, 0.0);
        let h = vec![1.0f32; axis.bins];
        for _ in 0..2000 {
            let xd = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
            set.push(
                Pair {
                    xi,
                    ni: DVec3::Z,
                    xd,
                    nd: DVec3::Z,
                },
                &h,
            )
            .unwrap();
        }
        let grid = VolumeGrid::new([-0.5, 0.5], [-0.5, 0.5], [0.5, 0.9], [64, 64, 32]).unwrap();
        let lead = 8;
        let hists: Vec<Vec<f32>> = (0..set.len())
            .map(|_| {
                (0..2 * (axis.bins + 2 * lead))
                    .map(|_| rng.random::<f32>())
                    .collect()
            })
            .collect();
        let lambda = 4.0 * axis.width;
        let (sums, stats) = backproject_tree(&set, &grid, 1.0, hists, lead, lambda, 0.25 * lambda);
        assert_eq!(sums.len(), grid.len());
        assert!(sums.iter().flatten().all(|v| v.is_finite()));
        let per_leaf = stats.leaf_sources as f64 / stats.leaves as f64;
        assert!(
            per_leaf < 0.25 * set.len() as f64,
            "a leaf reads {per_leaf} sources of {} pairs",
            set.len()
        );
        // The sample `auto` decides on sees what the whole volume does, and takes the
        // hierarchy here.
        let sampled = merged_fraction(&set, &grid, lambda, 0.25 * lambda);
        let whole = per_leaf / set.len() as f64;
        assert!(
            (sampled - whole).abs() < 0.05 && sampled <= super::super::AUTO_MAX_FRACTION,
            "sampled {sampled}, the whole volume {whole}"
        );
        // Both points free: few merges, so `auto` keeps the exact path.
        let mut free = TransientSet::new(axis).unwrap();
        for _ in 0..2000 {
            let mut wall = || DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
            let (xi, xd) = (wall(), wall());
            let pair = Pair {
                xi,
                ni: DVec3::Z,
                xd,
                nd: DVec3::Z,
            };
            free.push(pair, &h).unwrap();
        }
        let sampled = merged_fraction(&free, &grid, lambda, 0.25 * lambda);
        assert!(sampled > super::super::AUTO_MAX_FRACTION, "sampled {sampled}");
    }
}

//! Hierarchical backprojection of phasor-filtered histograms: fast factorised
//! backprojection's idea (Basu and Bresler's for CT, Ulander's for SAR) adapted to
//! arbitrary illumination/detection pairs. On a small box of voxels, pairs whose path
//! lengths change alike across the box carry the same information there, and can be
//! summed into one before they are backprojected.
//!
//! The volume is split recursively into boxes down to leaves, whose shape a cost model
//! picks from a sample of each shape's merges ([`choose`]). For
//! each leaf, with centre v, every pair's path-length gradient
//! k = (v − x_i)/|v − x_i| + (v − x_d)/|v − x_d| is computed, and the pairs whose k fall
//! in one cell of a grid are merged into one: a representative pair r at the members'
//! mean points, whose histogram is the sum of the members' histograms, each shifted by
//! its path length at v minus r's, ℓ_p(v) − ℓ_r(v). Across the leaf a member is then read
//! at a path length off by
//!
//! e_p(x) = [ℓ_p(x) − ℓ_p(v)] − [ℓ_r(x) − ℓ_r(v)],
//!
//! zero at v and about (k_p − k_r)·(x − v) elsewhere. A member joins the merge only
//! when a bound on |e_p| over the leaf (its Taylor terms, [`error_bound`]) stays within
//! `path-error` phasor wavelengths; those that do not stay apart, and the rest are
//! tried again about their own mean ([`Tree::merge_cells`]). The leaf then
//! backprojects its merged and unmerged pairs with the exact path's arithmetic (the
//! carrier interpolated linearly between bins, times the voxel's part of the falloff
//! weight; a member's part enters as its ratio to r's at v), over all its voxels as one
//! run rather than row by row, as a leaf's rows are short. Each leg's length comes
//! from its quadratic Taylor model about v instead of a square root, where the
//! remainder's bound over the leaf keeps the two legs within λ/64 together
//! ([`LegModel`], [`QUADRATIC_ERROR`]); a pair nearer the leaf than that takes the
//! square roots. Where the bins a source's voxels read fit one window of
//! [`WINDOW`], they are read from registers ([`crate::simd::Quad::window_add`]).
//!
//! The shift is done in baseband: the phasor histogram is a carrier e^{iωℓ}
//! (ω = 2π/λ) times a slow envelope, so a member read part of a bin off is the linear
//! interpolation of the envelope, with the carrier's phase put back exactly: a two-tap
//! complex filter whose taps are fixed for the whole window.
//!
//! The fixed cost is in the merging: every leaf visits every pair. So the groups of
//! all the leaves of a box one level up are planned from the pairs' geometry first (a
//! counting sort over the gradients' cells), and the histograms then read pair after
//! pair, each once for all those leaves (their windows overlap in path length), in the
//! real and imaginary parts apart, in whole chunks of bins, so the adds vectorise.
//! Those reads, and the leaves' reads of their sources' bins, jump from one
//! histogram to another, where the CPU's own prefetcher does not follow: the
//! memory a few sources ahead is asked for while one is added ([`PREFETCH_AHEAD`],
//! [`crate::simd::Quad::prefetch`]), and each member carries its group's window so
//! that the adds read nothing else of the plan.
//! Merging on larger boxes as well, to pass merged pairs down, was tried and merged
//! less: the larger box's merges spent the error budget the leaves' merges need
//! (docs/recon.md, "A hierarchical backprojection").
use glam::DVec3;
use rayon::prelude::*;

use crate::simd::WINDOW;
use crate::transient::{TimeAxis, TransientSet};
use crate::volume::VolumeGrid;

/// The leaf edges [`choose`] tries along each axis, in voxels.
const EDGES: [usize; 3] = [4, 8, 16];

/// The cost model [`choose`] ranks leaf shapes by, in nanoseconds of one core on the
/// machine that measured them (8,000 pairs into 128 × 128 × 64 voxels, docs/recon.md,
/// "A hierarchical backprojection"): a leaf's visit to a pair (its geometry, grouping,
/// merge plan and the shifted add of its histogram window), a leaf's backprojection of
/// one source into one voxel with the legs' quadratic models and with their square
/// roots, and the exact path's of one pair into one voxel. Only their ratios to the
/// exact path's matter. Each instruction set has its own: its leaves read their
/// windows their own way ([`crate::simd::Quad::window_add`]).
struct LeafCosts {
    visit: f64,
    modelled: f64,
    leaf: f64,
    exact: f64,
}

/// With AVX-512, fitted to seven leaf shapes' times on 2026-12-05 (the square roots'
/// figure is also what a leaf's voxel costs where its window is too wide to read from
/// registers).
const WITH_AVX512: LeafCosts = LeafCosts {
    visit: 100.0,
    modelled: 0.4,
    leaf: 0.8,
    exact: 1.4,
};

/// With AVX2 and FMA (no AVX-512), fitted to seven leaf shapes' times with the AVX2
/// window reads on 2026-12-05 (`PERISCOPE_SIMD=avx2` on the AVX-512 machine): a
/// voxel whose window is too wide for registers takes the gather, about 2 ns.
const WITH_AVX2: LeafCosts = LeafCosts {
    visit: 70.0,
    modelled: 0.85,
    leaf: 2.1,
    exact: 1.2,
};

/// Without either, the figures measured before the windows were read from registers
/// (2026-12-04), not measured on a CPU without AVX2.
const BASELINE: LeafCosts = LeafCosts {
    visit: 80.0,
    modelled: 1.8,
    leaf: 1.8,
    exact: 1.4,
};

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
    /// 1/d_i and 1/d_d.
    inv_i: f64,
    inv_d: f64,
}

impl Legs {
    fn at(v: DVec3, xi: DVec3, xd: DVec3) -> Self {
        let (a, b) = (v - xi, v - xd);
        let (di, dd) = (
            a.length().max(f64::MIN_POSITIVE),
            b.length().max(f64::MIN_POSITIVE),
        );
        let (inv_i, inv_d) = (1.0 / di, 1.0 / dd);
        Self {
            ui: a * inv_i,
            di,
            ud: b * inv_d,
            dd,
            inv_i,
            inv_d,
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
    /// The largest a leaf's quadratic path models may leave, metres
    /// ([`QUADRATIC_ERROR`] wavelengths).
    quadratic_tolerance: f64,
    /// The leaf boxes' voxels along x, y and z ([`choose`]).
    shape: [usize; 3],
    /// e^{iφj/TURN_STEPS} for j = 0..TURN_STEPS, and e^{−iφ} last ([`Tree::turn`]).
    turns: Vec<[f64; 2]>,
}

/// The steps of [`Tree::turns`]' table over one bin's phase.
const TURN_STEPS: usize = 64;

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
        shape: [usize; 3],
    ) -> Self {
        Tree {
            grid,
            axis: *axis,
            lead,
            falloff,
            phase_per_bin: 2.0 * std::f64::consts::PI * axis.width / wavelength,
            tolerance,
            quadratic_tolerance: QUADRATIC_ERROR * wavelength,
            turns: {
                let phi = 2.0 * std::f64::consts::PI * axis.width / wavelength;
                let mut t: Vec<[f64; 2]> = (0..TURN_STEPS)
                    .map(|j| {
                        let (s, c) = (phi * j as f64 / TURN_STEPS as f64).sin_cos();
                        [c, s]
                    })
                    .collect();
                let (s, c) = (-phi).sin_cos();
                t.push([c, s]);
                t
            },
            shape,
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

    /// e^{iφt} for t in [0, 1] as `[re, im]`: the table's nearest step below,
    /// turned on by the rest, e^{iδ} with |δ| ≤ φ/TURN_STEPS, from its Taylor series
    /// to the fifth power (off by under δ⁶/720, below 10⁻¹⁵ for φ up to π).
    #[inline(always)]
    fn turn(&self, t: f64) -> [f64; 2] {
        let x = t.clamp(0.0, 1.0) * TURN_STEPS as f64;
        let j = (x.floor() as usize).min(TURN_STEPS - 1);
        let d = self.phase_per_bin * (x - j as f64) / TURN_STEPS as f64;
        let d2 = d * d;
        let c = 1.0 - d2 * (0.5 - d2 * (1.0 / 24.0));
        let s = d * (1.0 - d2 * (1.0 / 6.0 - d2 * (1.0 / 120.0)));
        let [a, b] = self.turns[j];
        [a * c - b * s, a * s + b * c]
    }

    fn centre(&self, b: &Block) -> DVec3 {
        let (min, voxel) = (self.grid.min(), self.grid.voxel());
        DVec3::from_array(std::array::from_fn(|a| {
            min[a] + 0.5 * (b.lo[a] + b.hi[a]) as f64 * voxel[a]
        }))
    }

    /// Backprojects `sources` over box `b`: the leaves' values, each with its box.
    fn node(&self, b: Block, sources: &[Source<'_>], points: &Points) -> Vec<Leaf> {
        if b.levels(self.shape) > 1 {
            return b
                .children(self.shape)
                .into_par_iter()
                .flat_map_iter(|child| self.node(child, sources, points))
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
        let planned: Vec<LeafPlan> = leaves
            .par_iter()
            .map(|leaf| {
                crate::simd::dispatch(Plan {
                    tree: self,
                    block: leaf,
                    sources,
                    points,
                })
            })
            .collect();
        // Every member into its group's window, source after source, so that the
        // leaves' reads of one histogram follow each other.
        let mut data: Vec<(Vec<f32>, Vec<f32>)> = planned
            .iter()
            .map(|p| (vec![0.0f32; p.bins], vec![0.0f32; p.bins]))
            .collect();
        crate::simd::dispatch(Accumulate {
            planned: &planned,
            sources,
            data: &mut data,
        });
        let doubled: Vec<Vec<[f32; 4]>> = data
            .into_par_iter()
            .zip(planned.par_iter())
            .map(|((mut re, mut im), p)| {
                // The windows where the sums have them, each bin with the next.
                let mut out = vec![[0.0f32; 4]; p.bins];
                for g in &p.groups {
                    let window = g.offset..g.offset + g.len;
                    // The window's last bin stays zero; chunks may have run into it.
                    re[window.end - 1] = 0.0;
                    im[window.end - 1] = 0.0;
                    double(&re[window.clone()], &im[window.clone()], &mut out[window]);
                }
                out
            })
            .collect();
        leaves
            .into_par_iter()
            .zip(planned.into_par_iter().zip(doubled.par_iter()))
            .map(|(leaf, (p, merged))| {
                let mine: Vec<Source<'_>> = p
                    .plan
                    .into_iter()
                    .map(|q| match q {
                        Planned::Keep(i) => sources[i],
                        Planned::Merged(g) => {
                            let g = &p.groups[g];
                            Source {
                                xi: g.xi,
                                xd: g.xd,
                                start: g.start,
                                data: &merged[g.offset..g.offset + g.len],
                                re: &[],
                                im: &[],
                            }
                        }
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
    #[inline(always)]
    fn merge(&self, b: &Block, sources: &[Source<'_>], points: &Points) -> LeafPlan {
        if self.tolerance <= 0.0 {
            // No merges: every source kept, backprojected with the leaf's arithmetic.
            return LeafPlan {
                groups: Vec::new(),
                members: vec![Member::KEPT; sources.len()],
                plan: (0..sources.len()).map(Planned::Keep).collect(),
                bins: 0,
            };
        }
        let v = self.centre(b);
        let (half, diagonal) = self.half_extents(b);
        // Cells whose gradients differ by up to half the tolerance over the box's
        // half-diagonal: the other half is left to the position of k within its cell,
        // and to the quadratic and cubic terms.
        let cell = 0.5 * self.tolerance / diagonal.max(f64::MIN_POSITIVE);
        // Every pair's legs from v, in loops over the points' coordinates that the
        // compiler vectorises: the path length at v and the gradient's cell along x, y
        // and z. |k| ≤ 2, so each cell number fits 21 bits for cells down to 2⁻¹⁸;
        // finer cells than that merge nothing anyway.
        let n = sources.len();
        let (mut di, mut dd) = (vec![0.0f64; n], vec![0.0f64; n]);
        let (mut inv_i, mut inv_d) = (vec![0.0f64; n], vec![0.0f64; n]);
        let mut cells: [Vec<u32>; 3] = std::array::from_fn(|_| vec![0u32; n]);
        let inv_cell = 1.0 / cell;
        let [cx, cy, cz] = &mut cells;
        let [ix, iy, iz] = &points.xi;
        let [dx, dy, dz] = &points.xd;
        for i in 0..n {
            let (ax, ay, az) = (v.x - ix[i], v.y - iy[i], v.z - iz[i]);
            let (bx, by, bz) = (v.x - dx[i], v.y - dy[i], v.z - dz[i]);
            let a = (ax * ax + ay * ay + az * az).sqrt().max(f64::MIN_POSITIVE);
            let b = (bx * bx + by * by + bz * bz).sqrt().max(f64::MIN_POSITIVE);
            let (ra, rb) = (1.0 / a, 1.0 / b);
            let q = |c: f64| ((c + 2.0) * inv_cell).floor().clamp(0.0, 2_097_151.0) as u32;
            cx[i] = q(ax * ra + bx * rb);
            cy[i] = q(ay * ra + by * rb);
            cz[i] = q(az * ra + bz * rb);
            di[i] = a;
            dd[i] = b;
            inv_i[i] = ra;
            inv_d[i] = rb;
        }
        let legs = |i: u32| {
            let i = i as usize;
            Legs {
                ui: (v - DVec3::new(ix[i], iy[i], iz[i])) * inv_i[i],
                di: di[i],
                ud: (v - DVec3::new(dx[i], dy[i], dz[i])) * inv_d[i],
                dd: dd[i],
                inv_i: inv_i[i],
                inv_d: inv_d[i],
            }
        };
        let mut out = LeafPlan {
            groups: Vec::new(),
            members: vec![Member::KEPT; sources.len()],
            plan: Vec::with_capacity(sources.len()),
            bins: 0,
        };
        let everyone: Vec<u32> = (0..n as u32).collect();
        let mut apart = Vec::new();
        let leaf = (v, half, diagonal);
        self.merge_cells(&everyone, &cells, &legs, sources, leaf, &mut out, &mut apart);
        out.plan.extend(apart.iter().map(|&i| Planned::Keep(i as usize)));
        out
    }

    /// Groups the sources `ids` by their gradients' `cells` (one entry per id) and
    /// plans the merge of each group into `out`; the sources no merge takes are
    /// pushed to `apart`. The members a merge would take past the tolerance stay
    /// apart, and the rest are tried again about their own mean, up to
    /// [`MERGE_ROUNDS`] times.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn merge_cells(
        &self,
        ids: &[u32],
        cells: &[Vec<u32>; 3],
        legs: &impl Fn(u32) -> Legs,
        sources: &[Source<'_>],
        (v, half, diagonal): (DVec3, DVec3, f64),
        out: &mut LeafPlan,
        apart: &mut Vec<u32>,
    ) {
        let order = group_order(cells);
        let same = |a: u32, b: u32| (0..3).all(|c| cells[c][a as usize] == cells[c][b as usize]);
        let mut members = Vec::new();
        for group in order.chunk_by(|&a, &b| same(a, b)) {
            if group.len() == 1 {
                apart.push(ids[group[0] as usize]);
                continue;
            }
            members.clear();
            members.extend(group.iter().map(|&j| {
                let i = ids[j as usize];
                (i, legs(i))
            }));
            for _ in 0..MERGE_ROUNDS {
                let n = members.len() as f64;
                let xi = members
                    .iter()
                    .map(|&(i, _)| sources[i as usize].xi)
                    .sum::<DVec3>()
                    / n;
                let xd = members
                    .iter()
                    .map(|&(i, _)| sources[i as usize].xd)
                    .sum::<DVec3>()
                    / n;
                let r = Legs::at(v, xi, xd);
                let before = members.len();
                members.retain(|(i, g)| {
                    let fits = error_bound(g, &r, half, diagonal) <= self.tolerance;
                    if !fits {
                        apart.push(*i);
                    }
                    fits
                });
                if members.len() == before {
                    self.merge_group(&members, (xi, xd, &r), sources, diagonal, out);
                    members.clear();
                    break;
                }
                if members.len() < 2 {
                    break;
                }
            }
            // Out of rounds, or one left: what is left stays apart.
            apart.extend(members.iter().map(|&(i, _)| i));
        }
    }

    /// The box's half extents between its outermost voxel centres, and their length.
    fn half_extents(&self, b: &Block) -> (DVec3, f64) {
        let voxel = self.grid.voxel();
        let half = DVec3::from_array(std::array::from_fn(|a| {
            0.5 * (b.hi[a] - b.lo[a] - 1) as f64 * voxel[a]
        }));
        (half, half.length())
    }

    /// Plans the merge of `members` (each within the tolerance of the representative
    /// `r` at their mean points `xi`, `xd`) into `out`: its window and the members'
    /// taps.
    #[inline(always)]
    fn merge_group(
        &self,
        members: &[(u32, Legs)],
        (xi, xd, r): (DVec3, DVec3, &Legs),
        sources: &[Source<'_>],
        diagonal: f64,
        out: &mut LeafPlan,
    ) {
        let kr = r.k();
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
        // e^{−iφ}: the second tap's phase is the first's less φ.
        let back = self.turns[TURN_STEPS];
        let offset = out.bins;
        for (i, g) in members {
            let (i, s) = (*i, &sources[*i as usize]);
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
            let turn = self.turn(t);
            let (a0, a1) = (a * (1.0 - t), a * t);
            // A member more than 2³¹ bins off its histogram reads none of it, clamped
            // or not.
            let base = (start + m as isize - s.start).clamp(i32::MIN as isize, i32::MAX as isize);
            out.members[i as usize] = Member {
                offset,
                len,
                base: base as i32,
                c0: [(a0 * turn[0]) as f32, (a0 * turn[1]) as f32],
                c1: {
                    let [x, y] = turn;
                    let [bx, by] = back;
                    [(a1 * (x * bx - y * by)) as f32, (a1 * (x * by + y * bx)) as f32]
                },
            };
        }
        out.plan.push(Planned::Merged(out.groups.len()));
        out.groups.push(GroupPlan {
            xi,
            xd,
            start,
            len,
            offset,
        });
        out.bins += len + CHUNK;
    }

    /// The quadratic models of source `s`'s two legs over a leaf with centre `v`
    /// whose voxels lie within `diagonal` of it, where their errors together stay
    /// within [`QUADRATIC_ERROR`]; `None` (the exact arithmetic) where they may not.
    fn quadratic_legs(&self, v: DVec3, diagonal: f64, s: &Source<'_>) -> Option<[LegModel; 2]> {
        self.legs_modelled(v, diagonal, s.xi, s.xd)
            .then(|| [LegModel::at(v, s.xi), LegModel::at(v, s.xd)])
    }

    /// Whether a pair at `xi`, `xd` takes the quadratic leg models on a leaf with
    /// centre `v` and half-diagonal `diagonal` ([`Tree::quadratic_legs`]).
    fn legs_modelled(&self, v: DVec3, diagonal: f64, xi: DVec3, xd: DVec3) -> bool {
        quadratic_error(v.distance(xi), diagonal) + quadratic_error(v.distance(xd), diagonal)
            <= self.quadratic_tolerance
    }

    /// The leaf's arithmetic: every source, every voxel, the path length from the
    /// legs' quadratic models where they are within their tolerance, else exact.
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
    fn run<Q: crate::simd::Quad>(self, q: Q) {
        let LeafWork {
            tree,
            block: b,
            sources,
            out,
        } = self;
        let (min, voxel) = (tree.grid.min(), tree.grid.voxel());
        let coord = |a: usize, i: usize| (min[a] + (i as f64 + 0.5) * voxel[a]) as f32;
        // The leaf's voxels in the output's order (x fastest), as one run: a leaf's
        // rows are a few voxels long, too short to vectorise one by one.
        let n = b.len();
        let (mut xs, mut ys, mut zs) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
        for iz in b.lo[2]..b.hi[2] {
            for iy in b.lo[1]..b.hi[1] {
                for ix in b.lo[0]..b.hi[0] {
                    xs.push(coord(0, ix));
                    ys.push(coord(1, iy));
                    zs.push(coord(2, iz));
                }
            }
        }
        let (mut index, mut gain) = (vec![0.0f32; n], vec![1.0f32; n]);
        let mut bin = vec![0i32; n];
        let (mut w0, mut w1) = (vec![0.0f32; n], vec![0.0f32; n]);
        // The same voxels as offsets from the leaf's centre, and their squared
        // lengths, for the legs' quadratic models.
        let v = tree.centre(b);
        let (half, diagonal) = tree.half_extents(b);
        let offsets = |c: &[f32], a: usize| {
            c.iter()
                .map(|&x| (f64::from(x) - v[a]) as f32)
                .collect::<Vec<_>>()
        };
        let (ox, oy, oz) = (offsets(&xs, 0), offsets(&ys, 1), offsets(&zs, 2));
        let o2: Vec<f32> = ox
            .iter()
            .zip(&oy)
            .zip(&oz)
            .map(|((x, y), z)| x * x + y * y + z * z)
            .collect();
        debug_assert!(half.max_element() <= diagonal);
        let inv_w = (1.0 / tree.axis.width) as f32;
        // The bins a source's voxels read lie within its path length at the centre,
        // less or more the two legs' change over the half-diagonal.
        let reach = 2.0 * diagonal / tree.axis.width + 2.0;
        for (i, s) in sources.iter().enumerate() {
            // The next source's bins, asked for while this one is backprojected:
            // every source's histogram lies elsewhere in memory.
            if let Some(next) = sources.get(i + 1) {
                let centre = tree.index(v.distance(next.xi) + v.distance(next.xd)) - next.start as f64;
                let lo = (centre - reach).max(0.0) as usize;
                let hi = ((centre + reach).max(0.0) as usize + 1).min(next.data.len());
                if lo < hi {
                    q.prefetch_slice(&next.data[lo..hi]);
                }
            }
            let (xi, xd) = (s.xi.as_vec3(), s.xd.as_vec3());
            // The local fractional index is path·inv_w − offset.
            let offset = (s.start as f64 - tree.index(0.0)) as f32;
            let top = (s.data.len() - 1) as f32;
            let lanes = index.iter_mut().zip(gain.iter_mut());
            if let Some([qi, qd]) = tree.quadratic_legs(v, diagonal, s) {
                // Each leg's length from its quadratic model about the centre: no
                // square root, the same falloff weight.
                let offsets = ox.iter().zip(&oy).zip(&oz).zip(&o2);
                for ((f, g), (((&x, &y), &z), &r2)) in lanes.zip(offsets) {
                    let ri = qi.length(x, y, z, r2);
                    let rd = qd.length(x, y, z, r2);
                    let path = ri + rd;
                    *f = (path * inv_w - offset).max(0.0).min(top);
                    *g = (4.0 * ri * rd) / (path * path).max(f32::MIN_POSITIVE);
                }
            } else {
                // The exact path's arithmetic (`path_row`), voxel by voxel.
                for ((f, g), ((&x, &y), &z)) in lanes.zip(xs.iter().zip(&ys).zip(&zs)) {
                    let byi = (z - xi.z) * (z - xi.z) + (y - xi.y) * (y - xi.y);
                    let byd = (z - xd.z) * (z - xd.z) + (y - xd.y) * (y - xd.y);
                    let ri = (byi + (x - xi.x) * (x - xi.x)).sqrt();
                    let rd = (byd + (x - xd.x) * (x - xd.x)).sqrt();
                    let path = ri + rd;
                    *f = (path * inv_w - offset).max(0.0).min(top);
                    // 0, not NaN, for a voxel on a confocal relay point.
                    *g = (4.0 * ri * rd) / (path * path).max(f32::MIN_POSITIVE);
                }
            }
            super::falloff_power(&mut gain, tree.falloff);
            super::weights_row(&index, &gain, &mut bin, (&mut w0, &mut w1));
            // The bins the leaf reads (each with the next) are a few dozen at most on
            // a small leaf: then they are one window, read from registers.
            let (lo, hi) = bin
                .iter()
                .fold((i32::MAX, i32::MIN), |(lo, hi), &j| (lo.min(j), hi.max(j)));
            if hi.saturating_sub(lo) < WINDOW as i32 - 1 {
                let last = s.data.len() - 1;
                let mut window = [[0.0f32; WINDOW]; 2];
                for j in 0..=(hi - lo + 1) as usize {
                    // Bin b, or past the last one the last one's next.
                    let b = lo as usize + j;
                    let (re, im) = match s.data.get(b) {
                        Some(d) => (d[0], d[1]),
                        None => (s.data[last][2], s.data[last][3]),
                    };
                    (window[0][j], window[1][j]) = (re, im);
                }
                bin.iter_mut().for_each(|j| *j -= lo);
                q.window_add(&window, (hi - lo + 2) as usize, &bin, (&w0, &w1), out);
            } else {
                super::gather_row(out, &bin, (&w0, &w1), s.data);
            }
        }
    }
}

/// One leg's length |x − p| over a leaf as its Taylor polynomial about the leaf's
/// centre v, to the second order: with δ = x − v, d = |v − p| and u = (v − p)/d,
/// |x − p| ≈ d + u·δ + (|δ|² − (u·δ)²)/(2d). The remainder is the third-order term,
/// at most |δ|³/(2 (d − |δ|)²) ([`quadratic_error`]).
#[derive(Clone, Copy, Debug)]
struct LegModel {
    d: f32,
    u: [f32; 3],
    /// 1/(2d).
    curvature: f32,
}

impl LegModel {
    fn at(v: DVec3, p: DVec3) -> Self {
        let a = v - p;
        let d = a.length();
        let u = a / d;
        Self {
            d: d as f32,
            u: [u.x as f32, u.y as f32, u.z as f32],
            curvature: (0.5 / d) as f32,
        }
    }

    /// The model at offset (x, y, z) from the centre, whose squared length is `r2`.
    #[inline(always)]
    fn length(&self, x: f32, y: f32, z: f32, r2: f32) -> f32 {
        let t = self.u[0] * x + self.u[1] * y + self.u[2] * z;
        self.d + t + self.curvature * (r2 - t * t)
    }
}

/// The bound on a [`LegModel`]'s error anywhere within `diagonal` of the centre, for
/// a leg `d` long there: the Taylor remainder |δ|³/(2 (d − |δ|)²) at |δ| = `diagonal`
/// (a leg's third derivatives are at most 3/|x − p|², and /6); infinite for a point
/// within twice `diagonal` of the centre.
fn quadratic_error(d: f64, diagonal: f64) -> f64 {
    if d <= 2.0 * diagonal {
        return f64::INFINITY;
    }
    let near = d - diagonal;
    diagonal.powi(3) / (2.0 * near * near)
}

/// The largest path-length error the leaves' quadratic models may leave, in
/// wavelengths of the phasor: λ/64, a phase error of at most 0.1 rad, under
/// the merges' own (`path-error`, λ/4 by default).
const QUADRATIC_ERROR: f64 = 1.0 / 64.0;

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
    let hessian = (p.inv_i - r.inv_i).abs()
        + 2.0 * p.ui.distance(r.ui) * p.inv_i.max(r.inv_i)
        + (p.inv_d - r.inv_d).abs()
        + 2.0 * p.ud.distance(r.ud) * p.inv_d.max(r.inv_d);
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

/// A merged group: its representative, and its window (global start, length with the
/// zero bin at each end, and where it starts in the leaf's buffer of windows).
struct GroupPlan {
    xi: DVec3,
    xd: DVec3,
    start: isize,
    len: usize,
    /// Where the window starts in the leaf's buffers, which leave CHUNK bins of slack
    /// after each window.
    offset: usize,
}

/// A member of a group: where its group's window lies in the leaf's buffers (its
/// start, and its length without the slack), the offset from the window's index to
/// its own histogram's, and the two taps. What the pass that adds the members reads
/// of their groups is here, so that it reads nothing else of the plan.
#[derive(Clone, Copy)]
struct Member {
    offset: usize,
    len: usize,
    base: i32,
    c0: [f32; 2],
    c1: [f32; 2],
}

impl Member {
    /// A source kept apart, in no group.
    const KEPT: Member = Member {
        offset: usize::MAX,
        len: 0,
        base: 0,
        c0: [0.0; 2],
        c1: [0.0; 2],
    };

    /// The member's group's window in the leaf's buffers, with the slack after it;
    /// `None` for a source kept apart.
    #[inline(always)]
    fn window(&self) -> Option<std::ops::Range<usize>> {
        (self.offset != usize::MAX).then(|| self.offset..self.offset + self.len + CHUNK)
    }
}

/// A leaf's planned merges: the groups, each source's member ([`Member::KEPT`] for a
/// source kept apart), the leaf's sources in order, and the bins of all its groups'
/// windows.
struct LeafPlan {
    groups: Vec<GroupPlan>,
    members: Vec<Member>,
    plan: Vec<Planned>,
    bins: usize,
}

/// The order that puts sources of one cell next to each other, cells in the order of
/// their x, then y, then z numbers, and the sources of a cell in index order. A
/// counting sort over the cells the gradients span, where they are few enough;
/// otherwise a comparison sort.
fn group_order(cells: &[Vec<u32>; 3]) -> Vec<u32> {
    let n = cells[0].len();
    let lo: [u32; 3] = std::array::from_fn(|a| cells[a].iter().copied().min().unwrap_or(0));
    let hi: [u32; 3] = std::array::from_fn(|a| cells[a].iter().copied().max().unwrap_or(0));
    let span: [usize; 3] = std::array::from_fn(|a| (hi[a] - lo[a]) as usize + 1);
    let total = span[0].saturating_mul(span[1]).saturating_mul(span[2]);
    if total > 8 * n.max(1024) {
        let mut keyed: Vec<(u64, u32)> = (0..n)
            .map(|i| {
                let key = (cells[0][i] as u64) << 42 | (cells[1][i] as u64) << 21 | cells[2][i] as u64;
                (key, i as u32)
            })
            .collect();
        keyed.sort_unstable();
        return keyed.into_iter().map(|(_, i)| i).collect();
    }
    let at = |i: usize| {
        ((cells[0][i] - lo[0]) as usize * span[1] + (cells[1][i] - lo[1]) as usize) * span[2]
            + (cells[2][i] - lo[2]) as usize
    };
    let mut count = vec![0u32; total + 1];
    for i in 0..n {
        count[at(i) + 1] += 1;
    }
    for i in 1..count.len() {
        count[i] += count[i - 1];
    }
    let mut order = vec![0u32; n];
    for i in 0..n {
        let k = &mut count[at(i)];
        order[*k as usize] = i as u32;
        *k += 1;
    }
    order
}

/// The pairs' points, each coordinate in an array of its own for the loops that the
/// compiler vectorises.
struct Points {
    xi: [Vec<f64>; 3],
    xd: [Vec<f64>; 3],
}

impl Points {
    fn of(sources: &[Source<'_>]) -> Self {
        let coord = |f: &dyn Fn(&Source<'_>) -> f64| sources.iter().map(f).collect::<Vec<f64>>();
        Points {
            xi: [coord(&|s| s.xi.x), coord(&|s| s.xi.y), coord(&|s| s.xi.z)],
            xd: [coord(&|s| s.xd.x), coord(&|s| s.xd.y), coord(&|s| s.xd.z)],
        }
    }
}

/// [`Tree::merge`] for one leaf, under [`crate::simd::dispatch`].
struct Plan<'a, 'b> {
    tree: &'b Tree<'b>,
    block: &'b Block,
    sources: &'b [Source<'a>],
    points: &'b Points,
}

impl crate::simd::Work for Plan<'_, '_> {
    type Output = LeafPlan;

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, _: Q) -> LeafPlan {
        self.tree.merge(self.block, self.sources, self.points)
    }
}

/// The pass of [`Tree::node`] that adds every member into its group's window, source
/// after source and, for each, leaf after leaf, under [`crate::simd::dispatch`].
struct Accumulate<'a, 'b> {
    planned: &'b [LeafPlan],
    sources: &'b [Source<'a>],
    data: &'b mut [(Vec<f32>, Vec<f32>)],
}

impl crate::simd::Work for Accumulate<'_, '_> {
    type Output = ();

    #[inline(always)]
    fn run<Q: crate::simd::Quad>(self, q: Q) {
        // Each source's windows, and the groups' windows they are added into, lie
        // apart in memory, where the CPU's own prefetcher does not look: the ones a
        // few sources ahead are asked for while this one is added.
        let ahead = |i: usize, data: &[(Vec<f32>, Vec<f32>)]| {
            let Some(s) = self.sources.get(i) else {
                return;
            };
            let (mut lo, mut hi) = (isize::MAX, isize::MIN);
            for (p, (re, im)) in self.planned.iter().zip(data) {
                let member = &p.members[i];
                if let Some(window) = member.window() {
                    let base = member.base as isize;
                    lo = lo.min(base + 1);
                    hi = hi.max(base + window.len() as isize);
                    q.prefetch_slice(&re[window.clone()]);
                    q.prefetch_slice(&im[window]);
                }
            }
            let (lo, hi) = (lo.max(0) as usize, (hi.max(0) as usize).min(s.re.len()));
            if lo < hi {
                q.prefetch_slice(&s.re[lo..hi]);
                q.prefetch_slice(&s.im[lo..hi]);
            }
        };
        for (i, s) in self.sources.iter().enumerate() {
            ahead(i + PREFETCH_AHEAD, self.data);
            for (p, (re, im)) in self.planned.iter().zip(self.data.iter_mut()) {
                let member = &p.members[i];
                let Some(window) = member.window() else {
                    continue;
                };
                add_shifted(&mut re[window.clone()], &mut im[window], member, s);
            }
        }
    }
}

/// Adds `member` (whose histogram is `s`'s) into a group's window `(re, im)`:
/// window index o reads the member's o + base and the next. Only the interior (the
/// two ends stay zero) and what the member holds.
#[inline(always)]
fn add_shifted(re: &mut [f32], im: &mut [f32], member: &Member, s: &Source<'_>) {
    let Member { base, c0, c1, .. } = *member;
    let base = base as isize;
    let o_lo = (-base).max(1);
    let o_hi = (s.data.len() as isize - 2 - base).min(re.len() as isize - CHUNK as isize - 2);
    if o_hi < o_lo {
        return;
    }
    // Whole chunks of CHUNK bins, which compile to full-width vector operations: the
    // window has CHUNK bins of slack after its end and the histogram CHUNK zeros after
    // its own, so a chunk that runs past either reads zeros or writes into the slack
    // (cleared by the caller).
    let (mut o, mut i) = (o_lo as usize, (base + o_lo) as usize);
    while o as isize <= o_hi {
        let h0r: &[f32; CHUNK] = s.re[i..i + CHUNK].try_into().expect("a chunk");
        let h1r: &[f32; CHUNK] = s.re[i + 1..i + 1 + CHUNK].try_into().expect("a chunk");
        let h0i: &[f32; CHUNK] = s.im[i..i + CHUNK].try_into().expect("a chunk");
        let h1i: &[f32; CHUNK] = s.im[i + 1..i + 1 + CHUNK].try_into().expect("a chunk");
        let dr: &mut [f32; CHUNK] = (&mut re[o..o + CHUNK]).try_into().expect("a chunk");
        let di: &mut [f32; CHUNK] = (&mut im[o..o + CHUNK]).try_into().expect("a chunk");
        for k in 0..CHUNK {
            dr[k] += c0[0] * h0r[k] - c0[1] * h0i[k] + c1[0] * h1r[k] - c1[1] * h1i[k];
            di[k] += c0[0] * h0i[k] + c0[1] * h0r[k] + c1[0] * h1i[k] + c1[1] * h1r[k];
        }
        o += CHUNK;
        i += CHUNK;
    }
}

/// How many sources ahead [`Accumulate`] asks for the memory it will read.
const PREFETCH_AHEAD: usize = 8;

/// The bins [`add_shifted`] adds at a time.
const CHUNK: usize = 16;

/// A window as the leaves read it, each bin with the next, into `out` (as long).
fn double(re: &[f32], im: &[f32], out: &mut [[f32; 4]]) {
    for (o, at) in out.iter_mut().enumerate().take(re.len()) {
        let next = |v: &[f32]| v.get(o + 1).copied().unwrap_or_default();
        *at = [re[o], im[o], next(re), next(im)];
    }
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
    shape: [usize; 3],
) -> (Vec<[f32; 2]>, TreeStats) {
    // Each histogram with one zero bin before and after, each bin with the next.
    let complex = super::doubled::<2, 4>(&hists);
    // And the real and imaginary parts apart, with the same zero bin at each end.
    // All of them in one allocation, each part a zero bin, the bins, a zero bin and
    // CHUNK zeros for `add_shifted`'s chunks: the merges read a window of every
    // histogram in turn, and histograms side by side in memory keep those reads on
    // few pages.
    let stride = hists.first().map_or(0, |h| h.len() / 2) + CHUNK + 2;
    let mut split = vec![0.0f32; 2 * stride * hists.len()];
    split
        .par_chunks_mut(2 * stride)
        .zip(hists.par_iter())
        .for_each(|(out, h)| {
            let (re, im) = out.split_at_mut(stride);
            for (b, pair) in h.chunks_exact(2).enumerate() {
                re[b + 1] = pair[0];
                im[b + 1] = pair[1];
            }
        });
    // The two layouts replace the histograms.
    drop(hists);
    let sources: Vec<Source<'_>> = set
        .pairs()
        .iter()
        .zip(complex.iter().zip(split.chunks_exact(2 * stride)))
        .map(|(p, (data, parts))| {
            let (re, im) = parts.split_at(stride);
            Source {
                xi: p.xi,
                xd: p.xd,
                start: -1,
                data,
                re,
                im,
            }
        })
        .collect();
    let tree = Tree::new(grid, set.axis(), lead, falloff, wavelength, tolerance, shape);
    let root = Block {
        lo: [0; 3],
        hi: grid.shape,
    };
    let leaves = tree.node(root, &sources, &Points::of(&sources));
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

/// The times a group is tried again about its members' mean once those a merge would
/// take past the tolerance are taken out.
const MERGE_ROUNDS: usize = 3;

/// Leaves of each shape whose merges [`choose`] plans, at most.
const SAMPLE_LEAVES: usize = 16;

/// The steps of the R₃ sequence that places [`choose`]'s sample: 1/g, 1/g² and 1/g³,
/// g = 1.3247… the real root of g³ = g + 1.
const R3: [f64; 3] = [
    0.754_877_666_246_692_7,
    0.569_840_290_998_053_3,
    0.430_159_709_001_946_7,
];

/// The hierarchy's leaf shape for a backprojection, what its sample saw, and its
/// predicted cost.
#[derive(Clone, Copy, Debug)]
pub(super) struct Choice {
    /// The leaves' voxels along x, y and z.
    pub shape: [usize; 3],
    /// The share of the pairs a leaf still backprojects after its merges: the mean over
    /// a sample of up to [`SAMPLE_LEAVES`] leaves spread evenly through the volume.
    pub share: f64,
    /// The predicted time against the exact path's.
    pub cost: f64,
    /// Whether the leaves merge pairs (within the path-length tolerance); without, they
    /// backproject every pair with their own arithmetic, as exact as the exact path's
    /// to within the legs' quadratic models ([`QUADRATIC_ERROR`]).
    pub merges: bool,
}

/// [`choose`]'s two answers: the leaves of least predicted cost with merges, and
/// without.
#[derive(Clone, Copy, Debug)]
pub(super) struct Choices {
    /// With merges within the tolerance.
    pub merged: Choice,
    /// Every pair backprojected at every voxel, by the leaves' arithmetic.
    pub unmerged: Choice,
}

/// The leaf shapes of least predicted cost, with merges and without: each shape of
/// [`EDGES`] along each axis plans the merges of a sample of its leaves, and the cost
/// model ([`LeafCosts`]) weighs its leaves' visits to every pair against the sources
/// they still backproject (all of them, without merges). Planning reads no histogram,
/// so this costs about a hundredth of the backprojection it decides on.
pub(super) fn choose(set: &TransientSet, grid: &VolumeGrid, wavelength: f64, tolerance: f64) -> Choices {
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
    let points = Points::of(&sources);
    let mut shapes: Vec<[usize; 3]> = Vec::new();
    for ez in EDGES {
        for ey in EDGES {
            for ex in EDGES {
                let shape = [ex, ey, ez];
                let shape: [usize; 3] = std::array::from_fn(|a| shape[a].min(grid.shape[a]).max(1));
                if !shapes.contains(&shape) {
                    shapes.push(shape);
                }
            }
        }
    }
    let costs = if crate::simd::avx512() {
        WITH_AVX512
    } else if crate::simd::avx2() {
        WITH_AVX2
    } else {
        BASELINE
    };
    let mut best: Option<Choice> = None;
    let mut best_unmerged: Option<Choice> = None;
    for shape in shapes {
        // Planning reads neither the padding nor the falloff's exponent.
        let tree = Tree::new(grid, set.axis(), 0, 1.0, wavelength, tolerance, shape);
        let tiles: [usize; 3] = std::array::from_fn(|a| grid.shape[a] / shape[a]);
        let count = tiles.iter().product::<usize>();
        let n = count.min(SAMPLE_LEAVES);
        let (share, modelled, all_modelled) = if sources.is_empty() || n == 0 {
            (1.0, 0.0, 0.0)
        } else {
            let (kept, quadratic, all_quadratic): (usize, usize, usize) = (0..n)
                .into_par_iter()
                .map(|i| {
                    // The R₃ low-discrepancy sequence (steps 1/g, 1/g², 1/g³ with
                    // g³ = g + 1) spreads the sample along every axis at once.
                    let lo: [usize; 3] = std::array::from_fn(|a| {
                        let u = (0.5 + (i + 1) as f64 * R3[a]).fract();
                        ((u * tiles[a] as f64) as usize).min(tiles[a] - 1) * shape[a]
                    });
                    let leaf = Block {
                        lo,
                        hi: std::array::from_fn(|a| lo[a] + shape[a]),
                    };
                    let plan = tree.merge(&leaf, &sources, &points);
                    // How many of the leaf's sources take the quadratic leg models.
                    let (v, (_, diagonal)) = (tree.centre(&leaf), tree.half_extents(&leaf));
                    let quadratic = plan
                        .plan
                        .iter()
                        .filter(|p| {
                            let (xi, xd) = match **p {
                                Planned::Keep(i) => (sources[i].xi, sources[i].xd),
                                Planned::Merged(g) => (plan.groups[g].xi, plan.groups[g].xd),
                            };
                            tree.legs_modelled(v, diagonal, xi, xd)
                        })
                        .count();
                    // And how many of all its pairs would, unmerged.
                    let all = sources
                        .iter()
                        .filter(|s| tree.legs_modelled(v, diagonal, s.xi, s.xd))
                        .count();
                    (plan.plan.len(), quadratic, all)
                })
                .reduce(|| (0, 0, 0), |a, b| (a.0 + b.0, a.1 + b.1, a.2 + b.2));
            (
                kept as f64 / (n * sources.len()) as f64,
                quadratic as f64 / kept.max(1) as f64,
                all_quadratic as f64 / (n * sources.len()) as f64,
            )
        };
        let voxels = shape.iter().product::<usize>() as f64;
        let predict = |share: f64, modelled: f64| {
            let per_source = costs.modelled * modelled + costs.leaf * (1.0 - modelled);
            (costs.visit / voxels + per_source * share) / costs.exact
        };
        let cost = predict(share, modelled);
        if best.is_none_or(|b| cost < b.cost) {
            best = Some(Choice {
                shape,
                share,
                cost,
                merges: true,
            });
        }
        // Without merges a leaf has no cells, plans or shifted windows to make; its
        // visits are still counted at the merging figure, an upper bound (not measured
        // apart).
        let cost = predict(1.0, all_modelled);
        if best_unmerged.is_none_or(|b| cost < b.cost) {
            best_unmerged = Some(Choice {
                shape,
                share: 1.0,
                cost,
                merges: false,
            });
        }
    }
    let none = |merges| Choice {
        shape: grid.shape,
        share: 1.0,
        cost: f64::INFINITY,
        merges,
    };
    Choices {
        merged: best.unwrap_or(none(true)),
        unmerged: best_unmerged.unwrap_or(none(false)),
    }
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
    fn a_legs_quadratic_model_stays_within_its_bound() {
        // Leaves 5 mm to 16 cm across at 0.05–1.5 m from a relay point, in every
        // direction: the model's error at the box's corners and at random voxels,
        // against `quadratic_error` at the box's half-diagonal. The model runs in f32,
        // as the leaves do; its rounding (about 1e-7 of the leg) is added to the bound.
        let mut rng = ChaCha8Rng::seed_from_u64(11);
        let (mut modelled, mut ratios) = (0, Vec::new());
        for _ in 0..2000 {
            let p = DVec3::new(rng.random_range(-0.5..0.5), rng.random_range(-0.5..0.5), 0.0);
            let dir = DVec3::new(
                rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0),
                rng.random_range(0.05..1.0),
            )
            .normalize();
            let v = p + dir * rng.random_range(0.05..1.5);
            let half = DVec3::new(
                rng.random_range(0.0025..0.08),
                rng.random_range(0.0025..0.08),
                rng.random_range(0.0025..0.08),
            );
            let diagonal = half.length();
            let bound = quadratic_error(v.distance(p), diagonal);
            if !bound.is_finite() {
                assert!(v.distance(p) <= 2.0 * diagonal, "no bound at {} m", v.distance(p));
                continue;
            }
            modelled += 1;
            let model = LegModel::at(v, p);
            let rounding = 2e-7 * (v.distance(p) + diagonal);
            let mut worst = 0.0f64;
            let corners = (0..8).map(|c| {
                DVec3::new(
                    if c & 1 == 0 { -1.0 } else { 1.0 },
                    if c & 2 == 0 { -1.0 } else { 1.0 },
                    if c & 4 == 0 { -1.0 } else { 1.0 },
                )
            });
            let inside: Vec<DVec3> = (0..50)
                .map(|_| {
                    DVec3::new(
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                        rng.random_range(-1.0..1.0),
                    )
                })
                .collect();
            for u in corners.chain(inside) {
                let d = (u * half).as_vec3();
                let got = f64::from(model.length(d.x, d.y, d.z, d.length_squared()));
                worst = worst.max((got - (v + d.as_dvec3()).distance(p)).abs());
            }
            assert!(
                worst <= bound + rounding,
                "the model is {worst} m off, over its bound {bound} m (leg {} m, half {half})",
                v.distance(p)
            );
            if bound > 1e-5 {
                ratios.push(bound / worst);
            }
        }
        assert!(modelled > 1500, "only {modelled} boxes were far enough to model");
        // Tight enough to be worth having: the median bound within a few times the
        // worst error where the error is above the rounding.
        ratios.sort_by(f64::total_cmp);
        let median = ratios[ratios.len() / 2];
        assert!(
            median < 6.0,
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
        let choices = choose(&set, &grid, lambda, 0.25 * lambda);
        let choice = choices.merged;
        // Lit at one point, merges pay: `auto` takes them over leaves without.
        assert!(
            choice.merges
                && !choices.unmerged.merges
                && choices.unmerged.share == 1.0
                && choice.cost <= super::super::AUTO_MAX_COST * choices.unmerged.cost,
            "{choices:?}"
        );
        let (sums, stats) =
            backproject_tree(&set, &grid, 1.0, hists, lead, lambda, 0.25 * lambda, choice.shape);
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
        let whole = per_leaf / set.len() as f64;
        assert!(
            (choice.share - whole).abs() < 0.05 && choice.cost <= super::super::AUTO_MAX_COST,
            "{choice:?}, the whole volume's share {whole}"
        );
        // Both points free: fewer merges on every leaf shape, so a dearer hierarchy.
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
        let free_choice = choose(&free, &grid, lambda, 0.25 * lambda).merged;
        assert!(
            free_choice.cost > 1.5 * choice.cost,
            "both points free {free_choice:?}, one laser point {choice:?}"
        );
    }
}

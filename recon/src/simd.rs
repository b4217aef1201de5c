//! Run-time SIMD dispatch for the hot loops.
//!
//! The renderer, the synthesis and FBP are written as plain loops over slices that
//! LLVM vectorises. Built for the baseline x86-64 target, that code gets SSE2 only:
//! no FMA, no 256-bit vectors, and `floor` is a libm call. `dispatch` runs a function
//! inside a function compiled with AVX-512 (x86-64-v4) or else AVX2 and FMA (x86-64-v3)
//! enabled when the CPU has them (checked once, at run time, by `pulp`), so everything
//! inlined into it is vectorised for the machine it runs on; elsewhere it runs the same
//! function as compiled for the baseline.
//! No `unsafe` here: `pulp` proves the features are present before it calls the
//! specialised function.
//!
//! Functions called from inside it are compiled for the wider target only if
//! they are inlined into it, hence `#[inline(always)]` on the kernels' inner loops.
//! The arithmetic is the same in both builds, so results do not depend on the CPU: the
//! compiler never fuses a multiply and an add on its own, and where the kernels ask
//! for one (`mul_add`) the baseline build calls the correctly rounded software `fma`,
//! which gives the same bits as the instruction (slower, on CPUs without FMA only).
//!
//! Loops that LLVM does not vectorise well on its own (the renderer's per-bin
//! recurrences, whose state does not fit the registers in the shape it picks) are
//! written against `Lanes<N>`: four f64 lanes (`Quad`: AVX2 + FMA vectors under
//! `dispatch` on a CPU that has them, plain arrays otherwise) or eight (`Quad::oct`:
//! one AVX-512 vector, two AVX2 vectors, or an array). Every one does the same
//! IEEE operations lane by lane (`mul_add` fused in all), so they give the same bits:
//! a fit is bit for bit the same on a CPU with AVX-512, one with AVX2 only, and one
//! with neither.
use std::sync::LazyLock;

#[cfg(target_arch = "x86_64")]
static V3: LazyLock<Option<pulp::x86::V3>> =
    LazyLock::new(|| (*CEILING >= Ceiling::Avx2).then(pulp::x86::V3::try_new).flatten());
#[cfg(target_arch = "x86_64")]
static V4: LazyLock<Option<pulp::x86::V4>> = LazyLock::new(|| {
    (*CEILING >= Ceiling::Avx512)
        .then(pulp::x86::V4::try_new)
        .flatten()
});

/// The widest instruction set the hot loops may use, from `PERISCOPE_SIMD`.
static CEILING: LazyLock<Ceiling> =
    LazyLock::new(|| Ceiling::from_env(std::env::var("PERISCOPE_SIMD").ok().as_deref()));

/// How wide `dispatch` may go: the best the CPU has unless `PERISCOPE_SIMD` asks for
/// less (`avx2`, or `baseline` for the portable code), so that one machine can run and
/// time the paths a CPU without AVX-512, or without AVX2, takes. Asking for more than
/// the CPU has gets what it has. Every path gives the same bits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
enum Ceiling {
    Baseline,
    Avx2,
    Avx512,
}

impl Ceiling {
    fn from_env(value: Option<&str>) -> Self {
        match value.map(|v| v.trim().to_ascii_lowercase()).as_deref() {
            None | Some("" | "avx512" | "avx-512" | "x86-64-v4" | "native") => Self::Avx512,
            Some("avx2" | "x86-64-v3") => Self::Avx2,
            Some("baseline" | "portable" | "none") => Self::Baseline,
            Some(other) => {
                tracing::warn!(
                    value = other,
                    "PERISCOPE_SIMD is not one of avx512, avx2, baseline: using the best this CPU has"
                );
                Self::Avx512
            }
        }
    }
}

/// A unit of hot work: `run` holds the loops to compile for the wider target.
///
/// Implementations mark `run` `#[inline(always)]` so that its body is compiled inside
/// the specialised function (a closure, or a function item called through `FnOnce`,
/// is inlined only when the compiler finds it cheap, and a loop nest is not).
pub(crate) trait Work {
    /// What the work returns.
    type Output;
    /// Does the work, with `quad` the four-lane vector arithmetic of this CPU (and,
    /// through [`Quad::oct`], its eight-lane arithmetic).
    fn run<Q: Quad>(self, quad: Q) -> Self::Output;
}

/// `work` with the token `S`, for `pulp` to run inside a function compiled for `S`'s
/// instruction set.
#[cfg(target_arch = "x86_64")]
struct Op<W, S>(W, S);

#[cfg(target_arch = "x86_64")]
impl<W: Work, S: Quad> pulp::WithSimd for Op<W, S> {
    type Output = W::Output;
    #[inline(always)]
    fn with_simd<T: pulp::Simd>(self, _: T) -> W::Output {
        self.0.run(self.1)
    }
}

/// Runs `work` compiled for the best instruction set this CPU offers.
#[inline]
pub(crate) fn dispatch<W: Work>(work: W) -> W::Output {
    #[cfg(target_arch = "x86_64")]
    if let Some(simd) = *V4 {
        return pulp::Simd::vectorize(simd, Op(work, simd));
    }
    #[cfg(target_arch = "x86_64")]
    if let Some(simd) = *V3 {
        return pulp::Simd::vectorize(simd, Op(work, simd));
    }
    work.run(Portable)
}

/// The SIMD level the hot loops run at on this machine, for benchmarks and logs.
pub fn level() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    if V4.is_some() {
        return "x86-64-v4 (AVX-512)";
    }
    #[cfg(target_arch = "x86_64")]
    if V3.is_some() {
        return "x86-64-v3 (AVX2, FMA)";
    }
    "baseline"
}

/// Whether the hot loops run with AVX-512 here (where [`Quad::window_add`] reads its
/// window from registers).
pub(crate) fn avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    if V4.is_some() {
        return true;
    }
    false
}

/// Whether the hot loops run with AVX2 and FMA but not AVX-512 here.
pub(crate) fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    if V4.is_none() && V3.is_some() {
        return true;
    }
    false
}

/// `N` f64 lanes and the IEEE operations on them, lane by lane: four (an AVX2 vector)
/// or eight (an AVX-512 vector, or two AVX2 ones), or arrays of either on a CPU without
/// them. Every implementation does the same operations lane by lane (`mul_add` fused),
/// so they give the same bits.
pub(crate) trait Lanes<const N: usize>: Copy {
    /// The vector.
    type V: Copy;
    /// Every lane `x`.
    fn splat(self, x: f64) -> Self::V;
    /// The lanes from an array.
    fn load(self, a: [f64; N]) -> Self::V;
    /// The lanes as an array.
    fn store(self, v: Self::V) -> [f64; N];
    /// `a + b`.
    fn add(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a − b`.
    fn sub(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a b`.
    fn mul(self, a: Self::V, b: Self::V) -> Self::V;
    /// `a b + c`, rounded once.
    fn mul_add(self, a: Self::V, b: Self::V, c: Self::V) -> Self::V;
    /// `a / b`.
    fn div(self, a: Self::V, b: Self::V) -> Self::V;
    /// `√a`.
    fn sqrt(self, a: Self::V) -> Self::V;
    /// The nearest integer, ties to even.
    fn round(self, a: Self::V) -> Self::V;
    /// `⌊a⌋`.
    fn floor(self, a: Self::V) -> Self::V;
    /// `⌈a⌉`.
    fn ceil(self, a: Self::V) -> Self::V;
    /// The larger of `a` and `b`; `b` where `a` is NaN.
    fn max(self, a: Self::V, b: Self::V) -> Self::V;
    /// The smaller of `a` and `b`; `b` where `a` is NaN.
    fn min(self, a: Self::V, b: Self::V) -> Self::V;
    /// `2^k` for whole numbers `k` in [−1022, 1023] (anything else: unspecified bits,
    /// no panic).
    fn pow2(self, k: Self::V) -> Self::V;
    /// The lanes' total as a balanced tree of pairs, `(l₀ + l₁) + (l₂ + l₃)` and, of
    /// eight, that plus `(l₄ + l₅) + (l₆ + l₇)`: the same bits on every implementation.
    /// The vectors sum within their registers (a vector stored and read back lane by
    /// lane, three times a pulse, took 4.6 % of a fit).
    #[inline(always)]
    fn total(self, v: Self::V) -> f64 {
        pairwise(&self.store(v))
    }
}

/// `a`'s total as a balanced tree of pairs (`a.len()` a power of two).
#[inline(always)]
fn pairwise(a: &[f64]) -> f64 {
    match a {
        [x] => *x,
        _ => {
            let (lo, hi) = a.split_at(a.len() / 2);
            pairwise(lo) + pairwise(hi)
        }
    }
}

/// Four AVX lanes' total, `(l₀ + l₁) + (l₂ + l₃)`: neighbours swapped and added, then
/// the upper pair added to the lower.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn total_v3(v3: pulp::x86::V3, v: pulp::f64x4) -> f64 {
    use std::arch::x86_64::__m256d;
    let a: __m256d = pulp::cast(v);
    let a = v3.avx._mm256_add_pd(a, v3.avx._mm256_permute_pd::<0b0101>(a));
    let (lo, hi) = (
        v3.avx._mm256_castpd256_pd128(a),
        v3.avx._mm256_extractf128_pd::<1>(a),
    );
    v3.sse2._mm_cvtsd_f64(v3.sse2._mm_add_sd(lo, hi))
}

/// An instruction set's lanes: four, and eight through [`Quad::oct`].
pub(crate) trait Quad: Lanes<4> {
    /// Eight lanes of the same instruction set.
    type Oct: Lanes<8>;
    /// The eight-lane arithmetic of the same instruction set.
    fn oct(self) -> Self::Oct;

    /// A linear interpolation read from a window of [`WINDOW`] bins of two channels,
    /// for each voxel v: `out[v][c] += w0[v]·window[c][j] + w1[v]·window[c][j + 1]`
    /// with j = `bin[v]` (0 ≤ j and j + 1 < `reach` ≤ [`WINDOW`]: the window's bins
    /// from `reach` on are never read). The two products are summed, then added: the
    /// operations of FBP's gather, in its order, on every instruction set (AVX-512
    /// reads the window from registers, sixteen voxels at a time; AVX2 from as many
    /// registers as `reach` needs, eight voxels at a time; elsewhere one voxel at a
    /// time).
    #[inline(always)]
    fn window_add(
        self,
        window: &[[f32; WINDOW]; 2],
        reach: usize,
        bin: &[i32],
        w: (&[f32], &[f32]),
        out: &mut [[f32; 2]],
    ) {
        let _ = reach;
        window_add_from(window, bin, w, out, 0);
    }

    /// Asks the CPU to bring the cache line that holds `p` into its caches, for a read
    /// that follows soon: a hint, which never faults and changes no result (on
    /// x86-64 a `prefetcht0`; nothing on the portable path).
    #[inline(always)]
    fn prefetch<T>(self, p: *const T) {
        let _ = p;
    }

    /// [`Quad::prefetch`] of every cache line of `data`.
    #[inline(always)]
    fn prefetch_slice<T>(self, data: &[T]) {
        const LINE: usize = 64;
        let bytes = std::mem::size_of_val(data);
        let start = data.as_ptr().cast::<u8>();
        for at in (0..bytes).step_by(LINE) {
            self.prefetch(start.wrapping_add(at));
        }
        if bytes > 0 {
            // The last line, where the slice does not start on a line's edge.
            self.prefetch(start.wrapping_add(bytes - 1));
        }
    }
}

/// The bins of a window [`Quad::window_add`] reads: two AVX-512 registers of f32.
pub(crate) const WINDOW: usize = 32;

/// [`Quad::window_add`] from voxel `from` on, one voxel at a time.
#[inline(always)]
fn window_add_from(
    window: &[[f32; WINDOW]; 2],
    bin: &[i32],
    (w0, w1): (&[f32], &[f32]),
    out: &mut [[f32; 2]],
    from: usize,
) {
    let n = bin.len().min(w0.len()).min(w1.len()).min(out.len());
    for v in from..n {
        debug_assert!((0..WINDOW as i32 - 1).contains(&bin[v]));
        let j = (bin[v] as usize).min(WINDOW - 2);
        for (c, o) in out[v].iter_mut().enumerate() {
            *o += w0[v] * window[c][j] + w1[v] * window[c][j + 1];
        }
    }
}

/// `eˣ` within 1 ulp of `f64::exp` (tested) for `x` in [−708, 709] (clamped to it), the same bits in every
/// lane as [`exp_scalar`] gives: `x = k ln 2 + r` with `|r| ≤ ln 2 / 2` (Cody and Waite,
/// with fused multiply-adds), `eʳ` by its Taylor polynomial of degree 13 (truncation
/// below 1e-17 relative), times `2ᵏ`.
#[inline(always)]
pub(crate) fn exp<const N: usize, Q: Lanes<N>>(q: Q, x: Q::V) -> Q::V {
    let x = q.max(q.min(x, q.splat(EXP_MAX)), q.splat(EXP_MIN));
    let k = q.round(q.mul(x, q.splat(std::f64::consts::LOG2_E)));
    let minus_k = q.mul(k, q.splat(-1.0));
    let r = q.mul_add(minus_k, q.splat(LN2_HI), x);
    let r = q.mul_add(minus_k, q.splat(LN2_LO), r);
    let mut p = q.splat(EXP_TAYLOR[EXP_TAYLOR.len() - 1]);
    for &c in EXP_TAYLOR[..EXP_TAYLOR.len() - 1].iter().rev() {
        p = q.mul_add(p, r, q.splat(c));
    }
    q.mul(p, q.pow2(k))
}

/// [`exp`] for one value: the same operations, so the same bits.
#[inline(always)]
pub(crate) fn exp_scalar(x: f64) -> f64 {
    // As the lanes' `min` and `max` do: NaN becomes the upper end.
    let x = if x < EXP_MAX { x } else { EXP_MAX };
    let x = if x > EXP_MIN { x } else { EXP_MIN };
    let k = (x * std::f64::consts::LOG2_E).round_ties_even();
    let minus_k = -k;
    let r = minus_k.mul_add(LN2_HI, x);
    let r = minus_k.mul_add(LN2_LO, r);
    let mut p = EXP_TAYLOR[EXP_TAYLOR.len() - 1];
    for &c in EXP_TAYLOR[..EXP_TAYLOR.len() - 1].iter().rev() {
        p = p.mul_add(r, c);
    }
    p * pow2_scalar(k)
}

/// `tanh x` as `(e²ˣ − 1)/(e²ˣ + 1)` with [`exp`]: within 4e-16 of it absolutely (not
/// relatively: near 0 the difference cancels), ±1 beyond |x| = 354.
#[inline(always)]
pub(crate) fn tanh<const N: usize, Q: Lanes<N>>(q: Q, x: Q::V) -> Q::V {
    let e = exp(q, q.add(x, x));
    let one = q.splat(1.0);
    q.div(q.sub(e, one), q.add(e, one))
}

/// [`tanh`] for one value, the same bits.
#[inline(always)]
pub(crate) fn tanh_scalar(x: f64) -> f64 {
    let e = exp_scalar(x + x);
    (e - 1.0) / (e + 1.0)
}

/// The logistic function `1/(1 + e⁻ˣ)` with [`exp`].
#[inline(always)]
pub(crate) fn sigmoid<const N: usize, Q: Lanes<N>>(q: Q, x: Q::V) -> Q::V {
    let one = q.splat(1.0);
    q.div(one, q.add(one, exp(q, q.mul(q.splat(-1.0), x))))
}

/// `2^k` for a whole number `k` in [−1022, 1023].
#[inline(always)]
fn pow2_scalar(k: f64) -> f64 {
    f64::from_bits(((k as i64).wrapping_add(1023) as u64) << 52)
}

/// [`exp`]'s domain.
const EXP_MIN: f64 = -708.0;
const EXP_MAX: f64 = 709.0;
/// ln 2 as the nearest f64 and the remainder.
const LN2_HI: f64 = std::f64::consts::LN_2;
const LN2_LO: f64 = 2.319_046_813_846_299_6e-17;
/// 1/n! for n = 0, …, 13.
const EXP_TAYLOR: [f64; 14] = [
    1.0,
    1.0,
    0.5,
    1.0 / 6.0,
    1.0 / 24.0,
    1.0 / 120.0,
    1.0 / 720.0,
    1.0 / 5040.0,
    1.0 / 40320.0,
    1.0 / 362_880.0,
    1.0 / 3_628_800.0,
    1.0 / 39_916_800.0,
    1.0 / 479_001_600.0,
    1.0 / 6_227_020_800.0,
];

/// [`Lanes`] on arrays of `$n` lanes: IEEE operations lane by lane, `mul_add` the
/// correctly rounded `fma` (in software where the CPU has no FMA).
macro_rules! array_lanes {
    ($n:literal) => {
        type V = [f64; $n];
        #[inline(always)]
        fn splat(self, x: f64) -> Self::V {
            [x; $n]
        }
        #[inline(always)]
        fn load(self, a: [f64; $n]) -> Self::V {
            a
        }
        #[inline(always)]
        fn store(self, v: Self::V) -> [f64; $n] {
            v
        }
        #[inline(always)]
        fn add(self, a: Self::V, b: Self::V) -> Self::V {
            std::array::from_fn(|j| a[j] + b[j])
        }
        #[inline(always)]
        fn sub(self, a: Self::V, b: Self::V) -> Self::V {
            std::array::from_fn(|j| a[j] - b[j])
        }
        #[inline(always)]
        fn mul(self, a: Self::V, b: Self::V) -> Self::V {
            std::array::from_fn(|j| a[j] * b[j])
        }
        #[inline(always)]
        fn mul_add(self, a: Self::V, b: Self::V, c: Self::V) -> Self::V {
            std::array::from_fn(|j| a[j].mul_add(b[j], c[j]))
        }
        #[inline(always)]
        fn div(self, a: Self::V, b: Self::V) -> Self::V {
            std::array::from_fn(|j| a[j] / b[j])
        }
        #[inline(always)]
        fn sqrt(self, a: Self::V) -> Self::V {
            a.map(f64::sqrt)
        }
        #[inline(always)]
        fn round(self, a: Self::V) -> Self::V {
            a.map(f64::round_ties_even)
        }
        #[inline(always)]
        fn floor(self, a: Self::V) -> Self::V {
            a.map(f64::floor)
        }
        #[inline(always)]
        fn ceil(self, a: Self::V) -> Self::V {
            a.map(f64::ceil)
        }
        #[inline(always)]
        fn max(self, a: Self::V, b: Self::V) -> Self::V {
            std::array::from_fn(|j| if a[j] > b[j] { a[j] } else { b[j] })
        }
        #[inline(always)]
        fn min(self, a: Self::V, b: Self::V) -> Self::V {
            std::array::from_fn(|j| if a[j] < b[j] { a[j] } else { b[j] })
        }
        #[inline(always)]
        fn pow2(self, k: Self::V) -> Self::V {
            k.map(pow2_scalar)
        }
    };
}

/// Lanes as arrays, for CPUs without AVX2 and FMA (`mul_add` is then the correctly
/// rounded software `fma`).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Portable;

impl Lanes<4> for Portable {
    array_lanes!(4);
}

/// The eight-lane arithmetic of an instruction set (the four-lane one's token).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Wide<T>(T);

/// Each instruction set's eight lanes are [`Wide`] of its four-lane token. The x86
/// tokens prefetch with `prefetcht0` (safe through pulp's `sse` token), and take what
/// else they do their own way from the braces.
macro_rules! quad {
    ($t:ty) => {
        impl Quad for $t {
            type Oct = Wide<$t>;
            #[inline(always)]
            fn oct(self) -> Wide<$t> {
                Wide(self)
            }
        }
    };
    (x86 $t:ty { $($own:tt)* }) => {
        #[cfg(target_arch = "x86_64")]
        impl Quad for $t {
            type Oct = Wide<$t>;
            #[inline(always)]
            fn oct(self) -> Wide<$t> {
                Wide(self)
            }

            #[inline(always)]
            fn prefetch<T>(self, p: *const T) {
                self.sse._mm_prefetch::<{ std::arch::x86_64::_MM_HINT_T0 }>(p.cast());
            }

            $($own)*
        }
    };
}

quad!(Portable);
quad!(x86 pulp::x86::V3 {
    /// Eight voxels at a time: each of the four reads (bins j and j + 1 of either
    /// channel) permutes the window's first 8, 16 or 32 bins (one, two or four
    /// registers, as few as `reach` needs) and blends the registers' picks by j's
    /// bits; the products summed and added to the voxels' pairs lane by lane as one
    /// at a time, so the same bits.
    #[inline(always)]
    fn window_add(
        self,
        window: &[[f32; WINDOW]; 2],
        reach: usize,
        bin: &[i32],
        w: (&[f32], &[f32]),
        out: &mut [[f32; 2]],
    ) {
        let done = match reach {
            ..=8 => window_add_v3::<1>(self, window, bin, w, out),
            9..=16 => window_add_v3::<2>(self, window, bin, w, out),
            _ => window_add_v3::<4>(self, window, bin, w, out),
        };
        window_add_from(window, bin, w, out, done);
    }
});

/// Bin j (lane by lane) of the `8 R` bins in registers `t`: the permutes take j's low
/// three bits, the blends (on a mask's sign bit) its fourth and fifth.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn read_v3<const R: usize>(
    v3: pulp::x86::V3,
    t: &[std::arch::x86_64::__m256; R],
    j: std::arch::x86_64::__m256i,
) -> std::arch::x86_64::__m256 {
    use std::arch::x86_64::__m256;
    let (avx, avx2) = (v3.avx, v3.avx2);
    let p0 = avx2._mm256_permutevar8x32_ps(t[0], j);
    if R == 1 {
        return p0;
    }
    let fourth: __m256 = pulp::cast(avx2._mm256_slli_epi32::<28>(j));
    let lo = avx._mm256_blendv_ps(p0, avx2._mm256_permutevar8x32_ps(t[1], j), fourth);
    if R == 2 {
        return lo;
    }
    let hi = avx._mm256_blendv_ps(
        avx2._mm256_permutevar8x32_ps(t[2], j),
        avx2._mm256_permutevar8x32_ps(t[3], j),
        fourth,
    );
    let fifth: __m256 = pulp::cast(avx2._mm256_slli_epi32::<27>(j));
    avx._mm256_blendv_ps(lo, hi, fifth)
}

/// [`Quad::window_add`] with AVX2 from the window's first `8 R` bins (`R` registers a
/// channel), eight voxels at a time; returns how many voxels it did (the rest, fewer
/// than eight, are left to [`window_add_from`]).
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn window_add_v3<const R: usize>(
    v3: pulp::x86::V3,
    window: &[[f32; WINDOW]; 2],
    bin: &[i32],
    (w0, w1): (&[f32], &[f32]),
    out: &mut [[f32; 2]],
) -> usize {
    use std::arch::x86_64::{__m256, __m256i};
    const { assert!(R == 1 || R == 2 || R == 4, "one, two or four registers") };
    let (avx, avx2) = (v3.avx, v3.avx2);
    let n = bin.len().min(w0.len()).min(w1.len()).min(out.len());
    let part = |c: usize, r: usize| -> __m256 {
        pulp::cast(<[f32; 8]>::try_from(&window[c][8 * r..8 * r + 8]).expect("8 bins"))
    };
    let tables: [[__m256; R]; 2] = std::array::from_fn(|c| std::array::from_fn(|r| part(c, r)));
    // As one at a time: a bin past the registers reads their last two.
    let last = avx._mm256_set1_epi32(8 * R as i32 - 2);
    let one = avx._mm256_set1_epi32(1);
    // No closures in the loop: one the compiler does not inline is compiled without
    // AVX2, and every intrinsic in it becomes a call.
    let mut v = 0;
    while v + 8 <= n {
        let j: __m256i = pulp::cast(<[i32; 8]>::try_from(&bin[v..v + 8]).expect("8 lanes"));
        let j = avx2._mm256_min_epi32(j, last);
        let j1 = avx2._mm256_add_epi32(j, one);
        let a0: __m256 = pulp::cast(<[f32; 8]>::try_from(&w0[v..v + 8]).expect("8 lanes"));
        let a1: __m256 = pulp::cast(<[f32; 8]>::try_from(&w1[v..v + 8]).expect("8 lanes"));
        let re = avx._mm256_add_ps(
            avx._mm256_mul_ps(a0, read_v3(v3, &tables[0], j)),
            avx._mm256_mul_ps(a1, read_v3(v3, &tables[0], j1)),
        );
        let im = avx._mm256_add_ps(
            avx._mm256_mul_ps(a0, read_v3(v3, &tables[1], j)),
            avx._mm256_mul_ps(a1, read_v3(v3, &tables[1], j1)),
        );
        // Interleaved within each half (voxels 0, 1 | 4, 5 and 2, 3 | 6, 7), then the
        // halves put in order.
        let (lo, hi) = (avx._mm256_unpacklo_ps(re, im), avx._mm256_unpackhi_ps(re, im));
        let halves = [
            avx._mm256_permute2f128_ps::<0x20>(lo, hi),
            avx._mm256_permute2f128_ps::<0x31>(lo, hi),
        ];
        let pairs: &mut [[f32; 2]; 8] = (&mut out[v..v + 8]).try_into().expect("8 voxels");
        let flat: &mut [f32; 16] = pairs.as_flattened_mut().try_into().expect("16 values");
        let (first, second) = flat.split_at_mut(8);
        for (at, add) in [first, second].into_iter().zip(halves) {
            let at: &mut [f32; 8] = at.try_into().expect("8 values");
            let before: __m256 = pulp::cast(*at);
            *at = pulp::cast(avx._mm256_add_ps(before, add));
        }
        v += 8;
    }
    v
}

quad!(x86 pulp::x86::V4 {
    /// Sixteen voxels at a time: each of the four reads (bins j and j + 1 of either
    /// channel) one two-register permute of the window, whose 32 bins are two
    /// registers; the sums of the products interleaved by two more permutes and
    /// added to the voxels' pairs, lane by lane the operations of one at a time.
    #[inline(always)]
    fn window_add(
        self,
        window: &[[f32; WINDOW]; 2],
        reach: usize,
        bin: &[i32],
        (w0, w1): (&[f32], &[f32]),
        out: &mut [[f32; 2]],
    ) {
        use std::arch::x86_64::{__m512, __m512i};
        let _ = reach;
        let f = self.avx512f;
        let half = |c: usize, h: usize| -> __m512 {
            pulp::cast(<[f32; 16]>::try_from(&window[c][16 * h..16 * h + 16]).expect("16 bins"))
        };
        let (re0, re1, im0, im1) = (half(0, 0), half(0, 1), half(1, 0), half(1, 1));
        let n = bin.len().min(w0.len()).min(w1.len()).min(out.len());
        let (one, last) = (f._mm512_set1_epi32(1), f._mm512_set1_epi32(WINDOW as i32 - 2));
        // Lane l of the first interleaved half takes re[l/2] or im[l/2] (index 16 and
        // up: the second register); of the second half, 8 voxels on.
        let pick = |from: i32| -> __m512i {
            pulp::cast::<[i32; 16], __m512i>(std::array::from_fn(|l| {
                from + (l as i32 / 2) + 16 * (l as i32 % 2)
            }))
        };
        let (first, second) = (pick(0), pick(8));
        let lanes = |a: &[f32], v: usize| -> __m512 {
            pulp::cast(<[f32; 16]>::try_from(&a[v..v + 16]).expect("16 lanes"))
        };
        let mut v = 0;
        while v + 16 <= n {
            let j: __m512i = pulp::cast(<[i32; 16]>::try_from(&bin[v..v + 16]).expect("16 lanes"));
            // As one at a time: a bin past the window reads its last two.
            let j = f._mm512_min_epi32(j, last);
            let j1 = f._mm512_add_epi32(j, one);
            let (a0, a1) = (lanes(w0, v), lanes(w1, v));
            let sum = |lo: __m512, hi: __m512| {
                let (b0, b1) = (
                    f._mm512_permutex2var_ps(lo, j, hi),
                    f._mm512_permutex2var_ps(lo, j1, hi),
                );
                f._mm512_add_ps(f._mm512_mul_ps(a0, b0), f._mm512_mul_ps(a1, b1))
            };
            let (re, im) = (sum(re0, re1), sum(im0, im1));
            let pairs: &mut [[f32; 2]; 16] = (&mut out[v..v + 16]).try_into().expect("16 voxels");
            let flat: &mut [f32; 32] = pairs.as_flattened_mut().try_into().expect("32 values");
            for (h, order) in [first, second].into_iter().enumerate() {
                let at: &mut [f32; 16] = (&mut flat[16 * h..16 * h + 16]).try_into().expect("16 values");
                let before: __m512 = pulp::cast(*at);
                *at = pulp::cast(f._mm512_add_ps(before, f._mm512_permutex2var_ps(re, order, im)));
            }
            v += 16;
        }
        window_add_from(window, bin, (w0, w1), out, v);
    }
});

impl Lanes<8> for Wide<Portable> {
    array_lanes!(8);
}

#[cfg(target_arch = "x86_64")]
impl Lanes<4> for pulp::x86::V3 {
    type V = pulp::f64x4;
    #[inline(always)]
    fn splat(self, x: f64) -> Self::V {
        pulp::Simd::splat_f64s(self, x)
    }
    #[inline(always)]
    fn load(self, a: [f64; 4]) -> Self::V {
        pulp::f64x4(a[0], a[1], a[2], a[3])
    }
    #[inline(always)]
    fn store(self, v: Self::V) -> [f64; 4] {
        [v.0, v.1, v.2, v.3]
    }
    #[inline(always)]
    fn add(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::add_f64s(self, a, b)
    }
    #[inline(always)]
    fn sub(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::sub_f64s(self, a, b)
    }
    #[inline(always)]
    fn mul(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::mul_f64s(self, a, b)
    }
    #[inline(always)]
    fn mul_add(self, a: Self::V, b: Self::V, c: Self::V) -> Self::V {
        pulp::Simd::mul_add_f64s(self, a, b, c)
    }
    #[inline(always)]
    fn div(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::div_f64s(self, a, b)
    }
    #[inline(always)]
    fn sqrt(self, a: Self::V) -> Self::V {
        pulp::Simd::sqrt_f64s(self, a)
    }
    #[inline(always)]
    fn round(self, a: Self::V) -> Self::V {
        self.round_f64x4(a)
    }
    #[inline(always)]
    fn floor(self, a: Self::V) -> Self::V {
        self.floor_f64x4(a)
    }
    #[inline(always)]
    fn ceil(self, a: Self::V) -> Self::V {
        self.ceil_f64x4(a)
    }
    #[inline(always)]
    fn max(self, a: Self::V, b: Self::V) -> Self::V {
        // vmaxpd returns its second operand when either is NaN.
        self.max_f64x4(a, b)
    }
    #[inline(always)]
    fn min(self, a: Self::V, b: Self::V) -> Self::V {
        self.min_f64x4(a, b)
    }
    #[inline(always)]
    fn pow2(self, k: Self::V) -> Self::V {
        let k = self.convert_i32x4_to_i64x4(self.convert_f64x4_to_i32x4(k));
        let biased = self.wrapping_add_i64x4(k, self.splat_i64x4(1023));
        pulp::cast(self.shl_const_i64x4::<52>(biased))
    }
    #[inline(always)]
    fn total(self, v: Self::V) -> f64 {
        total_v3(self, v)
    }
}

/// Calls `$m!` with [`Lanes`]' operations on vectors and their operands' names, for
/// implementations that write them all alike.
#[cfg(target_arch = "x86_64")]
macro_rules! vector_ops {
    ($m:ident) => {
        $m!(
            add(a, b),
            sub(a, b),
            mul(a, b),
            mul_add(a, b, c),
            div(a, b),
            sqrt(a),
            round(a),
            floor(a),
            ceil(a),
            max(a, b),
            min(a, b),
            pow2(k)
        );
    };
}

/// AVX-512's four-lane operations: AVX2's (`*self`) of the same name.
#[cfg(target_arch = "x86_64")]
macro_rules! as_v3 {
    ($($f:ident($($a:ident),+)),+) => {
        $(
            #[inline(always)]
            fn $f(self, $($a: Self::V),+) -> Self::V {
                Lanes::<4>::$f(*self, $($a),+)
            }
        )+
    };
}

/// Eight lanes as two AVX2 vectors, low lanes first: each operation on both halves.
#[cfg(target_arch = "x86_64")]
macro_rules! halves {
    ($($f:ident($($a:ident),+)),+) => {
        $(
            #[inline(always)]
            fn $f(self, $($a: Self::V),+) -> Self::V {
                (Lanes::<4>::$f(self.0, $($a.0),+), Lanes::<4>::$f(self.0, $($a.1),+))
            }
        )+
    };
}

#[cfg(target_arch = "x86_64")]
impl Lanes<8> for Wide<pulp::x86::V3> {
    type V = (pulp::f64x4, pulp::f64x4);
    #[inline(always)]
    fn splat(self, x: f64) -> Self::V {
        let v = Lanes::<4>::splat(self.0, x);
        (v, v)
    }
    #[inline(always)]
    fn load(self, a: [f64; 8]) -> Self::V {
        (
            pulp::f64x4(a[0], a[1], a[2], a[3]),
            pulp::f64x4(a[4], a[5], a[6], a[7]),
        )
    }
    #[inline(always)]
    fn store(self, v: Self::V) -> [f64; 8] {
        [v.0.0, v.0.1, v.0.2, v.0.3, v.1.0, v.1.1, v.1.2, v.1.3]
    }
    #[inline(always)]
    fn total(self, v: Self::V) -> f64 {
        total_v3(self.0, v.0) + total_v3(self.0, v.1)
    }
    vector_ops!(halves);
}

/// AVX-512's four lanes are AVX2's operations (the same instructions, here with the
/// wider target's encodings).
#[cfg(target_arch = "x86_64")]
impl Lanes<4> for pulp::x86::V4 {
    type V = pulp::f64x4;
    #[inline(always)]
    fn splat(self, x: f64) -> Self::V {
        Lanes::<4>::splat(*self, x)
    }
    #[inline(always)]
    fn load(self, a: [f64; 4]) -> Self::V {
        Lanes::<4>::load(*self, a)
    }
    #[inline(always)]
    fn store(self, v: Self::V) -> [f64; 4] {
        Lanes::<4>::store(*self, v)
    }
    #[inline(always)]
    fn total(self, v: Self::V) -> f64 {
        total_v3(*self, v)
    }
    vector_ops!(as_v3);
}

/// AVX-512's eight lanes: one vector.
#[cfg(target_arch = "x86_64")]
impl Lanes<8> for Wide<pulp::x86::V4> {
    type V = pulp::f64x8;
    #[inline(always)]
    fn splat(self, x: f64) -> Self::V {
        pulp::Simd::splat_f64s(self.0, x)
    }
    #[inline(always)]
    fn load(self, a: [f64; 8]) -> Self::V {
        pulp::f64x8(a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7])
    }
    #[inline(always)]
    fn store(self, v: Self::V) -> [f64; 8] {
        [v.0, v.1, v.2, v.3, v.4, v.5, v.6, v.7]
    }
    #[inline(always)]
    fn add(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::add_f64s(self.0, a, b)
    }
    #[inline(always)]
    fn sub(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::sub_f64s(self.0, a, b)
    }
    #[inline(always)]
    fn mul(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::mul_f64s(self.0, a, b)
    }
    #[inline(always)]
    fn mul_add(self, a: Self::V, b: Self::V, c: Self::V) -> Self::V {
        pulp::Simd::mul_add_f64s(self.0, a, b, c)
    }
    #[inline(always)]
    fn div(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::div_f64s(self.0, a, b)
    }
    #[inline(always)]
    fn sqrt(self, a: Self::V) -> Self::V {
        pulp::Simd::sqrt_f64s(self.0, a)
    }
    #[inline(always)]
    fn round(self, a: Self::V) -> Self::V {
        self.0.round_f64x8(a)
    }
    #[inline(always)]
    fn floor(self, a: Self::V) -> Self::V {
        self.0.floor_f64x8(a)
    }
    #[inline(always)]
    fn ceil(self, a: Self::V) -> Self::V {
        self.0.ceil_f64x8(a)
    }
    #[inline(always)]
    fn max(self, a: Self::V, b: Self::V) -> Self::V {
        // vmaxpd returns its second operand when either is NaN.
        pulp::Simd::max_f64s(self.0, a, b)
    }
    #[inline(always)]
    fn min(self, a: Self::V, b: Self::V) -> Self::V {
        pulp::Simd::min_f64s(self.0, a, b)
    }
    #[inline(always)]
    fn pow2(self, k: Self::V) -> Self::V {
        let v = self.0;
        let k = v.convert_i32x8_to_i64x8(v.convert_f64x8_to_i32x8(k));
        let biased = v.wrapping_add_i64x8(k, v.splat_i64x8(1023));
        pulp::cast(v.shl_const_i64x8::<52>(biased))
    }
    /// Neighbours swapped and added, then pairs of them, then the upper four lanes
    /// added to the lower.
    #[inline(always)]
    fn total(self, v: Self::V) -> f64 {
        use std::arch::x86_64::__m512d;
        let (x, a) = (self.0, pulp::cast::<_, __m512d>(v));
        let a = x
            .avx512f
            ._mm512_add_pd(a, x.avx512f._mm512_permute_pd::<0b0101_0101>(a));
        let a = x
            .avx512f
            ._mm512_add_pd(a, x.avx512f._mm512_shuffle_f64x2::<0b10_11_00_01>(a, a));
        let (lo, hi) = (
            x.avx512f._mm512_castpd512_pd256(a),
            x.avx512f._mm512_extractf64x4_pd::<1>(a),
        );
        x.avx2._mm256_cvtsd_f64(x.avx._mm256_add_pd(lo, hi))
    }
}

/// This CPU's AVX2 + FMA token, for tests that compare it with [`Portable`].
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) fn v3() -> Option<pulp::x86::V3> {
    *V3
}

/// This CPU's AVX-512 token, for tests that compare it with [`Portable`].
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) fn v4() -> Option<pulp::x86::V4> {
    *V4
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The CPU's vectors and the arrays give the same bits, operation by operation,
    /// on operands that round (thirds, tenths), underflow and cancel.
    #[test]
    fn the_vectors_and_the_arrays_agree_bit_for_bit() {
        #[cfg(target_arch = "x86_64")]
        if let Some(v) = *V3 {
            let p = Portable;
            let (a, b, c) = (
                [0.1, -3.7e-12, 1.0 / 3.0, 7.5e300],
                [2.0 / 3.0, 1e-310, -0.0, 1.2],
                [1e16, 0.3, f64::MIN_POSITIVE, -9.0e300],
            );
            let (va, vb, vc) = (v.load(a), v.load(b), v.load(c));
            let bits = |x: [f64; 4]| x.map(f64::to_bits);
            assert_eq!(bits(p.add(a, b)), bits(v.store(v.add(va, vb))));
            assert_eq!(bits(p.sub(a, c)), bits(v.store(v.sub(va, vc))));
            assert_eq!(bits(p.mul(a, b)), bits(v.store(v.mul(va, vb))));
            assert_eq!(bits(p.mul_add(a, b, c)), bits(v.store(v.mul_add(va, vb, vc))));
            assert_eq!(bits(p.splat(0.25)), bits(v.store(v.splat(0.25))));
            assert_eq!(bits(p.div(a, b)), bits(v.store(v.div(va, vb))));
            assert_eq!(bits(p.div(c, a)), bits(v.store(v.div(vc, va))));
            let roots = [2.0, 1e-310, 0.0, 7.5e300];
            assert_eq!(bits(p.sqrt(roots)), bits(v.store(v.sqrt(v.load(roots)))));
            return;
        }
        eprintln!("skipped: this CPU has no AVX2 + FMA, only the arrays run");
    }

    /// The eight lanes of AVX2 (two vectors) and AVX-512 (one) give the arrays' bits,
    /// operation by operation, on operands that round, underflow, cancel and are NaN;
    /// `exp` on eight lanes gives `exp_scalar`'s bits.
    #[test]
    fn eight_lanes_agree_bit_for_bit() {
        fn check<O: Lanes<8>>(o: O) {
            let p = Portable.oct();
            let a = [0.1, -3.7e-12, 1.0 / 3.0, 7.5e300, 2.5, -0.0, 1e-300, 9.0];
            let b = [2.0 / 3.0, 1e-310, -0.0, 1.2, 0.7, f64::NAN, 1e-10, -1.0 / 7.0];
            let c = [
                1e16,
                0.3,
                f64::MIN_POSITIVE,
                -9.0e300,
                -1.75,
                2.0,
                1.0,
                1.0 / 49.0,
            ];
            let (va, vb, vc) = (o.load(a), o.load(b), o.load(c));
            let bits = |x: [f64; 8]| x.map(f64::to_bits);
            assert_eq!(bits(p.add(a, b)), bits(o.store(o.add(va, vb))));
            assert_eq!(bits(p.sub(a, c)), bits(o.store(o.sub(va, vc))));
            assert_eq!(bits(p.mul(a, b)), bits(o.store(o.mul(va, vb))));
            assert_eq!(bits(p.mul_add(a, b, c)), bits(o.store(o.mul_add(va, vb, vc))));
            assert_eq!(bits(p.splat(0.25)), bits(o.store(o.splat(0.25))));
            assert_eq!(bits(a), bits(o.store(va)));
            assert_eq!(bits(p.div(a, b)), bits(o.store(o.div(va, vb))));
            assert_eq!(bits(p.div(c, a)), bits(o.store(o.div(vc, va))));
            let roots = [2.0, 1e-310, 0.0, 7.5e300, 0.5, 3.0, 1e-300, 1e10];
            assert_eq!(bits(p.sqrt(roots)), bits(o.store(o.sqrt(o.load(roots)))));
            let r = [-2.5, -0.0, 3.5, 1e300, 0.5, -1.5, 2.4999, -7.7];
            let vr = o.load(r);
            assert_eq!(bits(p.round(r)), bits(o.store(o.round(vr))));
            assert_eq!(bits(p.floor(r)), bits(o.store(o.floor(vr))));
            assert_eq!(bits(p.ceil(r)), bits(o.store(o.ceil(vr))));
            assert_eq!(bits(p.max(r, b)), bits(o.store(o.max(vr, vb))));
            assert_eq!(bits(p.min(r, b)), bits(o.store(o.min(vr, vb))));
            assert_eq!(bits(p.max(b, r)), bits(o.store(o.max(vb, vr))));
            let k = [-1022.0, 0.0, 7.0, 1023.0, -1.0, 52.0, -300.0, 1.0];
            assert_eq!(bits(p.pow2(k)), bits(o.store(o.pow2(o.load(k)))));
            let x = [0.3, -700.0, 12.5, 0.0, -1e-9, 708.0, -0.75, 3.0];
            assert_eq!(bits(exp(p, x)), bits(o.store(exp(o, o.load(x)))));
            assert_eq!(bits(exp(p, x)), bits(x.map(exp_scalar)));
            // Totals whose rounding depends on the order of the adds.
            let t = [1e16, 1.0, -1e16, 1.0, 0.3, 1e-3, 7.0 / 3.0, -2.5];
            for l in [t, a, c, [t[1], t[0], t[3], t[2], t[6], t[7], t[4], t[5]]] {
                let tree = ((l[0] + l[1]) + (l[2] + l[3])) + ((l[4] + l[5]) + (l[6] + l[7]));
                assert_eq!(tree.to_bits(), p.total(l).to_bits());
                assert_eq!(tree.to_bits(), o.total(o.load(l)).to_bits());
            }
            let fold = t.iter().fold(0.0, |s, x| s + x);
            assert_ne!(
                fold.to_bits(),
                o.total(o.load(t)).to_bits(),
                "an order-blind check"
            );
            let four = |q: [f64; 4]| (q[0] + q[1]) + (q[2] + q[3]);
            let t4 = [t[0], t[1], t[2], t[3]];
            assert_eq!(four(t4).to_bits(), Portable.total(t4).to_bits());
            #[cfg(target_arch = "x86_64")]
            for v in [*V3].into_iter().flatten() {
                assert_eq!(four(t4).to_bits(), v.total(v.load(t4)).to_bits());
            }
            #[cfg(target_arch = "x86_64")]
            for v in [*V4].into_iter().flatten() {
                assert_eq!(four(t4).to_bits(), v.total(Lanes::<4>::load(v, t4)).to_bits());
            }
        }
        let mut ran = 0;
        #[cfg(target_arch = "x86_64")]
        if let Some(v) = *V3 {
            check(v.oct());
            ran += 1;
        }
        #[cfg(target_arch = "x86_64")]
        if let Some(v) = *V4 {
            check(v.oct());
            ran += 1;
        }
        if ran < 2 {
            eprintln!("skipped in part: this CPU lacks AVX2 + FMA or AVX-512 ({ran} of 2 ran)");
        }
    }

    #[test]
    fn the_window_reads_agree_bit_for_bit() {
        // 37 voxels (vectors of sixteen and of eight, and a tail) over every bin a
        // reach allows, the last pair included, added to values already there:
        // AVX-512's and AVX2's permutes against one voxel at a time, for reaches
        // that take AVX2's one, two and four registers (and their edges).
        let window: [[f32; WINDOW]; 2] = std::array::from_fn(|c| {
            std::array::from_fn(|j| ((j * 7 + c * 3) % 11) as f32 * 0.37 - 1.1 + c as f32 / 3.0)
        });
        let n = 37;
        let w0: Vec<f32> = (0..n).map(|v| 0.1 + v as f32 / 7.0).collect();
        let w1: Vec<f32> = (0..n).map(|v| 1.0 / (1.0 + v as f32)).collect();
        let start: Vec<[f32; 2]> = (0..n).map(|v| [v as f32 * 0.01, -(v as f32) / 3.0]).collect();
        let bits = |o: &[[f32; 2]]| o.iter().flatten().map(|x| x.to_bits()).collect::<Vec<_>>();
        for reach in [2, 5, 8, 9, 16, 17, 24, WINDOW] {
            let bin: Vec<i32> = (0..n).map(|v| ((v * 13) % (reach - 1)) as i32).collect();
            assert!(bin.contains(&(reach as i32 - 2)) && bin.contains(&0));
            let mut want = start.clone();
            window_add_from(&window, &bin, (&w0, &w1), &mut want, 0);
            let mut got = start.clone();
            Portable.window_add(&window, reach, &bin, (&w0, &w1), &mut got);
            assert_eq!(bits(&got), bits(&want), "portable, reach {reach}");
            #[cfg(target_arch = "x86_64")]
            if let Some(v) = pulp::x86::V4::try_new() {
                let mut got = start.clone();
                v.window_add(&window, reach, &bin, (&w0, &w1), &mut got);
                assert_eq!(bits(&got), bits(&want), "AVX-512, reach {reach}");
            } else if reach == WINDOW {
                eprintln!("the_window_reads_agree_bit_for_bit: no AVX-512 here, its path untested");
            }
            #[cfg(target_arch = "x86_64")]
            if let Some(v) = pulp::x86::V3::try_new() {
                let mut got = start.clone();
                v.window_add(&window, reach, &bin, (&w0, &w1), &mut got);
                assert_eq!(bits(&got), bits(&want), "AVX2, reach {reach}");
            } else if reach == WINDOW {
                eprintln!("the_window_reads_agree_bit_for_bit: no AVX2 here, its path untested");
            }
        }
    }

    /// `PERISCOPE_SIMD` caps the instruction set: names for each level (any case,
    /// spaces around), and anything else (or nothing) leaves the best the CPU has.
    #[test]
    fn the_simd_ceiling_reads_its_names() {
        assert_eq!(Ceiling::from_env(None), Ceiling::Avx512);
        assert_eq!(Ceiling::from_env(Some(" AVX2 ")), Ceiling::Avx2);
        assert_eq!(Ceiling::from_env(Some("x86-64-v3")), Ceiling::Avx2);
        assert_eq!(Ceiling::from_env(Some("baseline")), Ceiling::Baseline);
        assert_eq!(Ceiling::from_env(Some("avx512")), Ceiling::Avx512);
        assert_eq!(Ceiling::from_env(Some("sse9")), Ceiling::Avx512);
    }

    /// `exp` is within 1 ulp of `f64::exp` over its domain, and
    /// the arrays, this CPU's vectors and `exp_scalar` give the same bits; the other
    /// operations agree with `f64`'s.
    #[test]
    fn exp_is_accurate_and_the_same_everywhere() {
        let n = 200_000;
        let xs: Vec<f64> = (0..n)
            .map(|i| EXP_MIN + (EXP_MAX - EXP_MIN) * (i as f64 + 0.37) / n as f64)
            .chain((0..20_000).map(|i| (i as f64 - 10_000.0) * 1.3e-4))
            .chain([0.0, -0.0, 1.0, -1.0, 1e-300, -0.25, -450.0, EXP_MIN, EXP_MAX])
            .collect();
        let mut worst = 0u64;
        for &x in &xs {
            let (got, want) = (exp_scalar(x), x.exp());
            let ulps = got.to_bits().abs_diff(want.to_bits());
            worst = worst.max(ulps);
            let lanes = exp(Portable, [x, -x.abs(), x * 0.5, 0.0]);
            assert_eq!(lanes[0].to_bits(), got.to_bits(), "exp({x})");
            assert_eq!(lanes[1].to_bits(), exp_scalar(-x.abs()).to_bits());
        }
        assert!(worst <= 1, "exp off by {worst} ulp");
        assert_eq!(
            Portable.pow2([-1022.0, 0.0, 7.0, 1023.0]),
            [f64::MIN_POSITIVE, 1.0, 128.0, 2f64.powi(1023)]
        );
        assert_eq!(exp_scalar(f64::NAN), exp_scalar(EXP_MAX));
        for &x in xs
            .iter()
            .step_by(7)
            .chain(&[0.0, 1e-9, -3e-4, 0.5, -20.0, 400.0, -400.0])
        {
            let x = x / 20.0;
            assert!((tanh_scalar(x) - x.tanh()).abs() <= 4e-16, "tanh({x})");
            let logistic = 1.0 / (1.0 + (-x).exp());
            let got = sigmoid(Portable, [x; 4])[0];
            assert!(
                (got - logistic).abs() <= 5e-16 * logistic.max(1e-300),
                "sigmoid({x})"
            );
            let lanes = [x, -x, 2.0 * x, 0.1];
            assert_eq!(tanh(Portable, lanes)[0].to_bits(), tanh_scalar(x).to_bits());
            assert_eq!(
                sigmoid(Portable, lanes)[1].to_bits(),
                sigmoid(Portable, [-x; 4])[0].to_bits()
            );
        }
        assert_eq!(exp_scalar(-1e10), exp_scalar(EXP_MIN));
        #[cfg(target_arch = "x86_64")]
        if let Some(v) = *V3 {
            for c in xs.chunks_exact(4) {
                let a: [f64; 4] = c.try_into().unwrap();
                let bits = |x: [f64; 4]| x.map(f64::to_bits);
                assert_eq!(bits(v.store(exp(v, v.load(a)))), bits(exp(Portable, a)), "{a:?}");
                let a = a.map(|x| x / 20.0);
                assert_eq!(
                    bits(v.store(tanh(v, v.load(a)))),
                    bits(tanh(Portable, a)),
                    "{a:?}"
                );
                assert_eq!(
                    bits(v.store(sigmoid(v, v.load(a)))),
                    bits(sigmoid(Portable, a)),
                    "{a:?}"
                );
            }
            let p = Portable;
            let a = [-2.5, -0.0, 3.5, 1e300];
            let b = [0.0, 0.0, f64::NAN, -1e300];
            let bits = |x: [f64; 4]| x.map(f64::to_bits);
            let va = v.load(a);
            assert_eq!(bits(v.store(v.round(va))), bits(p.round(a)));
            assert_eq!(bits(v.store(v.floor(va))), bits(p.floor(a)));
            assert_eq!(bits(v.store(v.ceil(va))), bits(p.ceil(a)));
            assert_eq!(bits(v.store(v.max(va, v.load(b)))), bits(p.max(a, b)));
            assert_eq!(bits(v.store(v.min(va, v.load(b)))), bits(p.min(a, b)));
            assert_eq!(bits(v.store(v.max(v.load(b), va))), bits(p.max(b, a)));
            let k = [-1022.0, 0.0, 7.0, 1023.0];
            assert_eq!(bits(v.store(v.pow2(v.load(k)))), bits(p.pow2(k)));
            return;
        }
        eprintln!("skipped: this CPU has no AVX2 + FMA, only the arrays ran");
    }
}

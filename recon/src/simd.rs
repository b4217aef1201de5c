//! Run-time SIMD dispatch for the hot loops.
//!
//! The renderer, the synthesis and FBP are written as plain loops over slices that
//! LLVM vectorises. Built for the baseline x86-64 target, that code gets SSE2 only:
//! no FMA, no 256-bit vectors, and `floor` is a libm call. `dispatch` runs a function
//! inside a function compiled with AVX2 and FMA enabled when the CPU has them (checked
//! once, at run time, by `pulp`), so everything inlined into it is vectorised for the
//! machine it runs on; elsewhere it runs the same function as compiled for the baseline.
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
//! written against `Quad`, four f64 lanes: AVX2 + FMA vectors under `dispatch` on a
//! CPU that has them, plain arrays otherwise. Both do the same IEEE operations lane by
//! lane (`mul_add` fused in both), so they give the same bits.
use std::sync::LazyLock;

#[cfg(target_arch = "x86_64")]
static V3: LazyLock<Option<pulp::x86::V3>> = LazyLock::new(pulp::x86::V3::try_new);

/// A unit of hot work: `run` holds the loops to compile for the wider target.
///
/// Implementations mark `run` `#[inline(always)]` so that its body is compiled inside
/// the specialised function (a closure, or a function item called through `FnOnce`,
/// is inlined only when the compiler finds it cheap, and a loop nest is not).
pub(crate) trait Work {
    /// What the work returns.
    type Output;
    /// Does the work, with `quad` the four-lane vector arithmetic of this CPU.
    fn run<Q: Quad>(self, quad: Q) -> Self::Output;
}

/// Runs `work` compiled for the best instruction set this CPU offers.
#[inline]
pub(crate) fn dispatch<W: Work>(work: W) -> W::Output {
    #[cfg(target_arch = "x86_64")]
    if let Some(simd) = *V3 {
        struct Op<W>(W, pulp::x86::V3);
        impl<W: Work> pulp::WithSimd for Op<W> {
            type Output = W::Output;
            #[inline(always)]
            fn with_simd<S: pulp::Simd>(self, _: S) -> W::Output {
                self.0.run(self.1)
            }
        }
        return pulp::Simd::vectorize(simd, Op(work, simd));
    }
    work.run(Portable)
}

/// The SIMD level the hot loops run at on this machine, for benchmarks and logs.
pub fn level() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    if V3.is_some() {
        return "x86-64-v3 (AVX2, FMA)";
    }
    "baseline"
}

/// Four f64 lanes and the IEEE operations on them, lane by lane.
pub(crate) trait Quad: Copy {
    /// The vector.
    type V: Copy;
    /// Every lane `x`.
    fn splat(self, x: f64) -> Self::V;
    /// The lanes from an array.
    fn load(self, a: [f64; 4]) -> Self::V;
    /// The lanes as an array.
    fn store(self, v: Self::V) -> [f64; 4];
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
}

/// [`Quad`] as arrays, for CPUs without AVX2 and FMA (`mul_add` is then the correctly
/// rounded software `fma`).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Portable;

impl Quad for Portable {
    type V = [f64; 4];
    #[inline(always)]
    fn splat(self, x: f64) -> Self::V {
        [x; 4]
    }
    #[inline(always)]
    fn load(self, a: [f64; 4]) -> Self::V {
        a
    }
    #[inline(always)]
    fn store(self, v: Self::V) -> [f64; 4] {
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
}

#[cfg(target_arch = "x86_64")]
impl Quad for pulp::x86::V3 {
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
}

/// This CPU's AVX2 + FMA token, for tests that compare it with [`Portable`].
#[cfg(all(test, target_arch = "x86_64"))]
pub(crate) fn v3() -> Option<pulp::x86::V3> {
    *V3
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
}

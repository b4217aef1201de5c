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
use std::sync::LazyLock;

static ARCH: LazyLock<pulp::Arch> = LazyLock::new(pulp::Arch::new);

/// A unit of hot work: `run` holds the loops to compile for the wider target.
///
/// Implementations mark `run` `#[inline(always)]` so that its body is compiled inside
/// the specialised function (a closure, or a function item called through `FnOnce`,
/// is inlined only when the compiler finds it cheap, and a loop nest is not).
pub(crate) trait Work {
    /// What the work returns.
    type Output;
    /// Does the work.
    fn run(self) -> Self::Output;
}

/// Runs `work` compiled for the best instruction set this CPU offers.
#[inline]
pub(crate) fn dispatch<W: Work>(work: W) -> W::Output {
    struct Op<W>(W);
    impl<W: Work> pulp::WithSimd for Op<W> {
        type Output = W::Output;
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _: S) -> W::Output {
            self.0.run()
        }
    }
    ARCH.dispatch(Op(work))
}

/// The SIMD level the hot loops run at on this machine, for benchmarks and logs.
pub fn level() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        match *ARCH {
            pulp::Arch::V3(_) => "x86-64-v3 (AVX2, FMA)",
            _ => "baseline",
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        "baseline"
    }
}

//! CPU kernels, f32, row-major, NCHW for images.
//!
//! Every kernel takes its inputs as slices with explicit sizes, writes a caller-provided
//! output slice, and allocates nothing proportional to the model: scratch memory a kernel
//! needs (an im2col tile) is sized by a `*_scratch_len` function and passed in by the
//! executor, which plans it once. Kernels parallelise with rayon in the current thread
//! pool; the executor installs a pool of the requested size, and `threads` tells GEMM how
//! many of its threads to use.
//!
//! Each kernel has unit tests against a naive reference implementation, including odd
//! shapes.

pub mod conv;
pub mod elementwise;
pub mod gemm;
pub mod layout;
pub mod linear;
pub mod norm;
pub mod pool;
pub mod reduce;
pub mod resize;
pub mod softmax;

#[cfg(test)]
pub(crate) mod testutil;

/// Runs `f(args)` compiled for the widest SIMD extension the CPU has (AVX-512, AVX2+FMA,
/// or the baseline), chosen at run time; without it kernel loops only get the baseline's
/// SSE2.
///
/// `f` should be a function item marked `#[inline(always)]` holding the whole loop: it
/// is then inlined into the target-feature function and vectorised for it. (A large
/// closure is not reliably inlined there and silently stays SSE2; measured 4x slower for
/// GELU.)
#[inline(always)]
pub(crate) fn vectorized<A, R, F: FnOnce(A) -> R>(f: F, args: A) -> R {
    struct Op<F, A>(F, A);
    impl<A, R, F: FnOnce(A) -> R> pulp::WithSimd for Op<F, A> {
        type Output = R;
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) -> R {
            (self.0)(self.1)
        }
    }
    pulp::Arch::new().dispatch(Op(f, args))
}

/// Element-wise binary operations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BinaryOp {
    Add,
    Sub,
    Mul,
    Div,
}

/// Element-wise activations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Act {
    Relu,
    /// GELU with erf, as PyTorch's default.
    Gelu,
    /// GELU with the tanh approximation.
    GeluTanh,
    Sigmoid,
}

/// What happens to each output channel of a conv or linear after the accumulation:
/// `y = act(acc * scale[c] + shift[c])`. A bias is a `shift` without `scale`; a folded
/// BatchNorm is both.
#[derive(Clone, Copy, Debug, Default)]
pub struct Epilogue<'a> {
    pub scale: Option<&'a [f32]>,
    pub shift: Option<&'a [f32]>,
    pub relu: bool,
}

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
//!
//! # SIMD
//!
//! The crate is built without `-C target-cpu`, so a plain loop only gets the baseline's
//! SSE2. Every hot loop therefore runs inside a function that pulp dispatches at run time
//! to a copy compiled for AVX-512, AVX2+FMA or the baseline, in one of two ways:
//!
//! * `simd_fn!` (below) for plain loops left to LLVM's auto-vectoriser (element-wise maps,
//!   copies, per-channel affines): the body is written as usual.
//! * A hand-written `pulp::WithSimd` type, where the code is generic (conv's transforms,
//!   pooling) or uses pulp's vector type `S::f32s` explicitly. Reductions do (softmax,
//!   `reduce::sum_simd`, LayerNorm): lane-array accumulators left to LLVM ended up in
//!   memory or split into narrow vectors depending on the code around them.
//!
//! Measured pitfalls with AVX-512, each worth 2-3x on the loop it hit: a read-modify-write
//! select (`*a = if v > *a { v } else { *a }`) becomes a masked store, and the next read of
//! `*a` stalls on store forwarding; reading a buffer right after filling it with
//! differently sized stores (a `memcpy`, a scalar tail) stalls the same way; a loop
//! shorter than one 16-lane vector runs entirely in the scalar remainder. Check with
//! `objdump -d --no-show-raw-insn -C`: the loops belong in `V4::vectorize` functions, on
//! `zmm` registers, with no calls out.

/// Defines a function whose body is compiled for the widest SIMD extension the CPU has
/// (AVX-512, AVX2+FMA, or the baseline), chosen at run time on every call. The crate is
/// built without `-C target-cpu`, so loops elsewhere only get the baseline's SSE2.
///
/// The body becomes the `with_simd` method of a local `pulp::WithSimd` type, which pulp
/// inlines into one `#[target_feature]` function per extension, so every loop in it is
/// vectorised for that extension. Functions the body calls must be `#[inline(always)]`
/// (or trivially small) to be compiled with it; `objdump -d` on the binary shows whether
/// they were: the loops should use `zmm` registers inside `V4::vectorize`.
///
/// Why a macro and not a function taking the body as a closure or a function item: the
/// body then sits behind an `FnOnce` call (a closure or a fn-item shim) that each of the
/// three dispatch targets calls, and LLVM declines to inline a large callee with several
/// callers, so the body silently stays SSE2 (measured: GELU 3.0 ns/element that way,
/// 0.75 ns inlined; `scalar` likewise). Arguments are plain `name: Type` pairs; elided
/// reference lifetimes are fine, but a type's own lifetime parameters must be written
/// (`Part<'_>`); generic parameters are not supported (write a `WithSimd` type instead).
macro_rules! simd_fn {
    (
        $(#[$attr:meta])*
        $vis:vis fn $name:ident($($arg:ident: $ty:ty),* $(,)?) $(-> $ret:ty)? $body:block
    ) => {
        $(#[$attr])*
        $vis fn $name($($arg: $ty),*) $(-> $ret)? {
            struct Op<A>(A);
            impl pulp::WithSimd for Op<($($ty,)*)> {
                type Output = simd_fn!(@ret $($ret)?);
                #[inline(always)]
                fn with_simd<S: pulp::Simd>(self, _simd: S) -> Self::Output {
                    let ($($arg,)*) = self.0;
                    $body
                }
            }
            pulp::Arch::new().dispatch(Op(($($arg,)*)))
        }
    };
    (@ret) => { () };
    (@ret $ret:ty) => { $ret };
}

/// A LoRA branch fused into the kernel of the layer it adapts (conv, linear): `A` in the
/// layout that kernel reads, `B` `[out, rank]` row-major with the LoRA scale already
/// multiplied in. The kernel adds `B (A x)` to its accumulator before the epilogue.
#[derive(Clone, Copy, Debug)]
pub struct Lora<'a> {
    pub a: &'a [f32],
    pub b: &'a [f32],
    pub rank: usize,
}

pub mod bev_pool;
pub mod conv;
pub mod conv3d;
pub mod conv_transpose;
pub mod elementwise;
pub mod gemm;
pub mod index;
pub mod layout;
pub mod linear;
pub mod merge;
pub mod movement;
pub mod norm;
pub mod panel;
pub mod pool;
pub mod reduce;
pub mod resize;
#[cfg(target_arch = "x86_64")]
pub(crate) mod rows512;
pub mod select;
pub mod softmax;
pub mod sparse;
pub mod voxel;

#[cfg(test)]
pub(crate) mod testutil;

pub use readi_plan::ops::{Activation, BinaryOp};

/// What happens to each output channel of a conv or linear after the accumulation:
/// `y = act(acc * scale[c] + shift[c])`. A bias is a `shift` without `scale`; a folded
/// BatchNorm is both.
#[derive(Clone, Copy, Debug, Default)]
pub struct Epilogue<'a> {
    pub scale: Option<&'a [f32]>,
    pub shift: Option<&'a [f32]>,
    /// Applied last; `Relu` runs in the affine's own loop, any other activation as a
    /// second pass over the block the affine just wrote (still in cache), except where a
    /// register path computes it on its sums ([`Epilogue::clamp`],
    /// [`Epilogue::vector_act`]).
    pub act: Option<Activation>,
}

impl Epilogue<'_> {
    /// Whether the activation is a ReLU, which the kernels fuse into the affine's loop.
    #[inline(always)]
    pub fn relu(&self) -> bool {
        self.act == Some(Activation::Relu)
    }

    /// The bounds of the activation when it is a clamp ([`clamp_bounds`]), which the
    /// register-blocked conv paths apply to their vectors as they store them.
    #[inline(always)]
    pub fn clamp(&self) -> Option<(f32, f32)> {
        clamp_bounds(self.act?)
    }

    /// The activation a register path computes on its vectors before it stores them, on a
    /// SIMD backend `S` of more than one lane: SiLU, sigmoid, GELU, tanh, hardswish and
    /// hardsigmoid ([`elementwise::act_simd`]), whose pass over the stored block would
    /// read it back.
    #[inline(always)]
    pub fn vector_act<S: pulp::Simd>(&self) -> Option<Activation> {
        self.act.filter(|&a| size_of::<S::f32s>() > size_of::<f32>() && elementwise::on_vectors(a))
    }

    /// Applies the activation unless it is a clamp (see [`Epilogue::clamp`]) to `out`, a
    /// block a register path stored.
    #[inline]
    pub fn finish_unclamped(&self, out: &mut [f32]) {
        if let Some(act) = self.act
            && self.clamp().is_none()
        {
            elementwise::activation_chunk(act, out);
        }
    }

    /// Applies the activation other than a ReLU (see [`Epilogue::relu`]) to `out`, the
    /// finished affine of a block, on the calling thread.
    #[inline]
    pub fn finish_act(&self, out: &mut [f32]) {
        if let Some(act) = self.act
            && act != Activation::Relu
        {
            elementwise::activation_chunk(act, out);
        }
    }
}

/// The bounds of `act` when it is a clamp (ReLU, ReLU6, clamp), else `None`.
#[inline(always)]
pub fn clamp_bounds(act: Activation) -> Option<(f32, f32)> {
    match act {
        Activation::Relu => Some((0.0, f32::INFINITY)),
        Activation::Relu6 => Some((0.0, 6.0)),
        Activation::Clamp { min, max } => Some((min.unwrap_or(f32::NEG_INFINITY), max.unwrap_or(f32::INFINITY))),
        _ => None,
    }
}

//! Element-wise kernels: binary ops with NumPy broadcasting, ops with a scalar, activations.

use pulp::Simd;
use rayon::prelude::*;

use super::softmax::{exp_fast, exp_in_range, exp_simd};
use super::{Activation, BinaryOp};

/// Below this many elements a kernel runs on the calling thread.
const PAR_MIN: usize = 1 << 15;
/// Elements per parallel task.
const CHUNK: usize = 1 << 14;

/// `out = a op b` with NumPy broadcasting, all row-major.
///
/// Shapes are right-aligned; every axis of `a_shape` and `b_shape` is either the size of
/// the same axis of `out_shape` or 1 (missing leading axes count as 1). `out_shape` is the
/// broadcast shape. Neighbouring axes that broadcast alike are merged first, so the
/// innermost loop is always contiguous or a scalar: same-shape, `[N,C,H,W] + [1,C,1,1]`
/// and `[N,T,D] + [1,T,D]` all run as straight vectorised loops.
pub fn binary(
    op: BinaryOp,
    a: &[f32],
    a_shape: &[usize],
    b: &[f32],
    b_shape: &[usize],
    out: &mut [f32],
    out_shape: &[usize],
) {
    debug_assert_eq!(check_binary(a_shape, b_shape, out_shape), Ok(()), "binary preconditions");
    assert_eq!(a.len(), a_shape.iter().product::<usize>(), "binary: a does not match its shape");
    assert_eq!(b.len(), b_shape.iter().product::<usize>(), "binary: b does not match its shape");
    assert_eq!(out.len(), out_shape.iter().product::<usize>(), "binary: out does not match its shape");
    if out.is_empty() {
        return;
    }
    if a_shape == b_shape && a_shape == out_shape {
        return par_ranges(out, |start, o| {
            let n = o.len();
            vv_simd(op, &a[start..start + n], &b[start..start + n], o)
        });
    }
    let plan = Broadcast::new(a_shape, b_shape, out_shape);
    par_ranges(out, |start, o| broadcast_simd(&plan, op, a, b, start, o));
}

/// `out = x op value`, or `out = value op x` when `scalar_first`.
///
/// `x ** e` for `e` in 2, 3, 0.5, -0.5, -1, -2 is computed as PyTorch's CPU kernel does it
/// (`x * x`, `x * x * x`, `sqrt`, `1 / sqrt`, `1 / x`, `1 / (x * x)`), which vectorises;
/// other exponents call `powf` per element (a plain loop).
pub fn scalar(op: BinaryOp, x: &[f32], value: f32, scalar_first: bool, out: &mut [f32]) {
    assert_eq!(x.len(), out.len(), "scalar: x and out differ in length");
    if op == BinaryOp::Pow
        && !scalar_first
        && let Some(p) = PowBy::of(value)
    {
        return par_ranges(out, |start, o| pow_by_simd(p, &x[start..start + o.len()], o));
    }
    if op == BinaryOp::Pow {
        // `powf` is a libm call either way; inside the SIMD-dispatched function it ran
        // 1.3x slower than this plain loop (measured, `unary/readi/pow1.5`).
        return par_ranges(out, |start, o| {
            let x = &x[start..start + o.len()];
            for (o, &v) in o.iter_mut().zip(x) {
                *o = if scalar_first { value.powf(v) } else { v.powf(value) };
            }
        });
    }
    par_ranges(out, |start, o| {
        let x = &x[start..start + o.len()];
        scalar_simd(op, x, value, scalar_first, o)
    });
}

/// A constant exponent PyTorch computes without `pow`.
#[derive(Clone, Copy, Debug, PartialEq)]
enum PowBy {
    Square,
    Cube,
    Sqrt,
    Rsqrt,
    Recip,
    RecipSquare,
}

impl PowBy {
    fn of(e: f32) -> Option<PowBy> {
        Some(match e {
            2.0 => PowBy::Square,
            3.0 => PowBy::Cube,
            0.5 => PowBy::Sqrt,
            -0.5 => PowBy::Rsqrt,
            -1.0 => PowBy::Recip,
            -2.0 => PowBy::RecipSquare,
            _ => return None,
        })
    }
}

simd_fn! {
    /// `out[i] = x[i] ** e` for a [`PowBy`] exponent.
    fn pow_by_simd(p: PowBy, x: &[f32], out: &mut [f32]) {
        let x = &x[..out.len()];
        let it = out.iter_mut().zip(x);
        match p {
            PowBy::Square => it.for_each(|(o, &v)| *o = v * v),
            PowBy::Cube => it.for_each(|(o, &v)| *o = v * v * v),
            PowBy::Sqrt => it.for_each(|(o, &v)| *o = v.sqrt()),
            PowBy::Rsqrt => it.for_each(|(o, &v)| *o = 1.0 / v.sqrt()),
            PowBy::Recip => it.for_each(|(o, &v)| *o = 1.0 / v),
            PowBy::RecipSquare => it.for_each(|(o, &v)| *o = 1.0 / (v * v)),
        }
    }
}

/// `out = act(x)`, element-wise.
///
/// Every activation is plain arithmetic (no libm calls), so the loops vectorise. Measured
/// over [-12, 12]: `Gelu` is within 4e-7 of the exact erf form (PyTorch's CPU kernel is
/// within 1.1e-6 of it), `GeluTanh` within 6e-7 of its f64 formula. Largest relative
/// errors against f64 over [-12, 12] and every binade of f32, as
/// `unary_functions_within_a_few_ulp` measures them (one f32 ulp is 6e-8 to 1.2e-7):
/// `exp` 9.5e-8 (0 below -87, where e^x < 1.7e-38), `log` 7.7e-8, `erf` 2.6e-7, `tanh`
/// 2.7e-7, `sigmoid` 1.9e-7, `silu` 2.3e-7, `elu` 9.6e-8, `sqrt` 5.9e-8, `rsqrt` 8.9e-8,
/// `hardswish` 1.4e-7, `hardsigmoid` 8.9e-8; `abs`, `neg`, `relu6` and `clamp` are exact.
pub fn activation(act: Activation, x: &[f32], out: &mut [f32]) {
    assert_eq!(x.len(), out.len(), "activation: x and out differ in length");
    par_ranges(out, |start, o| map_chunk(act, &x[start..start + o.len()], o));
}

/// `x = act(x)`, element-wise.
pub fn activation_in_place(act: Activation, x: &mut [f32]) {
    par_ranges(x, |_, x| map_chunk_in_place(act, x));
}

/// `x = act(x)` on the calling thread: a conv's or linear's epilogue over the block it
/// just wrote.
pub fn activation_chunk(act: Activation, x: &mut [f32]) {
    map_chunk_in_place(act, x)
}

/// `out = act(out + r)`, element-wise: a residual added after the kernel that wrote `out`
/// (a conv step whose path does not add it as it writes, see `conv::conv2d_fused`), then
/// the step's activation.
pub fn add_in_place(out: &mut [f32], r: &[f32], act: Option<Activation>) {
    assert_eq!(out.len(), r.len(), "add: out and r differ in length");
    par_ranges(out, |start, o| add_chunk_in_place(o, &r[start..start + o.len()], act));
}

simd_fn! {
    /// [`add_in_place`] on one chunk, the ReLU in the sum's loop.
    fn add_chunk_in_place(out: &mut [f32], r: &[f32], act: Option<Activation>) {
        if act == Some(Activation::Relu) {
            out.iter_mut().zip(r).for_each(|(o, &r)| *o = relu(*o + r));
        } else {
            out.iter_mut().zip(r).for_each(|(o, &r)| *o += r);
            if let Some(f) = act {
                map_chunk_in_place(f, out);
            }
        }
    }
}

/// Expands `$body` once per activation, with `$f` bound to its function item (a direct
/// call, inlined), so each loop is compiled on its own.
macro_rules! per_act {
    ($act:expr, $f:ident => $body:expr) => {
        match $act {
            Activation::Relu => {
                let $f = relu;
                $body
            }
            Activation::Gelu => {
                let $f = gelu;
                $body
            }
            Activation::GeluTanh => {
                let $f = gelu_tanh;
                $body
            }
            Activation::Sigmoid => {
                let $f = sigmoid;
                $body
            }
            Activation::Tanh => {
                let $f = tanh;
                $body
            }
            Activation::Silu => {
                let $f = silu;
                $body
            }
            Activation::Relu6 => {
                let $f = relu6;
                $body
            }
            Activation::Clamp { min, max } => {
                let (lo, hi) = (min.unwrap_or(f32::NEG_INFINITY), max.unwrap_or(f32::INFINITY));
                let $f = move |x: f32| clamp(x, lo, hi);
                $body
            }
            Activation::Hardswish => {
                let $f = hardswish;
                $body
            }
            Activation::Hardsigmoid => {
                let $f = hardsigmoid;
                $body
            }
            Activation::LeakyRelu { negative_slope } => {
                let $f = move |x: f32| if x > 0.0 { x } else { x * negative_slope };
                $body
            }
            Activation::Elu { alpha } => {
                let $f = move |x: f32| if x > 0.0 { x } else { alpha * expm1(x) };
                $body
            }
            Activation::Exp => {
                let $f = exp;
                $body
            }
            Activation::Log => {
                let $f = log;
                $body
            }
            Activation::Sqrt => {
                let $f = f32::sqrt;
                $body
            }
            Activation::Rsqrt => {
                let $f = |x: f32| 1.0 / x.sqrt();
                $body
            }
            Activation::Abs => {
                let $f = f32::abs;
                $body
            }
            Activation::Neg => {
                let $f = |x: f32| -x;
                $body
            }
            Activation::Erf => {
                let $f = erf;
                $body
            }
        }
    };
}

/// `out[i] = act(x[i])`.
fn map_chunk(act: Activation, x: &[f32], out: &mut [f32]) {
    if on_vectors(act) {
        pulp::Arch::new().dispatch(VectorMap { act, x: Some(&x[..out.len()]), out })
    } else {
        map_chunk_loop(act, x, out)
    }
}

/// `x[i] = act(x[i])`.
fn map_chunk_in_place(act: Activation, x: &mut [f32]) {
    if on_vectors(act) {
        pulp::Arch::new().dispatch(VectorMap { act, x: None, out: x })
    } else {
        map_chunk_in_place_loop(act, x)
    }
}

simd_fn! {
    /// [`map_chunk`] as a loop over the scalar function, which LLVM vectorises.
    fn map_chunk_loop(act: Activation, x: &[f32], out: &mut [f32]) {
        let x = &x[..out.len()];
        per_act!(act, f => {
            for (o, &v) in out.iter_mut().zip(x) {
                *o = f(v);
            }
        })
    }
}

simd_fn! {
    /// [`map_chunk_in_place`] as a loop over the scalar function.
    fn map_chunk_in_place_loop(act: Activation, x: &mut [f32]) {
        per_act!(act, f => {
            for v in x.iter_mut() {
                *v = f(*v);
            }
        })
    }
}

/// Whether `act` runs on SIMD vectors written out ([`VectorMap`]) rather than as a loop
/// over its scalar function: the functions over `exp` (sigmoid, SiLU, GELU, tanh), whose
/// polynomials LLVM keeps as separate multiplies and adds in the vectorised loop (Rust
/// does not let it fuse them): about 40 instructions a vector for sigmoid. In place over
/// 144 planes of 56x56 (AVX-512, one thread, 2026-12-06), against those loops: SiLU
/// 0.63-0.69x the time, GELU 0.39x, tanh 0.59x. And hardswish and hardsigmoid, so that
/// the convs' register paths compute them on their sums as they store them
/// ([`crate::kernels::Epilogue::vector_act`]) instead of in a pass over the stored
/// block: MobileNetV3-Large's 1x1 expansions on 14x14 planes 0.89-0.91x the time (per
/// step, one session, 150 rounds, one / two threads), the model 0.991 / 0.987.
#[inline(always)]
pub(crate) fn on_vectors(act: Activation) -> bool {
    matches!(
        act,
        Activation::Silu
            | Activation::Sigmoid
            | Activation::Gelu
            | Activation::GeluTanh
            | Activation::Tanh
            | Activation::Hardswish
            | Activation::Hardsigmoid
    )
}

/// `act` on `N` vectors in registers, for an activation of [`on_vectors`]: a conv's store.
///
/// # Panics
/// For another activation.
#[inline(always)]
pub(crate) fn act_simd<S: Simd, const N: usize>(simd: S, act: Activation, x: [S::f32s; N]) -> [S::f32s; N] {
    match act {
        Activation::Silu => silu_simd(simd, x),
        Activation::Sigmoid => sigmoid_simd(simd, x),
        Activation::Gelu => gelu_simd(simd, x),
        Activation::GeluTanh => gelu_tanh_simd(simd, x),
        Activation::Tanh => tanh_simd(simd, x),
        Activation::Hardswish => hard_simd::<S, N, true>(simd, x),
        Activation::Hardsigmoid => hard_simd::<S, N, false>(simd, x),
        _ => unreachable!("act_simd: {act:?} is not computed on vectors"),
    }
}

/// `out = act(x)` (`x` given) or `out = act(out)`, vector by vector, for the activations
/// of [`on_vectors`]; on the scalar backend, the scalar loops.
struct VectorMap<'a> {
    act: Activation,
    x: Option<&'a [f32]>,
    out: &'a mut [f32],
}

impl pulp::WithSimd for VectorMap<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: Simd>(self, simd: S) {
        let VectorMap { act, x, out } = self;
        if size_of::<S::f32s>() == size_of::<f32>() {
            // One lane: the scalar functions (no software multiply-add).
            return match x {
                Some(x) => map_chunk_loop(act, x, out),
                None => map_chunk_in_place_loop(act, out),
            };
        }
        map_vectors(simd, act, x, out);
    }
}

/// Vectors [`map_vectors`] computes together. SiLU in place over 56x56 planes (AVX-512, 1
/// and 2 threads, alternating calls, 2026-12-06), against the loop over the scalar
/// function: one vector at a time 0.72x its time, four 0.61-0.66x, and with their steps
/// interleaved in the source ([`exp_simd`]) 0.95x that again: one vector's chain of ~25
/// dependent steps leaves the core waiting.
const TOGETHER: usize = 4;

/// `out = act(x)`, or `out = act(out)` without `x` ([`act_simd`]): [`TOGETHER`] vectors at a
/// time, then one at a time, then the last partial one.
#[inline(always)]
fn map_vectors<S: Simd>(simd: S, act: Activation, x: Option<&[f32]>, out: &mut [f32]) {
    let (head, tail) = S::as_mut_simd_f32s(out);
    let tail_in = match x {
        Some(x) => {
            let (xh, xt) = S::as_simd_f32s(x);
            let mut groups = head.chunks_exact_mut(TOGETHER);
            let mut xs = xh.chunks_exact(TOGETHER);
            for (o, v) in (&mut groups).zip(&mut xs) {
                o.copy_from_slice(&act_simd(simd, act, <[S::f32s; TOGETHER]>::try_from(v).expect("a group")));
            }
            for (o, &v) in groups.into_remainder().iter_mut().zip(xs.remainder()) {
                [*o] = act_simd(simd, act, [v]);
            }
            xt
        }
        None => {
            let mut groups = head.chunks_exact_mut(TOGETHER);
            for o in &mut groups {
                let y = act_simd(simd, act, <[S::f32s; TOGETHER]>::try_from(&*o).expect("a group"));
                o.copy_from_slice(&y);
            }
            for o in groups.into_remainder() {
                [*o] = act_simd(simd, act, [*o]);
            }
            &*tail
        }
    };
    if !tail.is_empty() {
        let [y] = act_simd(simd, act, [simd.partial_load_f32s(tail_in)]);
        simd.partial_store_f32s(tail, y);
    }
}

/// [`sigmoid`] on `N` vectors: `1 / (1 + e^-x)`, `-x` clamped to `-87..=89` first so
/// that [`exp_in_range`] needs no clamps or selects of its own: above 87 the result is 1,
/// and from -88.4 down `e^-x` is infinite (its `2^n` is `2^128`, the exponent field's
/// infinity) and the result 0, as at -inf (where [`silu`] is then NaN, as PyTorch's
/// `-inf · 0`). NaN stays NaN. Against the select-based form, `e^-|x|` with the clamps
/// of [`exp_simd`], 0.77x the time of a SiLU pass over EfficientNet-B0's first expansion
/// (one thread, 1.2 M values; the reciprocal estimate and a Newton step instead of the
/// division measured no faster).
#[inline(always)]
pub(crate) fn sigmoid_simd<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let one = simd.splat_f32s(1.0);
    let mut a = x;
    for i in 0..N {
        a[i] = clamp_vector(simd, simd.neg_f32s(x[i]), (-87.0, 89.0));
    }
    let e = exp_in_range(simd, a);
    let mut out = x;
    for i in 0..N {
        out[i] = simd.div_f32s(one, simd.add_f32s(one, e[i]));
    }
    out
}

/// `y` clamped to `lo..=hi` (a ReLU, ReLU6 or clamp, or a function's domain), NaN kept.
#[inline(always)]
pub(crate) fn clamp_vector<S: Simd>(simd: S, y: S::f32s, (lo, hi): (f32, f32)) -> S::f32s {
    // A NaN stays NaN, as the element-wise activations keep it: x86's vector max and
    // min return their second operand when either is NaN, so the bound goes first; the
    // scalar backend's (`f32::max`) drop NaN, so it compares instead (slower on vectors:
    // 1.07-1.15x a depthwise layer's time).
    let vector = size_of::<S::f32s>() > size_of::<f32>();
    let b = simd.splat_f32s(lo);
    let mut y = if vector { simd.max_f32s(b, y) } else { simd.select_f32s(simd.less_than_f32s(y, b), b, y) };
    if hi < f32::INFINITY {
        let b = simd.splat_f32s(hi);
        y = if vector { simd.min_f32s(b, y) } else { simd.select_f32s(simd.greater_than_f32s(y, b), b, y) };
    }
    y
}

/// [`gelu`] on `N` vectors: `0.5 x · erfc(|x| / √2)`, or `2 - erfc` for `x >= 0`, with
/// [`erfc_nr`]'s fit over [`exp_simd`].
#[inline(always)]
pub(crate) fn gelu_simd<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let c = |v: f32| simd.splat_f32s(v);
    let (mut z, mut t, mut p) = (x, x, [c(ERFC_POLY[0]); N]);
    for i in 0..N {
        z[i] = simd.mul_f32s(simd.abs_f32s(x[i]), c(std::f32::consts::FRAC_1_SQRT_2));
        t[i] = simd.div_f32s(c(1.0), simd.mul_add_e_f32s(z[i], c(0.5), c(1.0)));
    }
    for &k in &ERFC_POLY[1..] {
        for i in 0..N {
            p[i] = simd.mul_add_e_f32s(p[i], t[i], c(k));
        }
    }
    let mut arg = x;
    for i in 0..N {
        arg[i] = simd.negate_mul_add_e_f32s(z[i], z[i], p[i]);
    }
    let e = exp_simd(simd, arg);
    let mut out = x;
    for i in 0..N {
        let erfc = simd.mul_f32s(t[i], e[i]);
        let negative = simd.less_than_f32s(x[i], c(0.0));
        let factor = simd.select_f32s(negative, erfc, simd.sub_f32s(c(2.0), erfc));
        out[i] = simd.mul_f32s(simd.mul_f32s(c(0.5), x[i]), factor);
    }
    out
}

/// [`gelu_tanh`] on `N` vectors: `x · sigmoid(2 √(2/π) (x + 0.044715 x³))`.
#[inline(always)]
pub(crate) fn gelu_tanh_simd<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let c = |v: f32| simd.splat_f32s(v);
    let mut u = x;
    for i in 0..N {
        let cube = simd.mul_f32s(simd.mul_f32s(simd.mul_f32s(c(GELU_TANH_CUBIC), x[i]), x[i]), x[i]);
        u[i] = simd.mul_f32s(c(GELU_TANH_SCALE), simd.add_f32s(x[i], cube));
    }
    let mut out = sigmoid_simd(simd, u);
    for i in 0..N {
        out[i] = simd.mul_f32s(x[i], out[i]);
    }
    out
}

/// [`tanh`] on `N` vectors: the odd polynomial for `|x| <` [`TANH_SMALL`], else `sign(x) (1 - e) /
/// (1 + e)` with `e = e^(-2|x|)`.
#[inline(always)]
pub(crate) fn tanh_simd<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let c = |v: f32| simd.splat_f32s(v);
    let mut a = x;
    for i in 0..N {
        a[i] = simd.mul_f32s(c(-2.0), simd.abs_f32s(x[i]));
    }
    let e = exp_simd(simd, a);
    let mut out = x;
    for i in 0..N {
        let big = simd.div_f32s(simd.sub_f32s(c(1.0), e[i]), simd.add_f32s(c(1.0), e[i]));
        // `big` takes `x`'s sign: it is non-negative (or NaN), so an or of the sign bit.
        let sign = simd.and_f32s(x[i], c(-0.0));
        let big = simd.or_f32s(big, sign);
        let x2 = simd.mul_f32s(x[i], x[i]);
        let mut p = c(TANH_POLY[0]);
        for &k in &TANH_POLY[1..] {
            p = simd.mul_add_e_f32s(p, x2, c(k));
        }
        let small = simd.mul_f32s(x[i], p);
        let near = simd.less_than_f32s(simd.abs_f32s(x[i]), c(TANH_SMALL));
        out[i] = simd.select_f32s(near, small, big);
    }
    out
}

/// [`silu`] on `N` vectors: `x · sigmoid(x)`.
#[inline(always)]
pub(crate) fn silu_simd<S: Simd, const N: usize>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let mut out = sigmoid_simd(simd, x);
    for i in 0..N {
        out[i] = simd.mul_f32s(x[i], out[i]);
    }
    out
}

/// [`hardswish`] (`SWISH`) or [`hardsigmoid`] on vectors, in the same order of operations
/// (so the same bits): `relu6(x + 3)`, times `x` for the swish, divided by 6.
#[inline(always)]
fn hard_simd<S: Simd, const N: usize, const SWISH: bool>(simd: S, x: [S::f32s; N]) -> [S::f32s; N] {
    let (three, six) = (simd.splat_f32s(3.0), simd.splat_f32s(6.0));
    let mut out = x;
    for i in 0..N {
        let r = clamp_vector(simd, simd.add_f32s(x[i], three), (0.0, 6.0));
        let r = if SWISH { simd.mul_f32s(x[i], r) } else { r };
        out[i] = simd.div_f32s(r, six);
    }
    out
}

/// `max(x, 0)`, keeping NaN as PyTorch does.
#[inline(always)]
pub(crate) fn relu(x: f32) -> f32 {
    if x < 0.0 { 0.0 } else { x }
}

/// `min(max(x, lo), hi)` with NaN kept (compares, not `f32::max`, which drops NaN).
#[inline(always)]
fn clamp(x: f32, lo: f32, hi: f32) -> f32 {
    let y = if x < lo { lo } else { x };
    if y > hi { hi } else { y }
}

/// `min(max(x, 0), 6)`, NaN kept.
#[inline(always)]
fn relu6(x: f32) -> f32 {
    clamp(x, 0.0, 6.0)
}

/// `x · relu6(x + 3) / 6`, in PyTorch's order of operations.
#[inline(always)]
fn hardswish(x: f32) -> f32 {
    x * relu6(x + 3.0) / 6.0
}

/// `relu6(x + 3) / 6`.
#[inline(always)]
fn hardsigmoid(x: f32) -> f32 {
    relu6(x + 3.0) / 6.0
}

/// `e^x` over the whole f32 range: [`exp_fast`] (within 2 ulp on [-87, 88]), through
/// `e · e^(x-1)` above 88 so it reaches `f32::MAX` and overflows to `inf` past 88.72 as
/// PyTorch's does; 0 below -87 (PyTorch's gives subnormals there, all under 1.7e-38).
#[inline(always)]
fn exp(x: f32) -> f32 {
    let big = x > 88.0;
    let e = exp_fast(if big { x - 1.0 } else { x });
    if big { e * std::f32::consts::E } else { e }
}

/// `e^x - 1` without cancelling near 0: its Taylor series to `x^8` for `|x| < 0.5`
/// (truncation below 1.5e-11 relative), else `exp(x) - 1`.
#[inline(always)]
fn expm1(x: f32) -> f32 {
    let mut p = 1.0 / 40320.0;
    p = p * x + 1.0 / 5040.0;
    p = p * x + 1.0 / 720.0;
    p = p * x + 1.0 / 120.0;
    p = p * x + 1.0 / 24.0;
    p = p * x + 1.0 / 6.0;
    p = p * x + 0.5;
    // `x (1 + x p)` rather than `x + x² p` keeps the sign of -0.
    let small = x * (1.0 + x * p);
    if x.abs() < 0.5 { small } else { exp(x) - 1.0 }
}

/// The natural logarithm, Cephes' `logf`: `x = m · 2^e` with `m` in `[√½, √2)` from the
/// bits (subnormals scaled by 2^23 first), `ln m` by its degree-9 polynomial in `m - 1`,
/// plus `e ln 2` in two parts. NaN for negative `x` and NaN, `-inf` for ±0, `inf` for
/// `inf`. Branch-free, so the loop vectorises.
#[inline(always)]
fn log(x: f32) -> f32 {
    let sub = x < f32::MIN_POSITIVE;
    let xs = if sub { x * 8_388_608.0 } else { x };
    let bits = xs.to_bits();
    // Exponent and mantissa in [1, 2), then moved to [√½, √2).
    let mut e = ((bits >> 23) & 0xff) as i32 - 127;
    let mut m = f32::from_bits((bits & 0x007f_ffff) | 0x3f80_0000);
    let high = m > std::f32::consts::SQRT_2;
    if high {
        m *= 0.5;
        e += 1;
    }
    let e = e as f32 - if sub { 23.0 } else { 0.0 };
    let z = m - 1.0;
    let mut p = 7.037_683_6e-2;
    p = p * z - 1.151_461e-1;
    p = p * z + 1.167_699_9e-1;
    p = p * z - 1.242_014_1e-1;
    p = p * z + 1.424_932_3e-1;
    p = p * z - 1.666_805_8e-1;
    p = p * z + 2.000_071_5e-1;
    p = p * z - 2.499_999_4e-1;
    p = p * z + 3.333_333e-1;
    let z2 = z * z;
    let r = z + (z * z2 * p + e * -2.121_944_4e-4 - 0.5 * z2);
    let y = r + e * 0.693_359_4;
    if x > 0.0 && x < f32::INFINITY {
        y
    } else if x == 0.0 {
        f32::NEG_INFINITY
    } else if x == f32::INFINITY {
        x
    } else {
        f32::NAN
    }
}

/// The error function: its Maclaurin series to `x^13` for `|x| < 0.5` (truncation below
/// 1e-9 relative), else `±(1 - erfc(|x|))` with the Chebyshev `erfc` GELU uses (relative
/// error below 1.2e-7, so below 1.2e-7 absolute on `erf`'s values of at least 0.52 there).
#[inline(always)]
fn erf(x: f32) -> f32 {
    let x2 = x * x;
    let mut p = -1.0 / 75_600.0;
    p = p * x2 + 1.0 / 9_360.0;
    p = p * x2 - 1.0 / 1_320.0;
    p = p * x2 + 1.0 / 216.0;
    p = p * x2 - 1.0 / 42.0;
    p = p * x2 + 1.0 / 10.0;
    p = p * x2 - 1.0 / 3.0;
    p = p * x2 + 1.0;
    let small = std::f32::consts::FRAC_2_SQRT_PI * x * p;
    let big = (1.0 - erfc_nr(x.abs())).copysign(x);
    if x.abs() < 0.5 { small } else { big }
}

/// `0.5 x (1 + erf(x / √2))`, as PyTorch's default GELU.
///
/// `1 + erf(x / √2)` is `erfc(|x| / √2)` for negative `x` and `2 - erfc(x / √2)` otherwise,
/// with `erfc` from Numerical Recipes' Chebyshev fit (relative error below 1.2e-7) over the
/// vectorisable `exp_fast`: no libm call, so the loop vectorises, and the negative tail
/// keeps its relative accuracy instead of cancelling to 0.
#[inline(always)]
fn gelu(x: f32) -> f32 {
    let erfc = erfc_abs_sqrt1_2(x);
    0.5 * x * if x < 0.0 { erfc } else { 2.0 - erfc }
}

/// `erfc(|x| / √2)`. Kept a separate function: written inline in `gelu`, LLVM declined
/// to vectorise the loop (3 ns instead of 0.7 ns per element, measured).
#[inline(always)]
fn erfc_abs_sqrt1_2(x: f32) -> f32 {
    erfc_nr(x.abs() * std::f32::consts::FRAC_1_SQRT_2)
}

/// `erfc(z)` for `z >= 0`, Numerical Recipes' Chebyshev fit over [`exp_fast`].
#[inline(always)]
fn erfc_nr(z: f32) -> f32 {
    let t = 1.0 / (1.0 + 0.5 * z);
    let mut p = ERFC_POLY[0];
    for &k in &ERFC_POLY[1..] {
        p = p * t + k;
    }
    t * exp_fast(p - z * z)
}

/// [`erfc_nr`]'s polynomial in `t`, highest power first.
const ERFC_POLY: [f32; 10] = [
    0.170_872_77,
    -0.822_152_2,
    1.488_515_9,
    -1.135_204,
    0.278_868_07,
    -0.186_288_06,
    0.096_784_18,
    0.374_091_96,
    1.000_023_7,
    -1.265_512_2,
];

/// `0.5 x (1 + tanh(√(2/π) (x + 0.044715 x³)))`, PyTorch's `approximate='tanh'`, evaluated
/// as the equal `x · sigmoid(2 √(2/π) (x + 0.044715 x³))`.
#[inline(always)]
fn gelu_tanh(x: f32) -> f32 {
    x * sigmoid(GELU_TANH_SCALE * (x + GELU_TANH_CUBIC * x * x * x))
}

/// [`gelu_tanh`]'s `2 √(2/π)`, the sigmoid form's argument scale.
const GELU_TANH_SCALE: f32 = 1.595_769;

/// [`gelu_tanh`]'s cubic coefficient (PyTorch's `0.044715`).
const GELU_TANH_CUBIC: f32 = 0.044715;

/// `1 / (1 + e^-x)`, through `e^-|x|` so nothing overflows: exact to a few ulp, 0 below
/// x = -87 (where the true value is under 1.7e-38), NaN for NaN.
#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    let e = exp_fast(-x.abs());
    let s = 1.0 / (1.0 + e);
    if x < 0.0 { e * s } else { s }
}

/// `tanh(x)`: the odd Taylor polynomial to `x^9` for `|x| < 0.25` (error below 1e-8
/// relative), else `sign(x) (1 - e) / (1 + e)` with `e = e^(-2|x|)`, which cannot overflow;
/// ±1 beyond |x| ≈ 9, NaN for NaN. Branch-free, so the loop vectorises. (Below 0.25, `1 - e`
/// would cancel: `e`'s error grows by `e / (1 - e)`, 4.5x at 0.1.)
#[inline(always)]
fn tanh(x: f32) -> f32 {
    let a = x.abs();
    let e = exp_fast(-2.0 * a);
    let big = (1.0 - e) / (1.0 + e);
    let x2 = x * x;
    let mut p = TANH_POLY[0];
    for &k in &TANH_POLY[1..] {
        p = p * x2 + k;
    }
    if a < TANH_SMALL { x * p } else { big.copysign(x) }
}

/// Below this `|x|`, [`tanh`] is its Taylor polynomial.
const TANH_SMALL: f32 = 0.25;

/// [`tanh`]'s Taylor polynomial in `x²` (times `x`), highest power first: `62/2835`,
/// `-17/315`, `2/15`, `-1/3`, `1`.
const TANH_POLY: [f32; 5] = [62.0 / 2835.0, -17.0 / 315.0, 2.0 / 15.0, -1.0 / 3.0, 1.0];

/// `x * sigmoid(x)` (PyTorch's `silu`).
#[inline(always)]
fn silu(x: f32) -> f32 {
    x * sigmoid(x)
}

/// Runs `f(start, chunk)` over `out` in chunks, in parallel when `out` is large; `start` is
/// the chunk's offset in `out`.
fn par_ranges<F: Fn(usize, &mut [f32]) + Sync>(out: &mut [f32], f: F) {
    if out.len() >= PAR_MIN {
        out.par_chunks_mut(CHUNK).enumerate().for_each(|(i, o)| f(i * CHUNK, o));
    } else {
        f(0, out);
    }
}

/// Expands `$body` once per operation, with `$f` bound to that operation as a function
/// item, so `op` is matched once, outside the loop, and each loop is compiled (and
/// vectorised) on its own.
macro_rules! per_op {
    ($op:expr, $f:ident => $body:expr) => {
        match $op {
            BinaryOp::Add => {
                let $f = add;
                $body
            }
            BinaryOp::Sub => {
                let $f = sub;
                $body
            }
            BinaryOp::Mul => {
                let $f = mul;
                $body
            }
            BinaryOp::Div => {
                let $f = div;
                $body
            }
            BinaryOp::Pow => {
                let $f = f32::powf;
                $body
            }
            BinaryOp::Eq => {
                let $f = eq;
                $body
            }
            BinaryOp::Ne => {
                let $f = ne;
                $body
            }
            BinaryOp::Lt => {
                let $f = lt;
                $body
            }
            BinaryOp::Le => {
                let $f = le;
                $body
            }
            BinaryOp::Gt => {
                let $f = gt;
                $body
            }
            BinaryOp::Ge => {
                let $f = ge;
                $body
            }
            BinaryOp::Maximum => {
                let $f = readi_plan::ops::maximum;
                $body
            }
            BinaryOp::Minimum => {
                let $f = readi_plan::ops::minimum;
                $body
            }
            BinaryOp::FloorDiv => {
                let $f = readi_plan::ops::floor_divide;
                $body
            }
            BinaryOp::Remainder => {
                let $f = readi_plan::ops::remainder;
                $body
            }
            BinaryOp::Atan2 => {
                let $f = f32::atan2;
                $body
            }
        }
    };
}

/// A comparison's value: 1 where it holds, 0 where not (a select, which vectorises).
macro_rules! comparison {
    ($name:ident, $op:tt) => {
        #[inline(always)]
        fn $name(x: f32, y: f32) -> f32 {
            if x $op y { 1.0 } else { 0.0 }
        }
    };
}
comparison!(eq, ==);
comparison!(ne, !=);
comparison!(lt, <);
comparison!(le, <=);
comparison!(gt, >);
comparison!(ge, >=);

#[inline(always)]
fn add(x: f32, y: f32) -> f32 {
    x + y
}

#[inline(always)]
fn sub(x: f32, y: f32) -> f32 {
    x - y
}

#[inline(always)]
fn mul(x: f32, y: f32) -> f32 {
    x * y
}

#[inline(always)]
fn div(x: f32, y: f32) -> f32 {
    x / y
}

/// `out[i] = a[i] op b[i]`.
#[inline(always)]
fn vv(op: BinaryOp, a: &[f32], b: &[f32], out: &mut [f32]) {
    let (a, b) = (&a[..out.len()], &b[..out.len()]);
    per_op!(op, f => {
        for ((o, &x), &y) in out.iter_mut().zip(a).zip(b) {
            *o = f(x, y);
        }
    })
}

/// `out[i] = a[i] op s`.
#[inline(always)]
fn vs(op: BinaryOp, a: &[f32], s: f32, out: &mut [f32]) {
    let a = &a[..out.len()];
    per_op!(op, f => {
        for (o, &x) in out.iter_mut().zip(a) {
            *o = f(x, s);
        }
    })
}

/// `out[i] = s op b[i]`.
#[inline(always)]
fn sv(op: BinaryOp, s: f32, b: &[f32], out: &mut [f32]) {
    let b = &b[..out.len()];
    per_op!(op, f => {
        for (o, &y) in out.iter_mut().zip(b) {
            *o = f(s, y);
        }
    })
}

simd_fn! {
    /// [`vv`], vectorised.
    fn vv_simd(op: BinaryOp, a: &[f32], b: &[f32], out: &mut [f32]) {
        vv(op, a, b, out)
    }
}

simd_fn! {
    /// [`vs`] or, if `scalar_first`, [`sv`], vectorised.
    fn scalar_simd(op: BinaryOp, x: &[f32], value: f32, scalar_first: bool, out: &mut [f32]) {
        if scalar_first { sv(op, value, x, out) } else { vs(op, x, value, out) }
    }
}

simd_fn! {
    /// [`Broadcast::run`], vectorised.
    fn broadcast_simd(plan: &Broadcast, op: BinaryOp, a: &[f32], b: &[f32], start: usize, out: &mut [f32]) {
        plan.run(op, a, b, start, out)
    }
}

/// The strides of an operand of shape `shape` over the axes of `out_shape` (right-aligned,
/// NumPy's rule); 0 where it broadcasts.
///
/// # Panics
/// If `shape` does not broadcast to `out_shape`.
pub(crate) fn broadcast_strides(shape: &[usize], out_shape: &[usize]) -> Vec<usize> {
    let rank = out_shape.len();
    assert!(shape.len() <= rank, "broadcast: {shape:?} has more axes than {out_shape:?}");
    let mut s = vec![0; rank];
    let mut acc = 1;
    for (i, &n) in shape.iter().enumerate().rev() {
        let axis = rank - shape.len() + i;
        assert!(n == out_shape[axis] || n == 1, "broadcast: {shape:?} does not broadcast to {out_shape:?}");
        if n != 1 {
            s[axis] = acc;
        }
        acc *= n;
    }
    s
}

/// A broadcast reduced to the fewest axes: size-1 output axes dropped, neighbours that
/// broadcast alike in both operands merged. Innermost strides are 0 or 1.
struct Broadcast {
    dims: Vec<usize>,
    a_strides: Vec<usize>,
    b_strides: Vec<usize>,
}

impl Broadcast {
    fn new(a_shape: &[usize], b_shape: &[usize], out_shape: &[usize]) -> Broadcast {
        let rank = out_shape.len();
        assert!(a_shape.len() <= rank && b_shape.len() <= rank, "binary: input rank exceeds output rank");
        let (sa, sb) = (broadcast_strides(a_shape, out_shape), broadcast_strides(b_shape, out_shape));
        let mut dims: Vec<usize> = Vec::with_capacity(rank);
        let (mut a_strides, mut b_strides): (Vec<usize>, Vec<usize>) = (Vec::new(), Vec::new());
        for axis in 0..rank {
            let n = out_shape[axis];
            if n == 1 {
                continue;
            }
            if let (Some(&m), Some(&pa), Some(&pb)) = (dims.last(), a_strides.last(), b_strides.last()) {
                // The previous axis merges with this one if it continues both operands' strides.
                if pa == sa[axis] * n && pb == sb[axis] * n {
                    let last = dims.len() - 1;
                    dims[last] = m * n;
                    a_strides[last] = sa[axis];
                    b_strides[last] = sb[axis];
                    continue;
                }
            }
            dims.push(n);
            a_strides.push(sa[axis]);
            b_strides.push(sb[axis]);
        }
        if dims.is_empty() {
            dims.push(1);
            a_strides.push(0);
            b_strides.push(0);
        }
        Broadcast { dims, a_strides, b_strides }
    }

    /// Writes output elements `start..start + out.len()`.
    #[inline(always)]
    fn run(&self, op: BinaryOp, a: &[f32], b: &[f32], start: usize, out: &mut [f32]) {
        let r = self.dims.len();
        let inner = self.dims[r - 1];
        let (ia, ib) = (self.a_strides[r - 1], self.b_strides[r - 1]);
        // Multi-index of `start` and the operand offsets there.
        let mut idx = vec![0; r];
        let mut rem = start;
        for d in (0..r).rev() {
            idx[d] = rem % self.dims[d];
            rem /= self.dims[d];
        }
        let mut ao: usize = (0..r).map(|d| idx[d] * self.a_strides[d]).sum();
        let mut bo: usize = (0..r).map(|d| idx[d] * self.b_strides[d]).sum();
        let mut done = 0;
        while done < out.len() {
            let n = (inner - idx[r - 1]).min(out.len() - done);
            let o = &mut out[done..done + n];
            match (ia, ib) {
                (0, 0) => o.fill(per_op!(op, f => f(a[ao], b[bo]))),
                (0, _) => sv(op, a[ao], &b[bo..bo + n], o),
                (_, 0) => vs(op, &a[ao..ao + n], b[bo], o),
                _ => vv(op, &a[ao..ao + n], &b[bo..bo + n], o),
            }
            done += n;
            idx[r - 1] += n;
            ao += n * ia;
            bo += n * ib;
            if idx[r - 1] < inner {
                continue;
            }
            // Carry into the outer axes.
            for d in (0..r).rev() {
                if idx[d] < self.dims[d] {
                    break;
                }
                ao -= self.dims[d] * self.a_strides[d];
                bo -= self.dims[d] * self.b_strides[d];
                idx[d] = 0;
                if d > 0 {
                    idx[d - 1] += 1;
                    ao += self.a_strides[d - 1];
                    bo += self.b_strides[d - 1];
                }
            }
        }
    }
}

/// The preconditions of [`binary`]: each operand's rank at most the output's, and each
/// of its axes (right-aligned) equal to the output's or 1.
pub fn check_binary(a: &[usize], b: &[usize], out: &[usize]) -> Result<(), String> {
    let fits =
        |s: &[usize]| s.len() <= out.len() && s.iter().rev().zip(out.iter().rev()).all(|(&d, &o)| d == o || d == 1);
    if !fits(a) || !fits(b) {
        return Err(format!("{a:?} and {b:?} do not broadcast to {out:?}"));
    }
    Ok(())
}

/// The preconditions of [`scalar`] and [`activation`] (and of a reshape's copy): the
/// output has the input's length.
pub fn check_same_length(x: &[usize], out: &[usize]) -> Result<(), String> {
    if x.iter().product::<usize>() != out.iter().product::<usize>() {
        return Err(format!("output {out:?} does not have the length of input {x:?}"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kernels::testutil::{assert_close, backends, data};

    fn apply(op: BinaryOp, x: f32, y: f32) -> f32 {
        match op {
            BinaryOp::Add => x + y,
            BinaryOp::Sub => x - y,
            BinaryOp::Mul => x * y,
            BinaryOp::Div => x / y,
            BinaryOp::Pow => x.powf(y),
            // Written independently of the kernel's select.
            BinaryOp::Eq => f32::from(u8::from(x == y)),
            BinaryOp::Ne => f32::from(u8::from(x != y)),
            BinaryOp::Lt => f32::from(u8::from(x < y)),
            BinaryOp::Le => f32::from(u8::from(x <= y)),
            BinaryOp::Gt => f32::from(u8::from(x > y)),
            BinaryOp::Ge => f32::from(u8::from(x >= y)),
            BinaryOp::Maximum | BinaryOp::Minimum | BinaryOp::FloorDiv | BinaryOp::Remainder | BinaryOp::Atan2 => {
                reference(op, x, y)
            }
        }
    }

    /// The operations added with run-time indices, in f64 from their definitions
    /// (Python's `//` and `%`, C's `atan2`), independent of the kernel's f32 formulas.
    fn reference(op: BinaryOp, x: f32, y: f32) -> f32 {
        let (a, b) = (f64::from(x), f64::from(y));
        let nan = x.is_nan() || y.is_nan();
        (match op {
            BinaryOp::Maximum if nan => f64::NAN,
            BinaryOp::Minimum if nan => f64::NAN,
            BinaryOp::Maximum => a.max(b),
            BinaryOp::Minimum => a.min(b),
            BinaryOp::FloorDiv => (a / b).floor(),
            BinaryOp::Remainder => a - b * (a / b).floor(),
            BinaryOp::Atan2 => a.atan2(b),
            _ => unreachable!("{op:?}"),
        }) as f32
    }

    #[test]
    fn maximum_minimum_floor_divide_remainder_atan2_match_their_definitions() {
        let added = [BinaryOp::Maximum, BinaryOp::Minimum, BinaryOp::FloorDiv, BinaryOp::Remainder, BinaryOp::Atan2];
        let (a_shape, b_shape, out_shape) = ([2, 3, 40], [3, 1], [2, 3, 40]);
        let a: Vec<f32> = data(240, 5).iter().map(|v| v * 7.0).collect();
        let mut b: Vec<f32> = data(3, 6).iter().map(|v| v * 3.0 + 0.25).collect();
        b[1] = -b[1].abs() - 0.5;
        for op in added {
            let want: Vec<f32> = (0..240).map(|i| reference(op, a[i], b[(i / 40) % 3])).collect();
            let mut got = vec![f32::NAN; 240];
            binary(op, &a, &a_shape, &b, &b_shape, &mut got, &out_shape);
            assert_close(&got, &want, 1e-6);
            scalar(op, &a, -2.5, false, &mut got);
            let want: Vec<f32> = a.iter().map(|&v| reference(op, v, -2.5)).collect();
            assert_close(&got, &want, 1e-6);
        }
        // Integers (as f32) divide exactly: flat indices of a [3, 64] map to class, cell.
        let idx: Vec<f32> = (0..192).map(|i| i as f32).collect();
        let mut q = vec![0.0; 192];
        let mut r = vec![0.0; 192];
        scalar(BinaryOp::FloorDiv, &idx, 64.0, false, &mut q);
        scalar(BinaryOp::Remainder, &idx, 64.0, false, &mut r);
        for i in 0..192 {
            assert_eq!((q[i], r[i]), ((i / 64) as f32, (i % 64) as f32), "{i}");
        }
        // NaN propagates through maximum and minimum from either side.
        let mut o = [0.0; 2];
        binary(BinaryOp::Maximum, &[f32::NAN, 1.0], &[2], &[0.0, f32::NAN], &[2], &mut o, &[2]);
        assert!(o[0].is_nan() && o[1].is_nan(), "{o:?}");
    }

    /// Plain broadcasting: for every output multi-index, index each operand with its
    /// right-aligned axes, using 0 on size-1 axes.
    fn naive_binary(
        op: BinaryOp,
        a: &[f32],
        a_shape: &[usize],
        b: &[f32],
        b_shape: &[usize],
        out_shape: &[usize],
    ) -> Vec<f32> {
        let rank = out_shape.len();
        let len: usize = out_shape.iter().product();
        let offset = |shape: &[usize], idx: &[usize]| -> usize {
            let skip = rank - shape.len();
            shape.iter().enumerate().fold(0, |o, (i, &n)| o * n + if n == 1 { 0 } else { idx[skip + i] })
        };
        (0..len)
            .map(|flat| {
                let mut idx = vec![0; rank];
                let mut r = flat;
                for d in (0..rank).rev() {
                    idx[d] = r % out_shape[d];
                    r /= out_shape[d];
                }
                apply(op, a[offset(a_shape, &idx)], b[offset(b_shape, &idx)])
            })
            .collect()
    }

    fn broadcast_shape(a: &[usize], b: &[usize]) -> Vec<usize> {
        let rank = a.len().max(b.len());
        let at = |s: &[usize], i: usize| if i + s.len() >= rank { s[i + s.len() - rank] } else { 1 };
        (0..rank).map(|i| at(a, i).max(at(b, i))).collect()
    }

    fn check(a_shape: &[usize], b_shape: &[usize]) {
        let out_shape = broadcast_shape(a_shape, b_shape);
        let a = data(a_shape.iter().product(), 1);
        // Keep b away from 0 so Div is well conditioned.
        let b: Vec<f32> = data(b_shape.iter().product(), 2).iter().map(|v| v + 2.0).collect();
        for op in [BinaryOp::Add, BinaryOp::Sub, BinaryOp::Mul, BinaryOp::Div] {
            let want = naive_binary(op, &a, a_shape, &b, b_shape, &out_shape);
            let mut got = vec![f32::NAN; want.len()];
            binary(op, &a, a_shape, &b, b_shape, &mut got, &out_shape);
            assert_eq!(got, want, "{op:?} {a_shape:?} {b_shape:?}");
        }
    }

    #[test]
    fn binary_same_shape_and_fast_paths() {
        check(&[2, 3, 4, 5], &[2, 3, 4, 5]);
        check(&[2, 3, 4, 5], &[1, 3, 1, 1]);
        check(&[2, 3, 4, 5], &[3, 1, 1]);
        check(&[2, 7, 6], &[1, 7, 6]);
        check(&[2, 7, 6], &[7, 6]);
        check(&[2, 7, 6], &[6]);
        check(&[2, 7, 6], &[2, 1, 1]);
        check(&[2, 7, 6], &[2, 7, 1]);
    }

    #[test]
    fn binary_broadcasts_in_every_direction() {
        // a broadcast instead of b, both broadcast, scalars, middle axes, rank 0 and 1.
        check(&[1, 3, 1, 1], &[2, 3, 4, 5]);
        check(&[4, 1], &[1, 5]);
        check(&[1, 5], &[4, 1]);
        check(&[3, 1, 5], &[1, 4, 1]);
        check(&[2, 1, 4, 1], &[3, 1, 5]);
        check(&[2, 3, 4], &[1]);
        check(&[1], &[2, 3, 4]);
        check(&[], &[2, 3]);
        check(&[2, 3], &[]);
        check(&[], &[]);
        check(&[1, 1], &[1]);
        check(&[5, 1, 1, 3], &[1, 2, 2, 1]);
    }

    #[test]
    fn binary_large_broadcast_runs_in_parallel_and_matches() {
        check(&[2, 16, 48, 40], &[1, 16, 1, 1]);
        check(&[3, 100, 130], &[1, 100, 130]);
        check(&[100, 1, 400], &[1, 3, 400]);
        check(&[40000], &[40000]);
    }

    #[test]
    fn binary_empty_output() {
        let mut out: [f32; 0] = [];
        binary(BinaryOp::Add, &[], &[0, 3], &[1.0, 2.0, 3.0], &[3], &mut out, &[0, 3]);
    }

    #[test]
    fn scalar_both_orders() {
        let x = data(50_000, 3);
        for op in [BinaryOp::Add, BinaryOp::Sub, BinaryOp::Mul, BinaryOp::Div] {
            let mut got = vec![0.0; x.len()];
            scalar(op, &x, 3.0, false, &mut got);
            let want: Vec<f32> = x.iter().map(|&v| apply(op, v, 3.0)).collect();
            assert_eq!(got, want, "{op:?}");
            scalar(op, &x, 3.0, true, &mut got);
            let want: Vec<f32> = x.iter().map(|&v| apply(op, 3.0, v)).collect();
            assert_eq!(got, want, "{op:?} scalar_first");
        }
    }

    #[test]
    fn relu_and_in_place_agree() {
        let x: Vec<f32> = data(40_000, 4).iter().map(|v| v * 5.0).collect();
        let mut got = vec![0.0; x.len()];
        activation(Activation::Relu, &x, &mut got);
        let want: Vec<f32> = x.iter().map(|&v| if v > 0.0 { v } else { 0.0 }).collect();
        assert_eq!(got, want);
        for act in Activation::ALL {
            activation(act, &x, &mut got);
            let mut inplace = x.clone();
            activation_in_place(act, &mut inplace);
            let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert!(bits(&inplace) == bits(&got), "{act:?}");
        }
    }

    #[test]
    fn gelu_matches_f64_reference() {
        // A dense grid over [-12, 12], plus values near 0.
        let mut x: Vec<f32> = (-24_000..=24_000).map(|i| i as f32 * 5e-4).collect();
        x.extend(data(1000, 5).iter().map(|v| v * 1e-3));
        let mut got = vec![0.0; x.len()];
        activation(Activation::Gelu, &x, &mut got);
        let want: Vec<f32> = x
            .iter()
            .map(|&v| (0.5 * v as f64 * (1.0 + libm::erf(v as f64 / std::f64::consts::SQRT_2))) as f32)
            .collect();
        assert_close(&got, &want, 1e-6);
        activation(Activation::GeluTanh, &x, &mut got);
        let want: Vec<f32> = x
            .iter()
            .map(|&v| {
                let v = v as f64;
                let inner = (2.0 / std::f64::consts::PI).sqrt() * (v + 0.044715 * v * v * v);
                (0.5 * v * (1.0 + inner.tanh())) as f32
            })
            .collect();
        assert_close(&got, &want, 1e-6);
    }

    #[test]
    fn gelu_matches_pytorch() {
        let x = [-6.0, -3.0, -1.5, -0.5, -1e-3, 0.0, 1e-3, 0.5, 1.0, 2.5, 5.0];
        // torch.nn.functional.gelu(torch.tensor(x)).tolist()
        let erf = [
            -0.0,
            -0.004050225,
            -0.10021086,
            -0.15426877,
            -0.00049960107,
            0.0,
            0.000500399,
            0.34573123,
            0.8413447,
            2.4844759,
            4.999999,
        ];
        // torch.nn.functional.gelu(torch.tensor(x), approximate='tanh').tolist()
        let tanh = [
            -0.0,
            -0.003637433,
            -0.10042843,
            -0.154286,
            -0.00049960107,
            0.0,
            0.000500399,
            0.345714,
            0.841192,
            2.4849157,
            4.9999995,
        ];
        let mut got = [0.0; 11];
        activation(Activation::Gelu, &x, &mut got);
        assert_close(&got, &erf, 1e-6);
        activation(Activation::GeluTanh, &x, &mut got);
        assert_close(&got, &tanh, 1e-6);
    }

    #[test]
    fn sigmoid_is_safe_at_large_magnitudes() {
        let x = [-200.0, -100.0, -86.0, -20.0, -1.0, 0.0, 1.0, 20.0, 100.0, f32::INFINITY, f32::NEG_INFINITY];
        let mut got = [0.0; 11];
        activation(Activation::Sigmoid, &x, &mut got);
        let want: Vec<f32> = x.iter().map(|&v| (1.0 / (1.0 + (-(v as f64)).exp())) as f32).collect();
        assert_close(&got, &want, 1e-6);
        // Relative accuracy holds in the tail down to -87: sigmoid(-20) = 2.0611537e-9.
        assert!((got[3] / 2.061_153_6e-9 - 1.0).abs() < 1e-5, "sigmoid(-20) = {}", got[3]);
        assert!(got[2] > 0.0);
        assert!(got.iter().all(|v| (0.0..=1.0).contains(v)));
        let mut nan = [f32::NAN];
        activation_in_place(Activation::Sigmoid, &mut nan);
        assert!(nan[0].is_nan());
    }

    #[test]
    fn every_activation_matches_its_f64_formula() {
        // A dense grid over [-12, 12], values near 0 and the extremes.
        let mut x: Vec<f32> = (-24_000..=24_000).map(|i| i as f32 * 5e-4).collect();
        x.extend(data(1000, 6).iter().map(|v| v * 1e-3));
        x.extend([-100.0, -30.0, 30.0, 100.0, 0.1, -0.1, 0.099_999_99]);
        for act in Activation::ALL {
            let mut got = vec![0.0; x.len()];
            activation(act, &x, &mut got);
            let want: Vec<f32> = x.iter().map(|&v| act.reference(v as f64) as f32).collect();
            // Where the function is NaN (log, sqrt of negatives) the kernel must be too.
            let nan = |v: &[f32]| v.iter().map(|v| v.is_nan()).collect::<Vec<_>>();
            assert_eq!(nan(&got), nan(&want), "{act:?}: NaN at other points");
            let keep = |v: &[f32]| v.iter().zip(&want).filter(|w| w.1.is_finite()).map(|w| *w.0).collect::<Vec<_>>();
            let (got, want) = (keep(&got), keep(&want));
            // `exp` reaches 1.6e5 on this grid: compare relative to the value.
            assert_close(&got, &want, 1e-6);
        }
    }

    /// Largest relative error of `act` over `x` against its f64 formula (absolute below
    /// 1e-30, where f32 has lost its precision anyway), after checking NaN and infinities
    /// land where the formula's do.
    fn max_rel_error(act: Activation, x: &[f32]) -> f64 {
        let mut got = vec![0.0; x.len()];
        activation(act, x, &mut got);
        rel_error(act, x, &got)
    }

    /// [`max_rel_error`] of `got`, computed from `x`.
    fn rel_error(act: Activation, x: &[f32], got: &[f32]) -> f64 {
        let mut worst = 0.0f64;
        for (&v, &g) in x.iter().zip(got) {
            let w = act.reference(v as f64);
            let wf = w as f32;
            if wf.is_nan() || wf.is_infinite() {
                assert!(g.is_nan() == wf.is_nan() && (wf.is_nan() || g == wf), "{act:?}({v}) = {g}, want {w}");
                continue;
            }
            let err = (g as f64 - w).abs();
            worst = worst.max(if w.abs() > 1e-30 { err / w.abs() } else { err });
        }
        worst
    }

    #[test]
    fn unary_functions_within_a_few_ulp() {
        // A dense grid over [-12, 12], tiny values, and for the functions of positive
        // numbers every power of two's neighbourhood from 1e-45 (subnormal) to 3e38.
        let mut x: Vec<f32> = (-48_000..=48_000).map(|i| i as f32 * 2.5e-4).collect();
        x.extend(data(2000, 9).iter().map(|v| v * 1e-3));
        x.extend([-0.0, 0.0, 0.499_999_97, 0.5, -0.5, f32::MIN_POSITIVE, f32::MAX, -f32::MAX, 1e-45]);
        x.extend([f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 87.0, 88.0, 88.5, 88.72, 88.73, 100.0, -100.0]);
        // Where the sigmoid's clamped `e^-x` turns infinite.
        x.extend([-86.9, -87.0, -87.1, -88.3, -88.4, -88.5, -88.8, -89.0, -89.1]);
        let mut pos: Vec<f32> = Vec::new();
        let mut v = 1e-45f32;
        while v < 3e38 {
            pos.extend([v, v * 1.1, v * 1.414, v * 1.5, v * 1.9]);
            v *= 2.0;
        }
        x.extend(&pos);
        // (function, bound on the relative error, measured: 1 ulp of f32 is 6e-8 to 1.2e-7)
        let bounds = [
            (Activation::Exp, 1.5e-7),
            (Activation::Log, 1.2e-7),
            (Activation::Sqrt, 6.0e-8),
            (Activation::Rsqrt, 1.2e-7),
            (Activation::Abs, 0.0),
            (Activation::Neg, 0.0),
            (Activation::Erf, 3.0e-7),
            (Activation::Tanh, 3.0e-7),
            (Activation::Sigmoid, 2.5e-7),
            (Activation::Silu, 3.0e-7),
            (Activation::Elu { alpha: 1.0 }, 1.5e-7),
            (Activation::Relu6, 0.0),
            (Activation::Clamp { min: Some(-0.25), max: Some(2.0) }, 0.0),
            (Activation::LeakyRelu { negative_slope: 0.01 }, 6.0e-8),
            (Activation::Hardswish, 1.8e-7),
            (Activation::Hardsigmoid, 1.2e-7),
        ];
        for (act, bound) in bounds {
            // `exp` only where it does not flush to 0 (below -87, documented).
            // `hardswish` only below 5e37: above, `x · 6` overflows to inf before the division,
            // in PyTorch's kernel as in ours (torch.nn.functional.hardswish(3e38) is inf).
            let xs: Vec<f32> = x
                .iter()
                .copied()
                .filter(|&v| act != Activation::Exp || v.is_nan() || v >= -87.0)
                .filter(|&v| act != Activation::Hardswish || v.is_nan() || v.abs() <= 5e37)
                .collect();
            let err = max_rel_error(act, &xs);
            eprintln!("{act:?}: max relative error {err:e}");
            assert!(err <= bound, "{act:?}: max relative error {err:e} > {bound:e}");
        }
    }

    #[test]
    fn unary_functions_at_hand_derived_points() {
        let nan = f32::NAN;
        let x = [nan, f32::NEG_INFINITY, -7.0, -3.0, -1.0, -0.0, 0.0, 1.0, 3.0, 6.0, 7.0, f32::INFINITY];
        let check = |act: Activation, want: [f32; 12]| {
            let mut got = [0.0; 12];
            activation(act, &x, &mut got);
            for ((g, w), v) in got.iter().zip(want).zip(x) {
                // Exact where the value is exact (signed zeros included); within 2 ulp of a
                // transcendental value rounded from f64.
                let near = w.is_finite() && w != 0.0 && (g - w).abs() <= 2.4e-7 * w.abs();
                assert!(
                    g.to_bits() == w.to_bits() || near || (g.is_nan() && w.is_nan()),
                    "{act:?}({v}) = {g}, want {w}"
                );
            }
        };
        check(Activation::Relu6, [nan, 0.0, 0.0, 0.0, 0.0, -0.0, 0.0, 1.0, 3.0, 6.0, 6.0, 6.0]);
        let hardtanh = Activation::Clamp { min: Some(-1.0), max: Some(1.0) };
        check(hardtanh, [nan, -1.0, -1.0, -1.0, -1.0, -0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 1.0]);
        let at_least = Activation::Clamp { min: Some(-3.0), max: None };
        let inf = f32::INFINITY;
        check(at_least, [nan, -3.0, -3.0, -3.0, -1.0, -0.0, 0.0, 1.0, 3.0, 6.0, 7.0, inf]);
        // min > max: every value is max, as torch.clamp(x, min=2, max=1).
        check(
            Activation::Clamp { min: Some(2.0), max: Some(1.0) },
            [nan, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
        );
        // hardswish(-3) = -3 · 0 / 6 = -0, hardswish(-inf) = -inf · 0 = NaN (torch too).
        check(Activation::Hardswish, [nan, nan, -0.0, -0.0, -2.0 / 6.0, -0.0, 0.0, 4.0 / 6.0, 3.0, 6.0, 7.0, inf]);
        check(Activation::Hardsigmoid, [nan, 0.0, 0.0, 0.0, 2.0 / 6.0, 0.5, 0.5, 4.0 / 6.0, 1.0, 1.0, 1.0, 1.0]);
        let leaky = Activation::LeakyRelu { negative_slope: 0.01 };
        let s = |v: f32| v * 0.01;
        check(leaky, [nan, -inf, s(-7.0), s(-3.0), s(-1.0), -0.0, 0.0, 1.0, 3.0, 6.0, 7.0, inf]);
        let elu = Activation::Elu { alpha: 2.0 };
        let e = |v: f64| (2.0 * v.exp_m1()) as f32;
        check(elu, [nan, -2.0, e(-7.0), e(-3.0), e(-1.0), -0.0, 0.0, 1.0, 3.0, 6.0, 7.0, inf]);
        check(Activation::Abs, [nan, inf, 7.0, 3.0, 1.0, 0.0, 0.0, 1.0, 3.0, 6.0, 7.0, inf]);
        check(Activation::Neg, [nan, inf, 7.0, 3.0, 1.0, 0.0, -0.0, -1.0, -3.0, -6.0, -7.0, -inf]);
        // log: NaN below 0, -inf at ±0, 0 at 1.
        let l = |v: f64| v.ln() as f32;
        check(Activation::Log, [nan, nan, nan, nan, nan, -inf, -inf, 0.0, l(3.0), l(6.0), l(7.0), inf]);
        check(Activation::Sqrt, [nan, nan, nan, nan, nan, -0.0, 0.0, 1.0, 3f32.sqrt(), 6f32.sqrt(), 7f32.sqrt(), inf]);
        let r = |v: f32| 1.0 / v.sqrt();
        check(Activation::Rsqrt, [nan, nan, nan, nan, nan, -inf, inf, 1.0, r(3.0), r(6.0), r(7.0), 0.0]);
        let ex = |v: f64| v.exp() as f32;
        check(
            Activation::Exp,
            [nan, 0.0, ex(-7.0), ex(-3.0), ex(-1.0), 1.0, 1.0, ex(1.0), ex(3.0), ex(6.0), ex(7.0), inf],
        );
        let er = |v: f64| libm::erf(v) as f32;
        check(Activation::Erf, [nan, -1.0, -1.0, er(-3.0), er(-1.0), -0.0, 0.0, er(1.0), er(3.0), 1.0, 1.0, 1.0]);
        // exp overflows where f32 does: e^88.72 = 3.4e38 is finite, e^88.73 is not.
        let mut big = [88.72f32, 88.73];
        activation_in_place(Activation::Exp, &mut big);
        assert!(big[0].is_finite() && big[1] == inf, "{big:?}");
        let mut big = [3e38f32];
        activation_in_place(Activation::Hardswish, &mut big);
        assert_eq!(big[0], inf, "as torch.nn.functional.hardswish(torch.tensor(3e38))");
    }

    #[test]
    fn pow_with_a_constant_and_with_a_tensor() {
        let x = [-2.0f32, -0.0, 0.0, 0.5, 1.0, 3.0, f32::INFINITY, f32::NEG_INFINITY, f32::NAN];
        for e in [2.0f32, 3.0, 0.5, -0.5, -1.0, -2.0, 1.5, 0.0, -3.0] {
            let mut got = [0.0; 9];
            scalar(BinaryOp::Pow, &x, e, false, &mut got);
            for (&v, &g) in x.iter().zip(&got) {
                // PyTorch computes these exponents as products and roots: sqrt(-0) = -0 and
                // sqrt(-inf) = NaN, where powf has +0 and inf.
                let want = match e {
                    0.5 => v.sqrt(),
                    -0.5 => 1.0 / v.sqrt(),
                    _ => (v as f64).powf(e as f64) as f32,
                };
                assert!(
                    g.to_bits() == want.to_bits() || (g.is_nan() && want.is_nan()),
                    "{v} ** {e} = {g}, want {want}"
                );
            }
        }
        // 2 ** x, and x ** y broadcast against a naive loop.
        let mut got = [0.0; 9];
        scalar(BinaryOp::Pow, &x, 2.0, true, &mut got);
        assert_eq!(&got[..6], &[0.25, 1.0, 1.0, 2f32.sqrt(), 2.0, 8.0]);
        let a: Vec<f32> = data(60, 10).iter().map(|v| v.abs() + 0.1).collect();
        let b = data(5, 11);
        let mut out = vec![0.0; 60];
        binary(BinaryOp::Pow, &a, &[3, 4, 5], &b, &[5], &mut out, &[3, 4, 5]);
        let want: Vec<f32> = a.iter().enumerate().map(|(i, v)| v.powf(b[i % 5])).collect();
        assert_eq!(out, want);
    }

    /// The activations computed on whole vectors (`VectorMap`), on every backend this CPU
    /// has, out of place and in place, on lengths that end in groups of four vectors,
    /// single vectors and a partial one: within the bounds the scalar functions keep, NaN
    /// and infinities where the formula puts them.
    #[test]
    fn vector_activations_on_every_backend() {
        let special = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, -0.0, 0.0, -100.0, -88.0, -87.5, 88.73, 1e-30];
        for len in [3, 16, 64, 181, 517] {
            let mut x: Vec<f32> = data(len, 4).iter().map(|v| v * 24.0).collect();
            for (v, s) in x.iter_mut().step_by(7).zip(special) {
                *v = s;
            }
            let acts = [
                (Activation::Silu, 3.0e-7),
                (Activation::Sigmoid, 2.5e-7),
                (Activation::Gelu, 4.0e-7),
                (Activation::GeluTanh, 6.0e-7),
                (Activation::Tanh, 3.0e-7),
                (Activation::Hardswish, 1.8e-7),
                (Activation::Hardsigmoid, 8.9e-8),
            ];
            for (act, bound) in acts {
                assert!(on_vectors(act));
                for b in backends() {
                    let mut out = vec![0.0; len];
                    b.run(VectorMap { act, x: Some(&x), out: &mut out });
                    // The hard functions take the scalar ones' operations in their order:
                    // the same bits (NaN for NaN).
                    let scalar = match act {
                        Activation::Hardswish => Some(hardswish as fn(f32) -> f32),
                        Activation::Hardsigmoid => Some(hardsigmoid as fn(f32) -> f32),
                        _ => None,
                    };
                    if let Some(f) = scalar {
                        for (&v, &g) in x.iter().zip(&out) {
                            let want = f(v);
                            assert!(
                                want.to_bits() == g.to_bits() || (want.is_nan() && g.is_nan()),
                                "{act:?}({v}) = {g}, not {want}"
                            );
                        }
                    }
                    // GELU's bounds are absolute below 1 (its negative tail is a difference
                    // of nearly equal terms in the exact form too), relative above.
                    let err = if matches!(act, Activation::Gelu | Activation::GeluTanh) {
                        x.iter()
                            .zip(&out)
                            .map(|(&v, &g)| {
                                (g as f64 - act.reference(v as f64)).abs() / act.reference(v as f64).abs().max(1.0)
                            })
                            .filter(|e| !e.is_nan())
                            .fold(0.0, f64::max)
                    } else {
                        rel_error(act, &x, &out)
                    };
                    assert!(err <= bound, "{b:?} {act:?} length {len}: relative error {err:e}");
                    let mut in_place = x.clone();
                    b.run(VectorMap { act, x: None, out: &mut in_place });
                    assert!(
                        in_place.iter().zip(&out).all(|(a, b)| a.to_bits() == b.to_bits()),
                        "{b:?} {act:?} length {len}: in place differs"
                    );
                }
            }
        }
    }

    #[test]
    fn tanh_and_silu_match_pytorch() {
        let x = [-9.0, -3.0, -1.5, -0.5, -0.05, -1e-3, 0.0, 1e-3, 0.05, 0.5, 1.0, 2.5, 9.0];
        // torch.tanh(torch.tensor(x)).tolist(), torch 2.15
        let tanh = [
            -0.999_999_94,
            -0.995_054_8,
            -0.905_148_3,
            -0.462_117_17,
            -0.049_958_374,
            -0.000_999_999_7,
            0.0,
            0.000_999_999_7,
            0.049_958_374,
            0.462_117_17,
            0.761_594_2,
            0.986_614_3,
            0.999_999_94,
        ];
        // torch.nn.functional.silu(torch.tensor(x)).tolist()
        let silu = [
            -0.001_110_551_2,
            -0.142_277_61,
            -0.273_638_28,
            -0.188_770_34,
            -0.024_375_131,
            -0.000_499_75,
            0.0,
            0.000_500_25,
            0.025_624_87,
            0.311_229_68,
            0.731_058_6,
            2.310_354_5,
            8.998_89,
        ];
        let mut got = [0.0; 13];
        activation(Activation::Tanh, &x, &mut got);
        assert_close(&got, &tanh, 1e-6);
        activation(Activation::Silu, &x, &mut got);
        assert_close(&got, &silu, 1e-6);
        let mut nan = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY];
        activation_in_place(Activation::Tanh, &mut nan);
        assert!(nan[0].is_nan() && nan[1] == 1.0 && nan[2] == -1.0, "{nan:?}");
    }
}

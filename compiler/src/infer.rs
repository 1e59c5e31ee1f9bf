//! Shape inference: the output types of an op from its attributes and input types.
//!
//! One function per op family. The elaborator calls [`infer`] as it creates each node (the
//! language can ask for shapes, `dim(x, 1)`), and the verifier calls it again to check
//! that every stored output type still matches. Errors name both shapes; the caller adds
//! the node path and source location.

use readi_grammar::ast::DType;
use readi_runtime::kernels::window_out;

use crate::ir::*;

/// Why an op does not accept its inputs.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShapeError {
    pub message: String,
    pub notes: Vec<String>,
}

impl ShapeError {
    fn new(message: impl Into<String>) -> ShapeError {
        ShapeError { message: message.into(), notes: Vec::new() }
    }
    fn note(mut self, note: impl Into<String>) -> ShapeError {
        self.notes.push(note.into());
        self
    }
}

type Result<T> = std::result::Result<T, ShapeError>;

/// The output types of `op` applied to inputs of the given types.
pub fn infer(op: &Op, inputs: &[&TensorType]) -> Result<Vec<TensorType>> {
    if let Some(n) = op.arity()
        && inputs.len() != n
    {
        return Err(ShapeError::new(format!("{} takes {n} tensor input(s), got {}", op.kind_name(), inputs.len())));
    }
    if !matches!(op, Op::Input(_) | Op::Parameter { .. }) && inputs.is_empty() {
        return Err(ShapeError::new(format!("{} needs at least one input", op.kind_name())));
    }
    for t in inputs {
        if !t.dtype.is_float() {
            return Err(ShapeError::new(format!("{} works on floating-point tensors, got {t}", op.kind_name())));
        }
    }
    let out = match op {
        Op::Input(_) => return Err(ShapeError::new("an input's type is declared, not inferred")),
        Op::Conv2d(c) => conv2d(c, inputs[0])?,
        Op::BatchNorm { channels, .. } => batchnorm(*channels, inputs[0])?,
        Op::LayerNorm { features, .. } => layernorm(*features, inputs[0])?,
        Op::Linear { in_features, out_features, .. } => linear(*in_features, *out_features, inputs[0])?,
        Op::MatMul => matmul(inputs[0], inputs[1])?,
        Op::Binary(kind) => {
            if inputs[0].dtype != inputs[1].dtype {
                return Err(ShapeError::new(format!(
                    "{} of different element types: {} and {}",
                    kind.name(),
                    inputs[0],
                    inputs[1]
                )));
            }
            TensorType::new(
                inputs[0].dtype,
                broadcast(&inputs[0].shape, &inputs[1].shape).map_err(|e| {
                    ShapeError::new(format!("cannot broadcast {} with {}", inputs[0], inputs[1])).note(e)
                })?,
            )
        }
        Op::Scalar { .. } | Op::Activation(_) => inputs[0].clone(),
        Op::Softmax { axis } => {
            axis_in_range(*axis, inputs[0])?;
            inputs[0].clone()
        }
        Op::Concat { axis } => concat(*axis, inputs)?,
        Op::Reshape { shape } => reshape(shape, inputs[0])?,
        Op::Permute { perm } => permute(perm, inputs[0])?,
        Op::Pool(p) => pool(p, inputs[0])?,
        Op::GlobalAvgPool => {
            let x = nchw(inputs[0], "global_avgpool")?;
            TensorType::new(x.dtype, vec![x.shape[0].clone(), x.shape[1].clone(), Dim::known(1), Dim::known(1)])
        }
        Op::Upsample { size, .. } => {
            let x = nchw(inputs[0], "upsample")?;
            if size[0] < 1 || size[1] < 1 {
                return Err(ShapeError::new(format!("upsample to an empty size {}x{}", size[0], size[1])));
            }
            TensorType::new(
                x.dtype,
                vec![x.shape[0].clone(), x.shape[1].clone(), Dim::known(size[0]), Dim::known(size[1])],
            )
        }
        Op::Mean { axes, keepdim } => mean(axes, *keepdim, inputs[0])?,
        Op::Parameter { shape } => {
            if shape.iter().any(|&d| d < 1) {
                return Err(ShapeError::new(format!("parameter shape {shape:?} has an empty axis")));
            }
            TensorType::new(DType::F32, shape.iter().map(|&d| Dim::known(d)).collect())
        }
    };
    Ok(vec![out])
}

fn nchw<'a>(x: &'a TensorType, op: &str) -> Result<&'a TensorType> {
    if x.rank() != 4 {
        return Err(ShapeError::new(format!("{op} expects a 4-D NCHW tensor, got {x}")));
    }
    Ok(x)
}

fn axis_in_range(axis: usize, x: &TensorType) -> Result<()> {
    if axis >= x.rank() {
        return Err(ShapeError::new(format!("axis {axis} is out of range for {x}")));
    }
    Ok(())
}

/// A spatial size that must be known for windowed ops.
fn spatial(x: &TensorType, axis: usize, op: &str) -> Result<i64> {
    x.known_dim(axis)
        .ok_or_else(|| ShapeError::new(format!("{op} needs known spatial sizes, but axis {axis} of {x} is symbolic")))
}

fn conv2d(c: &Conv2dAttrs, x: &TensorType) -> Result<TensorType> {
    let x = nchw(x, "conv2d")?;
    let cin = x.known_dim(1).ok_or_else(|| ShapeError::new(format!("conv2d needs a known channel count, got {x}")))?;
    if cin != c.in_channels {
        return Err(ShapeError::new(format!("conv2d expects {} input channels, got {x}", c.in_channels)));
    }
    if c.groups < 1 || cin % c.groups != 0 || c.out_channels % c.groups != 0 {
        return Err(ShapeError::new(format!(
            "conv2d groups={} must divide both {cin} input and {} output channels",
            c.groups, c.out_channels
        )));
    }
    let mut out = vec![x.shape[0].clone(), Dim::known(c.out_channels)];
    for i in 0..2 {
        let len = spatial(x, 2 + i, "conv2d")?;
        match window_out(len, c.kernel[i], c.stride[i], c.padding[i], c.dilation[i], false) {
            Some(o) => out.push(Dim::known(o)),
            None => {
                return Err(ShapeError::new(format!(
                    "conv2d kernel {}x{} (dilation {}) does not fit input {x} with padding {}",
                    c.kernel[0], c.kernel[1], c.dilation[i], c.padding[i]
                )));
            }
        }
    }
    Ok(TensorType::new(x.dtype, out))
}

fn pool(p: &PoolAttrs, x: &TensorType) -> Result<TensorType> {
    let name = match p.kind {
        PoolKind::Max => "maxpool",
        PoolKind::Avg => "avgpool",
    };
    let x = nchw(x, name)?;
    for i in 0..2 {
        if p.padding[i] * 2 > p.kernel[i] {
            return Err(ShapeError::new(format!(
                "{name} padding {} must be at most half the kernel size {}",
                p.padding[i], p.kernel[i]
            )));
        }
    }
    let mut out = vec![x.shape[0].clone(), x.shape[1].clone()];
    for i in 0..2 {
        let len = spatial(x, 2 + i, name)?;
        match window_out(len, p.kernel[i], p.stride[i], p.padding[i], 1, p.ceil_mode) {
            Some(o) => out.push(Dim::known(o)),
            None => {
                return Err(ShapeError::new(format!(
                    "{name} kernel {}x{} does not fit input {x}",
                    p.kernel[0], p.kernel[1]
                )));
            }
        }
    }
    Ok(TensorType::new(x.dtype, out))
}

fn batchnorm(channels: i64, x: &TensorType) -> Result<TensorType> {
    if x.rank() < 2 {
        return Err(ShapeError::new(format!("batchnorm expects at least 2 axes (N, C, ...), got {x}")));
    }
    if x.known_dim(1) != Some(channels) {
        return Err(ShapeError::new(format!("batchnorm over {channels} channels got {x}")));
    }
    Ok(x.clone())
}

fn layernorm(features: i64, x: &TensorType) -> Result<TensorType> {
    if x.rank() < 1 || x.known_dim(x.rank() - 1) != Some(features) {
        return Err(ShapeError::new(format!("layernorm over {features} features got {x}")));
    }
    Ok(x.clone())
}

fn linear(fin: i64, fout: i64, x: &TensorType) -> Result<TensorType> {
    let last = x.rank().checked_sub(1).ok_or_else(|| ShapeError::new("linear needs at least one axis"))?;
    if x.known_dim(last) != Some(fin) {
        return Err(ShapeError::new(format!("linear expects {fin} input features on the last axis, got {x}")));
    }
    let mut shape = x.shape.clone();
    shape[last] = Dim::known(fout);
    Ok(TensorType::new(x.dtype, shape))
}

/// NumPy broadcasting of two shapes.
pub fn broadcast(a: &[Dim], b: &[Dim]) -> std::result::Result<Vec<Dim>, String> {
    let n = a.len().max(b.len());
    let one = Dim::known(1);
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let da = if i + a.len() >= n { &a[i + a.len() - n] } else { &one };
        let db = if i + b.len() >= n { &b[i + b.len() - n] } else { &one };
        let d = if da == db || *db == one {
            da.clone()
        } else if *da == one {
            db.clone()
        } else {
            return Err(format!("axis {i} (from the right: {}) has sizes {da} and {db}", n - i));
        };
        out.push(d);
    }
    Ok(out)
}

fn matmul(a: &TensorType, b: &TensorType) -> Result<TensorType> {
    if a.rank() < 2 || b.rank() < 2 {
        return Err(ShapeError::new(format!("matmul needs at least 2 axes on both sides, got {a} and {b}")));
    }
    if a.dtype != b.dtype {
        return Err(ShapeError::new(format!("matmul of different element types: {a} and {b}")));
    }
    let (ra, rb) = (a.rank(), b.rank());
    if a.shape[ra - 1] != b.shape[rb - 2] {
        return Err(ShapeError::new(format!(
            "matmul inner sizes differ: {a} @ {b} ({} vs {})",
            a.shape[ra - 1],
            b.shape[rb - 2]
        )));
    }
    let mut shape = broadcast(&a.shape[..ra - 2], &b.shape[..rb - 2])
        .map_err(|e| ShapeError::new(format!("matmul batch axes of {a} and {b} do not broadcast")).note(e))?;
    shape.push(a.shape[ra - 2].clone());
    shape.push(b.shape[rb - 1].clone());
    Ok(TensorType::new(a.dtype, shape))
}

fn concat(axis: usize, inputs: &[&TensorType]) -> Result<TensorType> {
    let first = inputs[0];
    axis_in_range(axis, first)?;
    let mut total = Dim::known(0);
    for t in inputs {
        if t.rank() != first.rank() || t.dtype != first.dtype {
            return Err(ShapeError::new(format!("concat of {first} and {t}: ranks or element types differ")));
        }
        for (i, (d0, d)) in first.shape.iter().zip(&t.shape).enumerate() {
            if i != axis && d0 != d {
                return Err(ShapeError::new(format!(
                    "concat along axis {axis} needs equal sizes elsewhere, but axis {i} of {first} and {t} differ"
                )));
            }
        }
        let d = &t.shape[axis];
        total = match (total.as_known(), d.as_known()) {
            (Some(a), Some(b)) => Dim::known(a.checked_add(b).ok_or_else(|| ShapeError::new("concat size overflows"))?),
            _ => {
                return Err(ShapeError::new(format!("concat along axis {axis} needs known sizes there, got {t}")));
            }
        };
    }
    let mut shape = first.shape.clone();
    shape[axis] = total;
    Ok(TensorType::new(first.dtype, shape))
}

fn reshape(target: &[Dim], x: &TensorType) -> Result<TensorType> {
    let have = Dim::product(&x.shape).ok_or_else(|| ShapeError::new("element count overflows"))?;
    let want = Dim::product(target).ok_or_else(|| ShapeError::new("element count overflows"))?;
    if have != want {
        let shown: Vec<String> = target.iter().map(|d| d.to_string()).collect();
        return Err(ShapeError::new(format!(
            "cannot reshape {x} ({have} elements) to [{}] ({want} elements)",
            shown.join(", ")
        )));
    }
    Ok(TensorType::new(x.dtype, target.to_vec()))
}

fn permute(perm: &[usize], x: &TensorType) -> Result<TensorType> {
    let mut seen = vec![false; x.rank()];
    if perm.len() != x.rank() {
        return Err(ShapeError::new(format!("permutation {perm:?} has {} axes but {x} has {}", perm.len(), x.rank())));
    }
    for &p in perm {
        if p >= x.rank() || seen[p] {
            return Err(ShapeError::new(format!("{perm:?} is not a permutation of the axes of {x}")));
        }
        seen[p] = true;
    }
    Ok(TensorType::new(x.dtype, perm.iter().map(|&p| x.shape[p].clone()).collect()))
}

fn mean(axes: &[usize], keepdim: bool, x: &TensorType) -> Result<TensorType> {
    let mut seen = vec![false; x.rank()];
    for &a in axes {
        if a >= x.rank() || seen[a] {
            return Err(ShapeError::new(format!("mean axes {axes:?} are out of range or repeated for {x}")));
        }
        seen[a] = true;
    }
    let shape = x
        .shape
        .iter()
        .enumerate()
        .filter_map(|(i, d)| match (seen[i], keepdim) {
            (false, _) => Some(d.clone()),
            (true, true) => Some(Dim::known(1)),
            (true, false) => None,
        })
        .collect();
    Ok(TensorType::new(x.dtype, shape))
}

/// The type of a graph input as declared.
pub fn input_type(dtype: DType, shape: Vec<Dim>) -> TensorType {
    TensorType::new(dtype, shape)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t(shape: &[i64]) -> TensorType {
        TensorType::new(DType::F32, shape.iter().map(|&d| Dim::known(d)).collect())
    }

    fn conv(cin: i64, cout: i64, k: i64, s: i64, p: i64, d: i64, g: i64) -> Op {
        Op::Conv2d(Conv2dAttrs {
            in_channels: cin,
            out_channels: cout,
            kernel: [k, k],
            stride: [s, s],
            padding: [p, p],
            dilation: [d, d],
            groups: g,
            bias: false,
        })
    }

    // Expected sizes below are hand-computed with PyTorch's formula
    // floor((L + 2p - d(k-1) - 1) / s) + 1.

    #[test]
    fn conv_output_sizes() {
        let out = infer(&conv(3, 64, 7, 2, 3, 1, 1), &[&t(&[1, 3, 224, 224])]).expect("fits");
        assert_eq!(out[0], t(&[1, 64, 112, 112]));
        let out = infer(&conv(8, 8, 3, 1, 2, 2, 4), &[&t(&[2, 8, 10, 7])]).expect("fits");
        assert_eq!(out[0], t(&[2, 8, 10, 7]));
        let out = infer(&conv(4, 6, 3, 2, 0, 1, 2), &[&t(&[1, 4, 9, 8])]).expect("fits");
        assert_eq!(out[0], t(&[1, 6, 4, 3]));
    }

    #[test]
    fn conv_rejects_bad_channels_and_groups() {
        let e = infer(&conv(3, 64, 3, 1, 1, 1, 1), &[&t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("3 input channels"), "{e:?}");
        let e = infer(&conv(4, 6, 3, 1, 1, 1, 4), &[&t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("groups=4"), "{e:?}");
        let e = infer(&conv(4, 6, 5, 1, 0, 1, 1), &[&t(&[1, 4, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("does not fit"), "{e:?}");
    }

    #[test]
    fn maxpool_ceil_mode_matches_pytorch() {
        let p = |ceil| {
            Op::Pool(PoolAttrs {
                kind: PoolKind::Max,
                kernel: [3, 3],
                stride: [2, 2],
                padding: [1, 1],
                ceil_mode: ceil,
                count_include_pad: true,
            })
        };
        // torch: MaxPool2d(3, 2, 1) on 112 -> 56; on 6 -> 3 (floor) and 4 (ceil: 3.5 -> 4,
        // last window starts at 6 >= 6 + 1? no -> keep 4).
        assert_eq!(infer(&p(false), &[&t(&[1, 1, 112, 112])]).expect("ok")[0], t(&[1, 1, 56, 56]));
        assert_eq!(infer(&p(false), &[&t(&[1, 1, 6, 6])]).expect("ok")[0], t(&[1, 1, 3, 3]));
        assert_eq!(infer(&p(true), &[&t(&[1, 1, 6, 6])]).expect("ok")[0], t(&[1, 1, 4, 4]));
    }

    #[test]
    fn broadcasting_follows_numpy() {
        assert_eq!(broadcast(&t(&[4, 1, 3]).shape, &t(&[5, 1]).shape), Ok(t(&[4, 5, 3]).shape));
        assert!(broadcast(&t(&[4, 2]).shape, &t(&[3]).shape).is_err());
    }

    #[test]
    fn matmul_batches_and_checks_inner_size() {
        assert_eq!(infer(&Op::MatMul, &[&t(&[2, 3, 4, 5]), &t(&[3, 5, 6])]).expect("ok")[0], t(&[2, 3, 4, 6]));
        let e = infer(&Op::MatMul, &[&t(&[4, 5]), &t(&[4, 5])]).expect_err("an error");
        assert!(e.message.contains("inner sizes"), "{e:?}");
    }

    #[test]
    fn reshape_keeps_symbolic_element_count() {
        let n = Dim::symbol("N");
        let x = TensorType::new(DType::F32, vec![n.clone(), Dim::known(6), Dim::known(3)]);
        let six_n = n.checked_mul(&Dim::known(6)).expect("no overflow");
        let out = infer(&Op::Reshape { shape: vec![six_n.clone(), Dim::known(3)] }, &[&x]).expect("ok");
        assert_eq!(out[0].to_string(), "f32[6*N, 3]");
        let e = infer(&Op::Reshape { shape: vec![n, Dim::known(17)] }, &[&x]).expect_err("an error");
        assert!(e.message.contains("18*N"), "{e:?}");
    }

    #[test]
    fn concat_sums_the_axis() {
        let out = infer(&Op::Concat { axis: 1 }, &[&t(&[1, 2, 4]), &t(&[1, 3, 4])]).expect("ok");
        assert_eq!(out[0], t(&[1, 5, 4]));
        assert!(infer(&Op::Concat { axis: 1 }, &[&t(&[1, 2, 4]), &t(&[1, 3, 5])]).is_err());
    }
}

//! Sparse 3-D convolution, spconv's as BEVFusion's `SparseEncoder` uses it (see
//! `readi_plan::ops::SparseConv3d` for the representation):
//!
//! - `sparse_out_coords(coords, spatial_shape, kernel, stride=1, padding=0, dilation=1,
//!   max_out)`: the active output sites of a strided conv (`max_out` left out: the input's
//!   capacity);
//! - `sparse_conv3d(features, coords, out_coords, weight, spatial_shape, stride=1,
//!   padding=0, dilation=1, bias)`: spconv's `SparseConv3d`, the kernel size read from the
//!   weight `[kD, kH, kW, Cin, Cout]`;
//! - `subm_conv3d(features, coords, weight, spatial_shape, dilation=1, bias)`: spconv's
//!   `SubMConv3d`, outputs at the input sites (an odd kernel, centred);
//! - `sparse_to_dense(features, coords, spatial_shape)`: `.dense()`, `f32[1, C, D, H, W]`.
//!
//! The weight and bias are tensors (`parameter([3, 3, 3, 16, 32])` in a block), so a block
//! names them as spconv's `state_dict` does (`conv_input.0.weight`).

use readi_plan::DType;
use readi_plan::ops::{
    Pure, SparseConv3d, SparseOutCoords, SparseToDense, Window3, check_spatial_shape, sparse_out_shape,
};

use super::conv3d::triple;
use super::{Args, Builtin, P, R, absent, int, req};
use crate::ir::{Op, ValueRef};

const OUT_COORDS: &[P] = &[
    req("coords"),
    req("spatial_shape"),
    req("kernel"),
    int("stride", 1),
    int("padding", 0),
    int("dilation", 1),
    absent("max_out"),
];

const SPARSE_CONV: &[P] = &[
    req("features"),
    req("coords"),
    req("out_coords"),
    req("weight"),
    req("spatial_shape"),
    int("stride", 1),
    int("padding", 0),
    int("dilation", 1),
    absent("bias"),
];

const SUBM_CONV: &[P] =
    &[req("features"), req("coords"), req("weight"), req("spatial_shape"), int("dilation", 1), absent("bias")];

const TO_DENSE: &[P] = &[req("features"), req("coords"), req("spatial_shape")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("sparse_out_coords", OUT_COORDS, sparse_out_coords),
        Builtin::new("sparse_conv3d", SPARSE_CONV, sparse_conv3d),
        Builtin::new("subm_conv3d", SUBM_CONV, subm_conv3d),
        Builtin::new("sparse_to_dense", TO_DENSE, sparse_to_dense),
    ]
}

/// `[D, H, W]`, each between 1 and `MAX_SPARSE_AXIS`.
fn spatial_shape(args: &Args<'_>) -> R<[i64; 3]> {
    let v = args.int_list("spatial_shape")?;
    let s = match v[..] {
        [d, h, w] => [d, h, w],
        _ => return Err(args.bad_value("spatial_shape", format!("must be [D, H, W], got {v:?}"))),
    };
    check_spatial_shape(s).map_err(|e| args.bad_value("spatial_shape", e))?;
    Ok(s)
}

/// A tensor argument of this dtype and rank.
fn typed(args: &Args<'_>, name: &str, dtype: DType, rank: usize, shown: &str) -> R<ValueRef> {
    let t = args.ttype(name)?;
    if t.dtype != dtype || t.rank() != rank {
        return Err(args.bad_value(name, format!("must be {} {shown}, got {t}", dtype.as_str())));
    }
    args.tensor(name)
}

/// The kernel size from a `[kD, kH, kW, Cin, Cout]` weight.
fn kernel_of(args: &Args<'_>) -> R<[i64; 3]> {
    let t = args.ttype("weight")?;
    let k: Option<Vec<i64>> = (0..3).map(|a| t.known_dim(a)).collect();
    match (t.rank(), k.as_deref()) {
        (5, Some(&[a, b, c])) if t.dtype == DType::F32 => Ok([a, b, c]),
        _ => Err(args.bad_value("weight", format!("must be f32 [kD, kH, kW, Cin, Cout] (spconv's layout), got {t}"))),
    }
}

/// The window, checked against the grid.
fn window(args: &Args<'_>, shape: [i64; 3], w: Window3) -> R<Window3> {
    sparse_out_shape(shape, &w).map_err(|e| args.bad_value("spatial_shape", e.message))?;
    Ok(w)
}

fn conv_inputs(args: &Args<'_>, out_coords: &str) -> R<(Vec<ValueRef>, bool)> {
    let mut inputs = vec![
        typed(args, "features", DType::F32, 2, "[V, C]")?,
        typed(args, "coords", DType::I64, 2, "[V, 3]")?,
        typed(args, out_coords, DType::I64, 2, "[V', 3]")?,
        typed(args, "weight", DType::F32, 5, "[kD, kH, kW, Cin, Cout]")?,
    ];
    let bias = args.present("bias");
    if bias {
        inputs.push(typed(args, "bias", DType::F32, 1, "[Cout]")?);
    }
    Ok((inputs, bias))
}

fn sparse_out_coords(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let spatial = spatial_shape(args)?;
    let w = Window3 {
        kernel: triple(args, "kernel", 1)?,
        stride: triple(args, "stride", 1)?,
        padding: triple(args, "padding", 0)?,
        dilation: triple(args, "dilation", 1)?,
    };
    let window = window(args, spatial, w)?;
    let max_out = if args.present("max_out") { Some(args.int_at_least("max_out", 1)?) } else { None };
    if max_out.is_some_and(|m| m > 1 << 31) {
        return Err(args.bad_value("max_out", "must be at most 2^31".into()));
    }
    let coords = typed(args, "coords", DType::I64, 2, "[V, 3]")?;
    Ok((Op::Pure(Pure::SparseOutCoords(SparseOutCoords { spatial_shape: spatial, window, max_out })), vec![coords]))
}

fn sparse_conv3d(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let spatial = spatial_shape(args)?;
    let w = Window3 {
        kernel: kernel_of(args)?,
        stride: triple(args, "stride", 1)?,
        padding: triple(args, "padding", 0)?,
        dilation: triple(args, "dilation", 1)?,
    };
    let window = window(args, spatial, w)?;
    let (inputs, bias) = conv_inputs(args, "out_coords")?;
    Ok((Op::Pure(Pure::SparseConv3d(SparseConv3d { spatial_shape: spatial, window, subm: false, bias })), inputs))
}

fn subm_conv3d(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let spatial = spatial_shape(args)?;
    let kernel = kernel_of(args)?;
    if kernel.iter().any(|k| k % 2 == 0) {
        return Err(args.bad_value("weight", format!("subm_conv3d needs an odd kernel, the weight's is {kernel:?}")));
    }
    let dilation = triple(args, "dilation", 1)?;
    let padding = [0, 1, 2].map(|a| dilation[a] * (kernel[a] - 1) / 2);
    let window = window(args, spatial, Window3 { kernel, stride: [1; 3], padding, dilation })?;
    let (mut inputs, bias) = conv_inputs(args, "coords")?;
    inputs[2] = inputs[1];
    Ok((Op::Pure(Pure::SparseConv3d(SparseConv3d { spatial_shape: spatial, window, subm: true, bias })), inputs))
}

fn sparse_to_dense(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let spatial = spatial_shape(args)?;
    let inputs =
        vec![typed(args, "features", DType::F32, 2, "[V, C]")?, typed(args, "coords", DType::I64, 2, "[V, 3]")?];
    Ok((Op::Pure(Pure::SparseToDense(SparseToDense { spatial_shape: spatial })), inputs))
}

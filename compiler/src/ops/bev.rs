//! `lss_bev_pool(depth, context, camera_intrinsics, camera2lidar, img_aug_matrix,
//! lidar_aug_matrix, image_size, xbound, ybound, zbound, dbound)`: BEVFusion's
//! camera-to-BEV view transform (`BaseTransform.get_geometry` + `bev_pool`), the tensors
//! named as mmdetection3d's model inputs, the numbers as BEVFusion's config.

use readi_plan::ops::{LSS_INPUTS, LssBevPool, Pure, check_bound};

use super::{Args, Builtin, P, R, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

const LSS_BEV_POOL: &[P] = &[
    req("depth"),
    req("context"),
    req("camera_intrinsics"),
    req("camera2lidar"),
    req("img_aug_matrix"),
    req("lidar_aug_matrix"),
    req("image_size"),
    req("xbound"),
    req("ybound"),
    req("zbound"),
    req("dbound"),
];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("lss_bev_pool", LSS_BEV_POOL, lss_bev_pool)]
}

/// `[start, stop, step]`: three numbers, finite, with a positive step and start < stop.
fn bound(args: &Args<'_>, name: &str) -> R<[f64; 3]> {
    let what = "a list [start, stop, step] of three numbers";
    let v = match args.value(name) {
        Some(Value::List(l)) if l.len() == 3 => {
            let num = |v: &Value| match v {
                Value::Int(i) => Ok(*i as f64),
                Value::Float(f) => Ok(*f),
                other => Err(args.mismatch(name, what, other)),
            };
            [num(&l[0])?, num(&l[1])?, num(&l[2])?]
        }
        Some(v) => return Err(args.mismatch(name, what, v)),
        None => return Err(args.bad_value(name, "missing".into())),
    };
    check_bound(v).map_err(|e| args.bad_value(name, e))?;
    Ok(v)
}

fn lss_bev_pool(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let size = args.int_list("image_size")?;
    let image_size = match size[..] {
        [h, w] if h >= 1 && w >= 1 => [h, w],
        _ => return Err(args.bad_value("image_size", format!("must be [height, width], both positive, got {size:?}"))),
    };
    let op = LssBevPool {
        image_size,
        xbound: bound(args, "xbound")?,
        ybound: bound(args, "ybound")?,
        zbound: bound(args, "zbound")?,
        dbound: bound(args, "dbound")?,
    };
    for (name, b) in [("xbound", op.xbound), ("ybound", op.ybound), ("zbound", op.zbound)] {
        LssBevPool::cells(name, b).map_err(|e| args.bad_value(name, e.message))?;
    }
    op.depth_bins().map_err(|e| args.bad_value("dbound", e.message))?;
    let shapes =
        ["[B, N, D, fH, fW]", "[B, N, C, fH, fW]", "[B, N, 4, 4]", "[B, N, 4, 4]", "[B, N, 4, 4]", "[B, 4, 4]"];
    let mut inputs = Vec::with_capacity(LSS_INPUTS.len());
    for (name, shape) in LSS_INPUTS.iter().zip(shapes) {
        let t = args.ttype(name)?;
        let rank = shape.split(',').count();
        if t.rank() != rank {
            return Err(args.bad_value(name, format!("must be {shape} ({rank} axes), got {t}")));
        }
        inputs.push(args.tensor(name)?);
    }
    Ok((Op::Pure(Pure::LssBevPool(op)), inputs))
}

//! Sparse 3-D convolution, spconv's (`SubMConv3d`, `SparseConv3d`, `.dense()`) as the
//! VoxelNet / SECOND `SparseEncoder` of BEVFusion uses it.
//!
//! A sparse tensor is two values with a declared capacity `V`: `features f32[V, C]` and
//! `coords i64[V, 3]`, each row a site `(z, y, x)` of a `spatial_shape = [D, H, W]` grid
//! (batch 1). The active sites are a prefix of the rows; every inactive row has coords
//! `(-1, -1, -1)`. Consumers ignore inactive rows (their features may be anything
//! finite, a BatchNorm's bias); producers write zeros to them. The kernels check the
//! coords of every run (in the grid, a prefix, no site twice) and refuse others.
//!
//! - `sparse_out_coords(coords)`: the active outputs of a strided sparse conv, the
//!   dilation of the inputs (every output site whose receptive field holds an active
//!   input), sorted by linear index `(z·H' + y)·W' + x`, padded with `-1` rows up to
//!   `max_out`; more active outputs than `max_out` is a run-time error.
//! - `sparse_conv3d(features, coords, out_coords, weight[, bias])`: output row `r` (a site
//!   `o` of `out_coords`) is `bias + Σ_k features[site o·stride − padding + k·dilation] ·
//!   weight[k]` over the kernel taps `k` whose input site is active: the dense conv3d
//!   evaluated at the output sites with inactive inputs zero. The weight is spconv's
//!   layout `[kD, kH, kW, Cin, Cout]` (mit-han-lab/bevfusion's `mmdet3d/ops/spconv`,
//!   spconv 1.x: `Parameter(torch.Tensor(*kernel_size, in_channels, out_channels))`).
//!   A submanifold conv (`subm`) is the case `out_coords = coords`, stride 1 and padding
//!   `dilation·(kernel − 1) / 2` (an odd kernel): spconv's centred `SubMConv3d`.
//! - `sparse_to_dense(features, coords)`: `f32[1, C, D, H, W]`, spconv's `.dense()`.

use serde::{Deserialize, Serialize};

use super::{DType, Operator, ShapeError, ShapeResult, TensorType, Window3, list};
use crate::dim::Dim;

/// Most cells an axis of a sparse grid may have: coords are exact in f32 below 2^24.
pub const MAX_SPARSE_AXIS: i64 = 1 << 20;

/// Most kernel taps a sparse conv may have.
pub const MAX_SPARSE_TAPS: i64 = 1 << 12;

/// Why a grid `[D, H, W]` is refused, if it is.
pub fn check_spatial_shape(s: [i64; 3]) -> Result<(), String> {
    if s.iter().any(|&d| !(1..=MAX_SPARSE_AXIS).contains(&d)) {
        return Err(format!("must be three sizes between 1 and {MAX_SPARSE_AXIS}, got {}", list(&s)));
    }
    Ok(())
}

/// The output grid of a sparse conv of window `w` over `spatial_shape`, or why not.
pub fn sparse_out_shape(spatial_shape: [i64; 3], w: &Window3) -> ShapeResult<[i64; 3]> {
    check_spatial_shape(spatial_shape).map_err(|e| ShapeError::new(format!("spatial_shape {e}")))?;
    let taps = w.kernel.iter().try_fold(1i64, |a, &k| a.checked_mul(k));
    if taps.is_none_or(|t| t > MAX_SPARSE_TAPS) {
        return Err(ShapeError::new(format!("a kernel {} has more than {MAX_SPARSE_TAPS} taps", list(&w.kernel))));
    }
    let mut out = [0; 3];
    for (a, o) in out.iter_mut().enumerate() {
        *o = w.out_len(a, spatial_shape[a]).ok_or_else(|| {
            ShapeError::new(format!(
                "the window (kernel {}, stride {}, padding {}, dilation {}) does not fit the grid {}",
                list(&w.kernel),
                list(&w.stride),
                list(&w.padding),
                list(&w.dilation),
                list(&spatial_shape)
            ))
        })?;
    }
    Ok(out)
}

fn window_attrs(w: &Window3) -> [(&'static str, String); 4] {
    [
        ("kernel", list(&w.kernel)),
        ("stride", list(&w.stride)),
        ("padding", list(&w.padding)),
        ("dilation", list(&w.dilation)),
    ]
}

/// `x` must be `[V, width]` of `dtype` (`width` `None`: any known width); its `V`.
fn rows<'a>(x: &'a TensorType, dtype: DType, width: Option<i64>, op: &str, name: &str) -> ShapeResult<&'a Dim> {
    let shown = width.map_or("C".to_string(), |w| w.to_string());
    // A plan holds i64 values as f32 (the runtime computes in f32); the compiler's
    // builtins have checked the language's types.
    let same = x.dtype == dtype || (dtype == DType::I64 && x.dtype == DType::F32 && x.rank() == 2);
    if !same || x.rank() != 2 || x.known_dim(1).is_none() || width.is_some_and(|w| x.known_dim(1) != Some(w)) {
        return Err(ShapeError::new(format!("{op} {name} must be {}[V, {shown}], got {x}", dtype.as_str())));
    }
    Ok(&x.shape[0])
}

/// The active outputs of a strided sparse conv: `coords i64[V, 3]` in, `i64[max_out, 3]`
/// out (`max_out` `None`: the input's capacity `V`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SparseOutCoords {
    /// The input grid `[D, H, W]`.
    pub spatial_shape: [i64; 3],
    pub window: Window3,
    pub max_out: Option<i64>,
}

impl Operator for SparseOutCoords {
    fn kind_name(&self) -> &'static str {
        "sparse_out_coords"
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        sparse_out_shape(self.spatial_shape, &self.window)?;
        let v = rows(inputs[0], DType::I64, Some(3), "sparse_out_coords", "coords")?;
        let cap = match self.max_out {
            Some(m) if !(1..=1 << 31).contains(&m) => {
                return Err(ShapeError::new(format!("sparse_out_coords max_out must be between 1 and 2^31, got {m}")));
            }
            Some(m) => Dim::known(m),
            None => v.clone(),
        };
        Ok(TensorType::new(DType::I64, vec![cap, Dim::known(3)]))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut a = vec![("spatial_shape", list(&self.spatial_shape))];
        a.extend(window_attrs(&self.window));
        a.push(("max_out", self.max_out.map_or("capacity".into(), |m| m.to_string())));
        a
    }
}

/// A sparse 3-D convolution (see the module doc): inputs `features f32[V, Cin]`, `coords
/// i64[V, 3]`, `out_coords i64[V', 3]`, `weight f32[kD, kH, kW, Cin, Cout]` and, with
/// `bias`, `bias f32[Cout]`; output `f32[V', Cout]`.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SparseConv3d {
    /// The input grid `[D, H, W]`.
    pub spatial_shape: [i64; 3],
    pub window: Window3,
    /// Submanifold (`SubMConv3d`): the builtin passed `coords` as `out_coords`, stride 1
    /// and the centring padding. For printouts and selectors; the kernel is the same.
    pub subm: bool,
    pub bias: bool,
}

impl Operator for SparseConv3d {
    fn kind_name(&self) -> &'static str {
        if self.subm { "subm_conv3d" } else { "sparse_conv3d" }
    }

    fn arity(&self) -> Option<usize> {
        Some(if self.bias { 5 } else { 4 })
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = self.kind_name();
        let out_grid = sparse_out_shape(self.spatial_shape, &self.window)?;
        if self.subm && out_grid != self.spatial_shape {
            return Err(ShapeError::new(format!(
                "{name} must keep the grid {}, its window gives {}",
                list(&self.spatial_shape),
                list(&out_grid)
            )));
        }
        let (f, c, oc, w) = (inputs[0], inputs[1], inputs[2], inputs[3]);
        let v = rows(f, DType::F32, None, name, "features")?;
        let cin = f.known_dim(1).unwrap_or(0);
        if rows(c, DType::I64, Some(3), name, "coords")? != v {
            return Err(ShapeError::new(format!("{name} coords {c} must have the rows of features {f}")));
        }
        let vout = rows(oc, DType::I64, Some(3), name, "out_coords")?;
        let k = self.window.kernel;
        let known: Option<Vec<i64>> = (0..5).map(|a| w.known_dim(a)).collect();
        let cout = match known.as_deref() {
            Some([a, b, cc, i, o]) if w.dtype == DType::F32 && [*a, *b, *cc] == k && *i == cin && *o >= 1 => *o,
            _ => {
                return Err(ShapeError::new(format!(
                    "{name} weight must be f32[{}, {}, {}, {cin}, Cout] (spconv's [kD, kH, kW, Cin, Cout]), got {w}",
                    k[0], k[1], k[2]
                )));
            }
        };
        if self.bias {
            let b = inputs[4];
            if b.dtype != DType::F32 || b.rank() != 1 || b.known_dim(0) != Some(cout) {
                return Err(ShapeError::new(format!("{name} bias must be f32[{cout}], got {b}")));
            }
        }
        Ok(TensorType::f32(vec![vout.clone(), Dim::known(cout)]))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let mut a = vec![("spatial_shape", list(&self.spatial_shape))];
        a.extend(window_attrs(&self.window));
        a.push(("bias", self.bias.to_string()));
        a
    }
}

/// spconv's `.dense()`: `features f32[V, C]` and `coords i64[V, 3]` to `f32[1, C, D, H,
/// W]`, zero at every inactive site.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SparseToDense {
    pub spatial_shape: [i64; 3],
}

impl Operator for SparseToDense {
    fn kind_name(&self) -> &'static str {
        "sparse_to_dense"
    }

    fn arity(&self) -> Option<usize> {
        Some(2)
    }

    fn any_dtype(&self) -> bool {
        true
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        check_spatial_shape(self.spatial_shape)
            .map_err(|e| ShapeError::new(format!("sparse_to_dense spatial_shape {e}")))?;
        let (f, c) = (inputs[0], inputs[1]);
        let v = rows(f, DType::F32, None, "sparse_to_dense", "features")?;
        if rows(c, DType::I64, Some(3), "sparse_to_dense", "coords")? != v {
            return Err(ShapeError::new(format!("sparse_to_dense coords {c} must have the rows of features {f}")));
        }
        let [d, h, w] = self.spatial_shape;
        let numel = [d, h, w, f.known_dim(1).unwrap_or(0)].iter().try_fold(1i64, |a, &x| a.checked_mul(x));
        if numel.is_none_or(|n| n > 1 << 40) {
            return Err(ShapeError::new("sparse_to_dense: the dense grid is too large"));
        }
        let shape = [1, f.known_dim(1).unwrap_or(0), d, h, w].map(Dim::known).to_vec();
        Ok(TensorType::f32(shape))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("spatial_shape", list(&self.spatial_shape))]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::run;
    use super::*;

    fn ti(shape: &[i64], dtype: DType) -> TensorType {
        TensorType::new(dtype, shape.iter().map(|&d| Dim::known(d)).collect())
    }

    fn win(k: [i64; 3], s: [i64; 3], p: [i64; 3]) -> Window3 {
        Window3 { kernel: k, stride: s, padding: p, dilation: [1; 3] }
    }

    #[test]
    fn conv_shapes() {
        let op =
            SparseConv3d { spatial_shape: [5, 8, 8], window: win([3; 3], [1; 3], [1; 3]), subm: true, bias: false };
        let f = ti(&[10, 4], DType::F32);
        let c = ti(&[10, 3], DType::I64);
        let w = ti(&[3, 3, 3, 4, 16], DType::F32);
        assert_eq!(run(&op, &[f.clone(), c.clone(), c.clone(), w.clone()]), Ok(ti(&[10, 16], DType::F32)));
        let bad_w = ti(&[16, 4, 3, 3, 3], DType::F32);
        let e = run(&op, &[f.clone(), c.clone(), c.clone(), bad_w]).expect_err("torch layout");
        assert!(e.message.contains("[kD, kH, kW, Cin, Cout]"), "{}", e.message);
        let e = run(&SparseConv3d { window: win([3; 3], [1; 3], [0; 3]), ..op.clone() }, &[f.clone(), c.clone(), c, w])
            .expect_err("subm shrinks");
        assert!(e.message.contains("must keep the grid"), "{}", e.message);
        let e = run(&op, &[f.clone(), ti(&[10, 3], DType::I32), ti(&[10, 3], DType::I64), f]).expect_err("i32 coords");
        assert_eq!(e.message, "subm_conv3d coords must be i64[V, 3], got i32[10, 3]");
    }

    #[test]
    fn out_coords_and_dense_shapes() {
        let op =
            SparseOutCoords { spatial_shape: [41, 16, 16], window: win([3, 1, 1], [2, 1, 1], [0; 3]), max_out: None };
        assert_eq!(sparse_out_shape(op.spatial_shape, &op.window), Ok([20, 16, 16]));
        let c = ti(&[7, 3], DType::I64);
        assert_eq!(run(&op, std::slice::from_ref(&c)), Ok(ti(&[7, 3], DType::I64)));
        assert_eq!(
            run(&SparseOutCoords { max_out: Some(30), ..op.clone() }, std::slice::from_ref(&c)),
            Ok(ti(&[30, 3], DType::I64))
        );
        assert!(run(&SparseOutCoords { max_out: Some(0), ..op.clone() }, std::slice::from_ref(&c)).is_err());
        assert!(run(&SparseOutCoords { spatial_shape: [0, 4, 4], ..op.clone() }, std::slice::from_ref(&c)).is_err());
        assert!(
            run(&SparseOutCoords { spatial_shape: [1, 4, 4], ..op }, std::slice::from_ref(&c)).is_err(),
            "kernel 3 on depth 1"
        );
        let d = SparseToDense { spatial_shape: [2, 3, 4] };
        assert_eq!(run(&d, &[ti(&[7, 5], DType::F32), c]), Ok(ti(&[1, 5, 2, 3, 4], DType::F32)));
    }
}

//! Operators: their attributes and shape rules, one definition each.
//!
//! Every operator the compiler can emit and the runtime can run is defined here once, in
//! one file per family: its attributes (serde-derived, so the plan stores them as they
//! are), its name in the language, and its shape rule ([`Operator::infer`]). The
//! compiler's shape inference and the runtime's plan check call the same rule: the
//! compiler on the symbolic shapes of the graph it elaborates, the runtime on the shapes a
//! plan declares, when it loads it. A plan whose shapes disagree with the rules is refused
//! before any kernel sees it.
//!
//! | file            | operators                                                        |
//! |-----------------|------------------------------------------------------------------|
//! | `conv.rs`       | `conv2d`                                                         |
//! | `conv_transpose.rs` | `conv_transpose2d`                                           |
//! | `conv3d.rs`     | `conv3d` (NCDHW; its window sized per axis by `window.rs`'s rule) |
//! | `pool.rs`       | `maxpool`, `avgpool`, `global_avgpool`, `adaptive_{avg,max}pool` |
//! | `window.rs`     | the sliding-window geometry of conv and pool                     |
//! | `elementwise.rs`| binary ops with broadcasting, ops with a scalar, activations      |
//! | `linear.rs`     | `linear`, `matmul`                                               |
//! | `norm.rs`       | `batchnorm`, `layernorm`, `groupnorm`, the channel affine a BatchNorm folds to |
//! | `layout.rs`     | `concat`, `reshape`, `permute`                                   |
//! | `reduce.rs`     | `sum`, `mean`, `max`, `min`, `var`, `std`, `softmax`             |
//! | `resize.rs`     | `upsample`, `pixel_shuffle`, `pixel_unshuffle`                   |
//! | `movement.rs`   | `pad`, `roll`, `slice` (also `narrow`, `select`, `chunk`, `split`), `expand` |
//! | `index.rs`      | `index_select` (also `embedding`), `where`, casts, `arange` / `full` constants |
//! | `bev.rs`        | `lss_bev_pool`, BEVFusion's camera-to-BEV view transform         |
//! | `select.rs`     | run-time indices: `argmax`, `argmin`, `topk`, `gather`, `take_along_dim`, `index_select` at a computed index, `one_hot`, `where` with a number |
//! | `voxel.rs`      | the lidar front end: `voxelize`, `dynamic_voxelize`, `lidar_depth_map` |
//! | `sparse.rs`     | `sparse_out_coords`, `sparse_conv3d` / `subm_conv3d`, `sparse_to_dense`: spconv's sparse 3-D conv |
//!
//! Operators without stored tensors are [`Pure`]: the graph IR and the plan hold the same
//! value, so lowering one is a copy. Operators with weights (conv, linear, the norms) are
//! wrapped by the IR with their parameter slots and by the plan's kernel with the indices
//! of their stored tensors.

mod bev;
mod conv;
mod conv3d;
mod conv_transpose;
mod elementwise;
mod index;
mod layout;
mod linear;
mod movement;
mod norm;
mod pool;
mod reduce;
mod resize;
mod select;
mod sparse;
mod voxel;
mod window;

use std::fmt;

use serde::{Deserialize, Serialize};

use crate::dim::Dim;
pub use bev::{LSS_INPUTS, LssBevPool, MAX_GRID_AXIS, check_bound, show_bound};
pub use conv::{Conv2d, Conv2dShape, ConvAlgo};
pub use conv_transpose::{ConvTranspose2d, ConvTranspose2dShape, transpose_out};
pub use conv3d::{Conv3d, Conv3dShape, Window3};
pub use elementwise::{Activation, BinaryOp, Scalar, broadcast, floor_divide, maximum, minimum, remainder};
pub use index::{Cast, Fill, IndexSelect, Where};
pub use layout::{Concat, Permute, Reshape};
pub use linear::{Linear, MatMul, PANEL};
pub use movement::{Expand, Pad, PadMode, Resolved, Roll, Slice, SliceAxis};
pub use norm::{BatchNorm, ChannelAffine, GroupNorm, LayerNorm, batchnorm_affine, batchnorm_channel};
pub use pool::{AdaptivePool2d, GlobalAvgPool, Pool2d, PoolKind, adaptive_bin};
pub use reduce::{Reduce, ReduceKind, Softmax};
pub use resize::{PixelShuffle, Upsample, UpsampleMode};
pub use select::{ArgKind, ArgReduce, Gather, IndexSelectAt, OneHot, TopK, WhereScalar};
pub use sparse::{
    MAX_SPARSE_AXIS, MAX_SPARSE_TAPS, SparseConv3d, SparseOutCoords, SparseToDense, check_spatial_shape,
    sparse_out_shape,
};
pub use voxel::{DEPTH_MAP_INPUTS, LidarDepthMap, MAX_GRID_CELLS, MAX_VOXELS, VoxelOutput, Voxelize, point_features};
pub use window::{Window2, window_out};

/// Element types of tensors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum DType {
    F32,
    F16,
    BF16,
    I64,
    I32,
    Bool,
}

impl DType {
    pub fn as_str(self) -> &'static str {
        match self {
            DType::F32 => "f32",
            DType::F16 => "f16",
            DType::BF16 => "bf16",
            DType::I64 => "i64",
            DType::I32 => "i32",
            DType::Bool => "bool",
        }
    }
    pub fn is_float(self) -> bool {
        matches!(self, DType::F32 | DType::F16 | DType::BF16)
    }
    /// Size of one element in bytes.
    pub fn size_bytes(self) -> u64 {
        match self {
            DType::F32 | DType::I32 => 4,
            DType::F16 | DType::BF16 => 2,
            DType::I64 => 8,
            DType::Bool => 1,
        }
    }
}

/// The element type and shape of a tensor.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub struct TensorType {
    pub dtype: DType,
    pub shape: Vec<Dim>,
}

impl TensorType {
    pub fn new(dtype: DType, shape: Vec<Dim>) -> TensorType {
        TensorType { dtype, shape }
    }
    /// An f32 tensor, the only kind a plan computes.
    pub fn f32(shape: Vec<Dim>) -> TensorType {
        TensorType { dtype: DType::F32, shape }
    }
    pub fn rank(&self) -> usize {
        self.shape.len()
    }
    /// The known size of an axis, `None` if symbolic or out of range.
    pub fn known_dim(&self, axis: usize) -> Option<i64> {
        self.shape.get(axis).and_then(Dim::as_known)
    }
}

impl fmt::Display for TensorType {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}[", self.dtype.as_str())?;
        for (i, d) in self.shape.iter().enumerate() {
            if i > 0 {
                f.write_str(", ")?;
            }
            write!(f, "{d}")?;
        }
        f.write_str("]")
    }
}

/// Why an operator does not accept its inputs. The message names both shapes; the caller
/// adds the place (a node path and source span, or a plan step).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ShapeError {
    pub message: String,
    pub notes: Vec<String>,
}

impl ShapeError {
    pub fn new(message: impl Into<String>) -> ShapeError {
        ShapeError { message: message.into(), notes: Vec::new() }
    }
    pub fn note(mut self, note: impl Into<String>) -> ShapeError {
        self.notes.push(note.into());
        self
    }
}

impl fmt::Display for ShapeError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.message)?;
        for n in &self.notes {
            write!(f, " ({n})")?;
        }
        Ok(())
    }
}

pub type ShapeResult<T> = Result<T, ShapeError>;

/// What every operator defines.
pub trait Operator {
    /// The name in the language; selectors match op kinds by it.
    fn kind_name(&self) -> &'static str;
    /// Number of tensor inputs, or `None` for one or more (concat).
    fn arity(&self) -> Option<usize> {
        Some(1)
    }
    /// The output type for inputs of these types. Called through [`infer`], which has
    /// checked the arity and that every input is floating-point.
    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType>;
    /// The attributes as `key=value` pairs for printouts, in a fixed order. Defaults are
    /// printed too: the printout is the op's full meaning.
    fn attrs(&self) -> Vec<(&'static str, String)> {
        Vec::new()
    }
    /// Whether the operator takes integer and bool inputs too (comparisons, `where`,
    /// casts, indexing); every other one works on floating-point tensors only.
    fn any_dtype(&self) -> bool {
        false
    }
    /// The multiply-adds one run of the operator does on inputs and an output of these
    /// concrete shapes, counted as the direct (textbook) algorithm does them: what a
    /// kernel's or a model's GFLOP/s is measured in (`readi bench`). Zero for the
    /// operators that do no products (elementwise, movement, normalisation), and for those
    /// whose work depends on the data (a sparse conv's rulebook).
    fn multiply_adds(&self, inputs: &[&[usize]], output: &[usize]) -> u64 {
        let _ = (inputs, output);
        0
    }
}

/// Elements of a concrete shape, saturating (a count, not an allocation size).
pub(crate) fn count(shape: &[usize]) -> u64 {
    shape.iter().fold(1u64, |n, &d| n.saturating_mul(d as u64))
}

/// The output type of `op` on inputs of the given types: the operator's own rule after
/// the checks every operator shares (arity, floating-point inputs unless it takes any).
pub fn infer(op: &dyn Operator, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
    let name = op.kind_name();
    match op.arity() {
        Some(n) if inputs.len() != n => {
            return Err(ShapeError::new(format!("{name} takes {n} tensor input(s), got {}", inputs.len())));
        }
        None if inputs.is_empty() => return Err(ShapeError::new(format!("{name} needs at least one input"))),
        _ => {}
    }
    for t in inputs.iter().filter(|_| !op.any_dtype()) {
        if !t.dtype.is_float() {
            return Err(ShapeError::new(format!("{name} works on floating-point tensors, got {t}")));
        }
    }
    op.infer(inputs)
}

/// An operator whose output depends on its inputs alone: no stored tensors. The graph IR
/// and the plan's schedule hold the same value, so lowering one is a copy.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Pure {
    MatMul(MatMul),
    Binary(BinaryOp),
    Scalar(Scalar),
    Activation(Activation),
    Softmax(Softmax),
    Concat(Concat),
    Reshape(Reshape),
    Permute(Permute),
    Pool(Pool2d),
    GlobalAvgPool(GlobalAvgPool),
    Upsample(Upsample),
    AdaptivePool(AdaptivePool2d),
    PixelShuffle(PixelShuffle),
    /// Plans of format versions 2 and 3 call it `Mean` (it was the only kind).
    #[serde(alias = "Mean")]
    Reduce(Reduce),
    Pad(Pad),
    Roll(Roll),
    Slice(Slice),
    Expand(Expand),
    IndexSelect(IndexSelect),
    Where(Where),
    Cast(Cast),
    /// A constant; the compiler folds it, a plan never runs it.
    Fill(Fill),
    LssBevPool(LssBevPool),
    ArgReduce(ArgReduce),
    TopK(TopK),
    Gather(Gather),
    IndexSelectAt(IndexSelectAt),
    OneHot(OneHot),
    WhereScalar(WhereScalar),
    Voxelize(Voxelize),
    LidarDepthMap(LidarDepthMap),
    SparseOutCoords(SparseOutCoords),
    SparseConv3d(SparseConv3d),
    SparseToDense(SparseToDense),
}

impl Pure {
    /// The operator's definition.
    pub fn op(&self) -> &dyn Operator {
        match self {
            Pure::MatMul(o) => o,
            Pure::Binary(o) => o,
            Pure::Scalar(o) => o,
            Pure::Activation(o) => o,
            Pure::Softmax(o) => o,
            Pure::Concat(o) => o,
            Pure::Reshape(o) => o,
            Pure::Permute(o) => o,
            Pure::Pool(o) => o,
            Pure::GlobalAvgPool(o) => o,
            Pure::Upsample(o) => o,
            Pure::AdaptivePool(o) => o,
            Pure::PixelShuffle(o) => o,
            Pure::Reduce(o) => o,
            Pure::Pad(o) => o,
            Pure::Roll(o) => o,
            Pure::Slice(o) => o,
            Pure::Expand(o) => o,
            Pure::IndexSelect(o) => o,
            Pure::Where(o) => o,
            Pure::Cast(o) => o,
            Pure::Fill(o) => o,
            Pure::LssBevPool(o) => o,
            Pure::ArgReduce(o) => o,
            Pure::TopK(o) => o,
            Pure::Gather(o) => o,
            Pure::IndexSelectAt(o) => o,
            Pure::OneHot(o) => o,
            Pure::WhereScalar(o) => o,
            Pure::Voxelize(o) => o,
            Pure::LidarDepthMap(o) => o,
            Pure::SparseOutCoords(o) => o,
            Pure::SparseConv3d(o) => o,
            Pure::SparseToDense(o) => o,
        }
    }
}

/// The input must be 4-D (NCHW).
pub(crate) fn nchw<'a>(x: &'a TensorType, op: &str) -> ShapeResult<&'a TensorType> {
    if x.rank() != 4 {
        return Err(ShapeError::new(format!("{op} expects a 4-D NCHW tensor, got {x}")));
    }
    Ok(x)
}

pub(crate) fn axis_in_range(axis: usize, x: &TensorType) -> ShapeResult<()> {
    if axis >= x.rank() {
        return Err(ShapeError::new(format!("axis {axis} is out of range for {x}")));
    }
    Ok(())
}

/// A spatial size that must be known for windowed ops.
pub(crate) fn spatial(x: &TensorType, axis: usize, op: &str) -> ShapeResult<i64> {
    x.known_dim(axis)
        .ok_or_else(|| ShapeError::new(format!("{op} needs known spatial sizes, but axis {axis} of {x} is symbolic")))
}

/// `[a, b]` as `a` when equal, else `axb`: how printouts show pairs.
pub(crate) fn pair(p: [i64; 2]) -> String {
    if p[0] == p[1] { p[0].to_string() } else { format!("{}x{}", p[0], p[1]) }
}

/// A float as printouts show it: always with a point or an exponent.
pub(crate) fn float(v: f64) -> String {
    let s = format!("{v:?}");
    if s.contains('e') || s.contains('.') { s } else { format!("{s}.0") }
}

/// `[a, b, c]`.
pub(crate) fn list<T: fmt::Display>(v: &[T]) -> String {
    let parts: Vec<String> = v.iter().map(|x| x.to_string()).collect();
    format!("[{}]", parts.join(", "))
}

#[cfg(test)]
pub(crate) mod testutil {
    use super::*;

    pub fn t(shape: &[i64]) -> TensorType {
        TensorType::f32(shape.iter().map(|&d| Dim::known(d)).collect())
    }

    pub fn run(op: &dyn Operator, inputs: &[TensorType]) -> ShapeResult<TensorType> {
        let refs: Vec<&TensorType> = inputs.iter().collect();
        infer(op, &refs)
    }
}

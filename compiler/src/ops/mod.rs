//! The compiler's side of each operator: its builtins in the language and, for operators
//! with weights, the IR wrapper that adds the parameter slots.
//!
//! The back end's forms of the weighted operators live here too: a conv or linear with
//! its fused [`Epilogue`], algorithm and packed weight, and the channel affine a
//! BatchNorm folds to ([`AffineOp`]).
//!
//! An operator's attributes and shape rule are defined once, in `readi_plan::ops` (shared
//! with the runtime, which checks plans with the same rule). Here, one file per family
//! says how the language writes the operator (a [`Builtin`]: its name, its parameters with
//! PyTorch's names and defaults, and a builder that checks the arguments and makes the IR
//! op) and which `state_dict` tensors it owns.
//!
//! | file             | builtins                                                    |
//! |------------------|-------------------------------------------------------------|
//! | `conv.rs`        | `conv2d`, `conv1d` (a conv2d over `[N, C, 1, L]`)           |
//! | `conv_transpose.rs` | `conv_transpose2d`                                       |
//! | `conv3d.rs`      | `conv3d` (NCDHW)                                            |
//! | `pool.rs`        | `maxpool`, `avgpool`, `global_avgpool`, `adaptive_avgpool`, `adaptive_maxpool` |
//! | `elementwise.rs` | `add`, `sub`, `mul`, `div`, `pow`, every activation (`relu`, `clamp`, `gelu`, ...) and unary function (`exp`, `sqrt`, ...) |
//! | `linear.rs`      | `linear`, `matmul`                                          |
//! | `norm.rs`        | `batchnorm`, `layernorm`, `groupnorm`                       |
//! | `layout.rs`      | `concat`, `reshape`, `flatten`, `transpose`, `permute`      |
//! | `reduce.rs`      | `sum`, `mean`, `max`, `min`, `var`, `std`, `softmax`        |
//! | `resize.rs`      | `upsample`, `pixel_shuffle`, `pixel_unshuffle`              |
//! | `movement.rs`    | `pad`, `roll`, `slice`, `narrow`, `select`, `chunk`, `split`, `squeeze`, `unsqueeze`, `expand` |
//! | `parameter.rs`   | `parameter`, `buffer`                                       |
//! | `index.rs`       | `arange`, `zeros`, `ones`, `full`, `where`, `float`, `to`, `index_select`, `embedding` |
//! | `bev.rs`         | `lss_bev_pool` (BEVFusion's camera-to-BEV view transform)   |
//! | `select.rs`      | `argmax`, `argmin`, `topk`, `gather`, `take_along_dim`, `one_hot`, `maximum`, `minimum`, `floor_divide`, `remainder`, `atan2` |
//! | `voxel.rs`       | `voxelize`, `dynamic_voxelize`, `lidar_depth_map` (BEVFusion's lidar front end) |
//! | `sparse.rs`      | `sparse_out_coords`, `sparse_conv3d`, `subm_conv3d`, `sparse_to_dense` (spconv's sparse 3-D conv) |
//! | `pytorch.rs`     | no builtins: PyTorch's names readi spells differently or lacks |
//!
//! Activations need nothing here: every [`Activation`](readi_plan::ops::Activation) without
//! options becomes a builtin `name(x)` by itself (`docs/contributing.md`); those with
//! options (`clamp`, `leaky_relu`, ...) have a builder in `elementwise.rs`.

mod args;
mod bev;
mod conv;
mod conv3d;
mod conv_transpose;
mod elementwise;
mod epilogue;
mod index;
mod layout;
mod linear;
mod movement;
mod norm;
mod parameter;
mod pool;
pub mod pytorch;
mod reduce;
mod resize;
mod select;
mod sparse;
mod voxel;

use std::sync::LazyLock;

pub use args::{Args, Def, P, R, Sig, absent, boolean, flt, int, positive_float, req};
pub use conv::{AdapterOp, ConvOp};
pub use conv_transpose::ConvTransposeOp;
pub use conv3d::Conv3dOp;
pub use epilogue::{BiasedConv, BnFold, ConvWeights, Epilogue};
pub use index::IndexSelectOp;
pub use linear::LinearOp;
pub use norm::{AffineOp, batchnorm_slots, groupnorm_slots, layernorm_slots};
pub use parameter::{BufferOp, ConstantOp, ParameterOp};

use crate::ir::{Op, ValueRef};

/// A builtin's builder: checks the bound arguments and makes the op and its tensor inputs
/// in port order.
pub type Build = fn(&Args<'_>) -> R<(Op, Vec<ValueRef>)>;

/// A builder of a builtin whose value is a list of tensors (`chunk`, `split`): one op and
/// its inputs per element.
pub type BuildMany = fn(&Args<'_>) -> R<Vec<(Op, Vec<ValueRef>)>>;

/// How a builtin makes its value: one tensor, or a list of them.
#[derive(Clone, Copy)]
pub enum Make {
    One(Build),
    Many(BuildMany),
}

/// A builtin op of the language.
pub struct Builtin {
    pub sig: Sig,
    pub make: Make,
    /// The builtin writes an op of another kind (`transpose` and `flatten` make a
    /// `permute` and a `reshape`), so selectors do not know it as a kind.
    pub alias: bool,
}

impl Builtin {
    pub(crate) const fn new(name: &'static str, params: &'static [P], build: Build) -> Builtin {
        Builtin { sig: Sig { name, params }, make: Make::One(build), alias: false }
    }
    /// A builtin whose value is a list of tensors, each made by an op of another kind.
    pub(crate) const fn many(name: &'static str, params: &'static [P], many: BuildMany) -> Builtin {
        Builtin { sig: Sig { name, params }, make: Make::Many(many), alias: true }
    }
    pub(crate) const fn alias(self) -> Builtin {
        Builtin { alias: true, ..self }
    }
}

static BUILTINS: LazyLock<Vec<Builtin>> = LazyLock::new(|| {
    let families = [
        conv::builtins(),
        conv_transpose::builtins(),
        conv3d::builtins(),
        norm::builtins(),
        linear::builtins(),
        elementwise::builtins(),
        reduce::builtins(),
        layout::builtins(),
        movement::builtins(),
        pool::builtins(),
        resize::builtins(),
        parameter::builtins(),
        index::builtins(),
        bev::builtins(),
        select::builtins(),
        voxel::builtins(),
        sparse::builtins(),
    ];
    families.into_iter().flatten().collect()
});

/// Every builtin op.
pub fn builtins() -> &'static [Builtin] {
    &BUILTINS
}

/// The builtin op called `name`.
pub fn builtin(name: &str) -> Option<&'static Builtin> {
    BUILTINS.iter().find(|b| b.sig.name == name)
}

/// The op kinds selectors may name: every builtin that is not an alias.
pub fn op_kinds() -> impl Iterator<Item = &'static str> {
    BUILTINS.iter().filter(|b| !b.alias).map(|b| b.sig.name)
}

//! PyTorch's names for functions the language spells differently or does not have, so
//! that an unknown call that is a PyTorch name gets an answer that cannot mislead: the
//! readi spelling of the same function, or "not supported (yet)". The elaborator consults
//! [`lookup`] before its edit-distance suggestion, which never fires for these names
//! (`relu6` once got "did you mean `relu`?", a different function).
//!
//! A name here is never a builtin (a test checks it): builtins with PyTorch's names
//! (`relu6`, `clamp`, `silu`, `conv3d`, `dynamic_voxelize`, ...) need no entry. Beside
//! torch's names and `torch.nn`'s module classes, [`LIBRARY_NAMES`] holds those of the
//! libraries BEVFusion's lidar branch is written in (spconv, mmcv, its own `bev_pool`),
//! each note naming its library.

/// What readi has for a PyTorch function.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Spelling {
    /// The same function, written this way in readi: a builtin's name, or a phrase
    /// (`written `x ** 2``, `the identity in eval mode: leave it out`).
    Readi(&'static str),
    /// Not in readi (yet).
    Unsupported,
}

use Spelling::{Readi, Unsupported};

/// PyTorch names (`torch.*`, `torch.nn.functional.*`, tensor methods) and their readi
/// spelling.
pub static PYTORCH_NAMES: &[(&str, Spelling)] = &[
    // Aliases of builtins.
    ("clip", Readi("clamp")),
    ("swish", Readi("silu")),
    ("negative", Readi("neg")),
    ("absolute", Readi("abs")),
    ("multiply", Readi("mul")),
    ("divide", Readi("div")),
    ("true_divide", Readi("div")),
    ("subtract", Readi("sub")),
    ("square", Readi("written `x ** 2` in readi")),
    ("reciprocal", Readi("written `1 / x` in readi")),
    ("max_pool2d", Readi("maxpool")),
    ("avg_pool2d", Readi("avgpool")),
    ("adaptive_avg_pool2d", Readi("adaptive_avgpool")),
    ("adaptive_max_pool2d", Readi("adaptive_maxpool")),
    ("AdaptiveAvgPool2d", Readi("adaptive_avgpool")),
    ("AdaptiveMaxPool2d", Readi("adaptive_maxpool")),
    ("amax", Readi("max")),
    ("amin", Readi("min")),
    ("group_norm", Readi("groupnorm")),
    ("GroupNorm", Readi("groupnorm")),
    ("PixelShuffle", Readi("pixel_shuffle")),
    ("PixelUnshuffle", Readi("pixel_unshuffle")),
    ("batch_norm", Readi("batchnorm")),
    ("layer_norm", Readi("layernorm")),
    ("cat", Readi("concat")),
    ("view", Readi("reshape")),
    ("interpolate", Readi("upsample")),
    ("mm", Readi("matmul")),
    ("bmm", Readi("matmul")),
    ("dropout", Readi("the identity in eval mode: leave it out")),
    ("identity", Readi("the identity: use the value itself")),
    // `torch.nn` modules: a readi layer op is the module and its call at once.
    ("Conv1d", Readi("conv1d")),
    ("Conv2d", Readi("conv2d")),
    ("Conv3d", Readi("conv3d")),
    ("ConvTranspose2d", Readi("conv_transpose2d")),
    ("BatchNorm1d", Readi("batchnorm")),
    ("BatchNorm2d", Readi("batchnorm")),
    ("BatchNorm3d", Readi("batchnorm")),
    ("Linear", Readi("linear")),
    ("LayerNorm", Readi("layernorm")),
    // Activations and unary functions readi does not have: each close, by spelling, to
    // one it has (selu, celu, prelu, rrelu to relu or elu; log1p, log2, log10 to log;
    // expm1 to exp; logsigmoid to sigmoid; softmin, log_softmax to softmax).
    ("selu", Unsupported),
    ("celu", Unsupported),
    ("prelu", Unsupported),
    ("rrelu", Unsupported),
    ("glu", Unsupported),
    ("mish", Unsupported),
    ("softplus", Unsupported),
    ("softsign", Unsupported),
    ("logsigmoid", Unsupported),
    ("tanhshrink", Unsupported),
    ("hardshrink", Unsupported),
    ("softshrink", Unsupported),
    ("threshold", Unsupported),
    ("softmin", Unsupported),
    ("log_softmax", Unsupported),
    ("log1p", Unsupported),
    ("log2", Unsupported),
    ("log10", Unsupported),
    ("expm1", Unsupported),
    ("exp2", Unsupported),
    ("erfc", Unsupported),
    ("erfinv", Unsupported),
    ("sin", Unsupported),
    ("cos", Unsupported),
    ("tan", Unsupported),
    ("sinh", Unsupported),
    ("cosh", Unsupported),
    ("asin", Unsupported),
    ("acos", Unsupported),
    ("atan", Unsupported),
    ("floor", Unsupported),
    ("ceil", Unsupported),
    ("round", Unsupported),
    ("trunc", Unsupported),
    ("frac", Unsupported),
    ("sign", Unsupported),
    ("instance_norm", Unsupported),
    ("einsum", Unsupported),
    // 3-D ops beyond the convolution: the transposed one, pooling.
    ("conv_transpose3d", Unsupported),
    ("ConvTranspose3d", Unsupported),
    ("max_pool3d", Unsupported),
    ("MaxPool3d", Unsupported),
    ("avg_pool3d", Unsupported),
    ("AvgPool3d", Unsupported),
];

/// The names of the libraries BEVFusion's lidar and view-transform code is written in,
/// `(library, name, spelling)`: spconv's sparse convolution, mmcv's voxelization and
/// BEVFusion's own CUDA op.
pub static LIBRARY_NAMES: &[(&str, &str, Spelling)] = &[
    ("spconv", "SubMConv3d", Readi("subm_conv3d")),
    ("spconv", "SparseConv3d", Readi("sparse_conv3d")),
    (
        "spconv",
        "SparseConvTensor",
        Readi("two values in readi, `features [V, C]` and `coords` i64 `[V, 3]`; its `.dense()` is `sparse_to_dense`"),
    ),
    (
        "spconv",
        "dense",
        Readi("`SparseConvTensor.dense()`: `sparse_to_dense` in readi (a fully connected layer is `linear`)"),
    ),
    ("spconv", "SparseInverseConv3d", Unsupported),
    ("spconv", "SparseConvTranspose3d", Unsupported),
    ("spconv", "SparseMaxPool3d", Unsupported),
    ("mmcv", "Voxelization", Readi("voxelize")),
    ("mmcv", "hard_voxelize", Readi("voxelize")),
    ("mmcv", "DynamicScatter", Readi("the mean per voxel of `dynamic_voxelize`, which returns it with the coords")),
    ("BEVFusion", "bev_pool", Readi("lss_bev_pool")),
];

/// The library `name` is from (`PyTorch`, `spconv`, ...) and what readi has for it, if
/// it is one of [`PYTORCH_NAMES`] or [`LIBRARY_NAMES`].
pub fn lookup(name: &str) -> Option<(&'static str, Spelling)> {
    let torch = PYTORCH_NAMES.iter().map(|&(n, s)| ("PyTorch", n, s));
    torch.chain(LIBRARY_NAMES.iter().copied()).find(|&(_, n, _)| n == name).map(|(lib, _, s)| (lib, s))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_pytorch_name_is_a_builtin_and_each_spelling_is_one() {
        let all = || PYTORCH_NAMES.iter().map(|&(n, s)| (n, s)).chain(LIBRARY_NAMES.iter().map(|&(_, n, s)| (n, s)));
        for (name, spelling) in all() {
            assert!(super::super::builtin(name).is_none(), "`{name}` is a builtin: drop its entry");
            if let Readi(s) = spelling
                && !s.contains(' ')
            {
                assert!(super::super::builtin(s).is_some(), "`{name}` -> `{s}`, which is no builtin");
            }
        }
        let mut names: Vec<&str> = all().map(|p| p.0).collect();
        names.sort_unstable();
        let n = names.len();
        names.dedup();
        assert_eq!(names.len(), n, "a name listed twice");
    }
}

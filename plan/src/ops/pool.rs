//! Pooling over the last two axes of NCHW: `maxpool`, `avgpool`, `global_avgpool`, and
//! `adaptive_avgpool` / `adaptive_maxpool` with PyTorch's bins ([`adaptive_bin`]).

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, Window2, nchw, pair, spatial};
use crate::dim::Dim;

/// Which reduction a pooling window applies.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum PoolKind {
    /// Maximum; padding counts as `-inf` and NaN propagates.
    Max,
    /// Mean, with the divisor chosen by `count_include_pad`.
    Avg,
}

/// Max or average pooling. The window's dilation is 1.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Pool2d {
    pub kind: PoolKind,
    pub window: Window2,
    pub ceil_mode: bool,
    /// Average pooling only: whether padded zeros count in the divisor.
    pub count_include_pad: bool,
}

impl Operator for Pool2d {
    fn kind_name(&self) -> &'static str {
        match self.kind {
            PoolKind::Max => "maxpool",
            PoolKind::Avg => "avgpool",
        }
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = self.kind_name();
        let x = nchw(inputs[0], name)?;
        let w = &self.window;
        if w.dilation != [1, 1] {
            return Err(ShapeError::new(format!("{name} has dilation {}, but pooling supports 1", pair(w.dilation))));
        }
        for i in 0..2 {
            if w.padding[i].checked_mul(2).is_none_or(|p| p > w.kernel[i]) {
                return Err(ShapeError::new(format!(
                    "{name} padding {} must be at most half the kernel size {}",
                    w.padding[i], w.kernel[i]
                )));
            }
        }
        let mut out = vec![x.shape[0].clone(), x.shape[1].clone()];
        for i in 0..2 {
            let len = spatial(x, 2 + i, name)?;
            match w.out_len(i, len, self.ceil_mode) {
                Some(o) => out.push(Dim::known(o)),
                None => {
                    return Err(ShapeError::new(format!(
                        "{name} kernel {}x{} does not fit input {x}",
                        w.kernel[0], w.kernel[1]
                    )));
                }
            }
        }
        Ok(TensorType::new(x.dtype, out))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let w = &self.window;
        let mut v = vec![
            ("kernel", pair(w.kernel)),
            ("stride", pair(w.stride)),
            ("padding", pair(w.padding)),
            ("ceil_mode", self.ceil_mode.to_string()),
        ];
        if self.kind == PoolKind::Avg {
            v.push(("count_include_pad", self.count_include_pad.to_string()));
        }
        v
    }
}

/// Mean over the spatial axes of NCHW, keeping them as 1x1.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct GlobalAvgPool;

impl Operator for GlobalAvgPool {
    fn kind_name(&self) -> &'static str {
        "global_avgpool"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = nchw(inputs[0], "global_avgpool")?;
        Ok(TensorType::new(x.dtype, vec![x.shape[0].clone(), x.shape[1].clone(), Dim::known(1), Dim::known(1)]))
    }
}

/// Adaptive max or average pooling to `output_size` (`[oh, ow]`), as PyTorch's
/// `adaptive_{max,avg}_pool2d`: output index `i` of an axis of length `len` reduces the
/// input range [`adaptive_bin`]`(i, len, out)`. The input may be smaller than the output
/// (bins then repeat input positions) but not empty.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct AdaptivePool2d {
    pub kind: PoolKind,
    pub output_size: [i64; 2],
}

impl Operator for AdaptivePool2d {
    fn kind_name(&self) -> &'static str {
        match self.kind {
            PoolKind::Max => "adaptive_maxpool",
            PoolKind::Avg => "adaptive_avgpool",
        }
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = self.kind_name();
        let x = nchw(inputs[0], name)?;
        let [oh, ow] = self.output_size;
        if oh < 1 || ow < 1 {
            return Err(ShapeError::new(format!("{name} to an empty size {}", pair(self.output_size))));
        }
        if let Some(a) = (2..4).find(|&a| x.known_dim(a) == Some(0)) {
            return Err(ShapeError::new(format!("{name} of an empty axis {a} of {x}")));
        }
        Ok(TensorType::new(x.dtype, vec![x.shape[0].clone(), x.shape[1].clone(), Dim::known(oh), Dim::known(ow)]))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        vec![("output_size", pair(self.output_size))]
    }
}

/// PyTorch's adaptive pooling bin of output index `i` of `out` over an axis of `len`:
/// `[floor(i * len / out), ceil((i + 1) * len / out))`, never empty when `len >= 1`.
#[inline]
pub fn adaptive_bin(i: usize, len: usize, out: usize) -> (usize, usize) {
    (i * len / out, ((i + 1) * len).div_ceil(out))
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    #[test]
    fn maxpool_ceil_mode_matches_pytorch() {
        let p = |ceil_mode| Pool2d {
            kind: PoolKind::Max,
            window: Window2 { kernel: [3, 3], stride: [2, 2], padding: [1, 1], dilation: [1, 1] },
            ceil_mode,
            count_include_pad: true,
        };
        // torch: MaxPool2d(3, 2, 1) on 112 -> 56; on 6 -> 3 (floor) and 4 (ceil).
        assert_eq!(run(&p(false), &[t(&[1, 1, 112, 112])]), Ok(t(&[1, 1, 56, 56])));
        assert_eq!(run(&p(false), &[t(&[1, 1, 6, 6])]), Ok(t(&[1, 1, 3, 3])));
        assert_eq!(run(&p(true), &[t(&[1, 1, 6, 6])]), Ok(t(&[1, 1, 4, 4])));
    }

    #[test]
    fn padding_beyond_half_the_kernel_is_refused() {
        let p = Pool2d {
            kind: PoolKind::Avg,
            window: Window2 { kernel: [2, 2], stride: [1, 1], padding: [2, 2], dilation: [1, 1] },
            ceil_mode: false,
            count_include_pad: true,
        };
        let e = run(&p, &[t(&[1, 1, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("at most half"), "{e:?}");
        assert_eq!(run(&GlobalAvgPool, &[t(&[2, 5, 7, 3])]), Ok(t(&[2, 5, 1, 1])));
    }

    #[test]
    fn adaptive_pooling_shapes_and_bins() {
        let p = |kind, output_size| AdaptivePool2d { kind, output_size };
        assert_eq!(run(&p(PoolKind::Avg, [3, 2]), &[t(&[2, 5, 7, 3])]), Ok(t(&[2, 5, 3, 2])));
        // Larger than the input: bins repeat positions.
        assert_eq!(run(&p(PoolKind::Max, [9, 9]), &[t(&[1, 2, 4, 4])]), Ok(t(&[1, 2, 9, 9])));
        let e = run(&p(PoolKind::Max, [0, 2]), &[t(&[1, 1, 4, 4])]).expect_err("empty output");
        assert_eq!(e.message, "adaptive_maxpool to an empty size 0x2");
        let e = run(&p(PoolKind::Avg, [2, 2]), &[t(&[1, 1, 0, 4])]).expect_err("empty input");
        assert_eq!(e.message, "adaptive_avgpool of an empty axis 2 of f32[1, 1, 0, 4]");
        assert!(run(&p(PoolKind::Avg, [2, 2]), &[t(&[1, 4, 4])]).is_err());
        // torch: 7 -> 3 bins [0, 3), [2, 5), [4, 7); 5 -> 3 bins [0, 2), [1, 4), [3, 5).
        assert_eq!((0..3).map(|i| adaptive_bin(i, 7, 3)).collect::<Vec<_>>(), [(0, 3), (2, 5), (4, 7)]);
        assert_eq!((0..3).map(|i| adaptive_bin(i, 5, 3)).collect::<Vec<_>>(), [(0, 2), (1, 4), (3, 5)]);
        assert_eq!((0..4).map(|i| adaptive_bin(i, 2, 4)).collect::<Vec<_>>(), [(0, 1), (0, 1), (1, 2), (1, 2)]);
    }
}

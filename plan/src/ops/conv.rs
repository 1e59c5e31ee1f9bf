//! `conv2d`: 2-D convolution over NCHW, weight `[out, in/groups, kh, kw]`.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, Window2, nchw, pair, spatial};
use crate::dim::Dim;

/// A 2-D convolution's geometry. The bias, and what the back end fuses into the conv (a
/// folded BatchNorm, an activation), are the IR's and the plan kernel's business.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Conv2d {
    pub in_channels: i64,
    pub out_channels: i64,
    pub window: Window2,
    pub groups: i64,
}

impl Conv2d {
    /// The PyTorch weight shape `[out, in/groups, kh, kw]`.
    pub fn weight_shape(&self) -> [i64; 4] {
        let w = &self.window;
        [self.out_channels, self.in_channels / self.groups.max(1), w.kernel[0], w.kernel[1]]
    }
}

impl Operator for Conv2d {
    fn kind_name(&self) -> &'static str {
        "conv2d"
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let x = nchw(inputs[0], "conv2d")?;
        let cin =
            x.known_dim(1).ok_or_else(|| ShapeError::new(format!("conv2d needs a known channel count, got {x}")))?;
        if cin != self.in_channels {
            return Err(ShapeError::new(format!("conv2d expects {} input channels, got {x}", self.in_channels)));
        }
        if self.groups < 1 || cin % self.groups != 0 || self.out_channels % self.groups != 0 {
            return Err(ShapeError::new(format!(
                "conv2d groups={} must divide both {cin} input and {} output channels",
                self.groups, self.out_channels
            )));
        }
        if self.out_channels < 1 {
            return Err(ShapeError::new(format!(
                "conv2d needs at least one output channel, not {}",
                self.out_channels
            )));
        }
        let w = &self.window;
        let mut out = vec![x.shape[0].clone(), Dim::known(self.out_channels)];
        for i in 0..2 {
            let len = spatial(x, 2 + i, "conv2d")?;
            match w.out_len(i, len, false) {
                Some(o) => out.push(Dim::known(o)),
                None => {
                    return Err(ShapeError::new(format!(
                        "conv2d kernel {}x{} (dilation {}) does not fit input {x} with padding {}",
                        w.kernel[0], w.kernel[1], w.dilation[i], w.padding[i]
                    )));
                }
            }
        }
        Ok(TensorType::new(x.dtype, out))
    }

    fn attrs(&self) -> Vec<(&'static str, String)> {
        let w = &self.window;
        vec![
            ("in", self.in_channels.to_string()),
            ("out", self.out_channels.to_string()),
            ("kernel", pair(w.kernel)),
            ("stride", pair(w.stride)),
            ("padding", pair(w.padding)),
            ("dilation", pair(w.dilation)),
            ("groups", self.groups.to_string()),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    fn conv(cin: i64, cout: i64, k: i64, s: i64, p: i64, d: i64, g: i64) -> Conv2d {
        let window = Window2 { kernel: [k, k], stride: [s, s], padding: [p, p], dilation: [d, d] };
        Conv2d { in_channels: cin, out_channels: cout, window, groups: g }
    }

    // Expected sizes are hand-computed with PyTorch's formula
    // floor((L + 2p - d(k-1) - 1) / s) + 1.
    #[test]
    fn output_sizes() {
        assert_eq!(run(&conv(3, 64, 7, 2, 3, 1, 1), &[t(&[1, 3, 224, 224])]), Ok(t(&[1, 64, 112, 112])));
        assert_eq!(run(&conv(8, 8, 3, 1, 2, 2, 4), &[t(&[2, 8, 10, 7])]), Ok(t(&[2, 8, 10, 7])));
        assert_eq!(run(&conv(4, 6, 3, 2, 0, 1, 2), &[t(&[1, 4, 9, 8])]), Ok(t(&[1, 6, 4, 3])));
    }

    #[test]
    fn rejects_bad_channels_groups_and_windows() {
        let e = run(&conv(3, 64, 3, 1, 1, 1, 1), &[t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("3 input channels"), "{e:?}");
        let e = run(&conv(4, 6, 3, 1, 1, 1, 4), &[t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("groups=4"), "{e:?}");
        let e = run(&conv(4, 6, 5, 1, 0, 1, 1), &[t(&[1, 4, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("does not fit"), "{e:?}");
        let e = run(&conv(4, 6, 3, 1, 1, 1, 1), &[t(&[4, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("4-D"), "{e:?}");
    }
}

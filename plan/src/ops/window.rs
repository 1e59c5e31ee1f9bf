//! The sliding-window geometry conv and pooling share: kernel, stride, padding and
//! dilation per spatial axis, and PyTorch's output-size formula.

use serde::{Deserialize, Serialize};

/// A 2-D sliding window: per axis (height, width) its kernel size, stride, zero padding
/// on both sides and dilation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Window2 {
    pub kernel: [i64; 2],
    pub stride: [i64; 2],
    pub padding: [i64; 2],
    pub dilation: [i64; 2],
}

impl Window2 {
    /// A 1x1 window: stride 1, no padding, no dilation.
    pub const ONE: Window2 = Window2 { kernel: [1, 1], stride: [1, 1], padding: [0, 0], dilation: [1, 1] };

    /// The output length along `axis` (0: height, 1: width) for an input of `len`, or
    /// `None` when the window does not fit or a value is out of range.
    pub fn out_len(&self, axis: usize, len: i64, ceil_mode: bool) -> Option<i64> {
        window_out(len, self.kernel[axis], self.stride[axis], self.padding[axis], self.dilation[axis], ceil_mode)
    }

    /// The output lengths for an input of `h x w`.
    pub fn out_size(&self, h: i64, w: i64, ceil_mode: bool) -> Option<[i64; 2]> {
        Some([self.out_len(0, h, ceil_mode)?, self.out_len(1, w, ceil_mode)?])
    }
}

/// Output length of a sliding window (conv, pooling), as PyTorch's
/// `pooling_output_shape` computes it:
/// `floor((len + 2 pad - dilation (kernel - 1) - 1 + (ceil ? stride - 1 : 0)) / stride) + 1`,
/// minus one when ceil mode would start the last window past the input and left padding.
/// `None` when the result is not at least 1 or a value is out of range.
pub fn window_out(len: i64, kernel: i64, stride: i64, pad: i64, dilation: i64, ceil: bool) -> Option<i64> {
    if stride < 1 || kernel < 1 || dilation < 1 || pad < 0 || len < 0 {
        return None;
    }
    let eff = dilation.checked_mul(kernel - 1)?;
    let num = len.checked_add(pad.checked_mul(2)?)?.checked_sub(eff)?.checked_sub(1)?.checked_add(if ceil {
        stride - 1
    } else {
        0
    })?;
    let mut out = num.div_euclid(stride) + 1;
    if ceil && (out - 1).checked_mul(stride)? >= len.checked_add(pad)? {
        out -= 1;
    }
    (out >= 1).then_some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    // Expected sizes are hand-computed with PyTorch's formula
    // floor((L + 2p - d(k-1) - 1) / s) + 1.
    #[test]
    fn output_lengths_follow_pytorch() {
        assert_eq!(window_out(224, 7, 2, 3, 1, false), Some(112));
        assert_eq!(window_out(10, 3, 1, 2, 2, false), Some(10));
        assert_eq!(window_out(1, 2, 2, 0, 1, true), Some(1));
        assert_eq!(window_out(3, 5, 1, 0, 1, false), None);
        // ceil mode: 6 with k=3, s=2, p=1 -> 3.5 -> 4; the last window starts at 6 < 6 + 1.
        assert_eq!(window_out(6, 3, 2, 1, 1, true), Some(4));
        assert_eq!(window_out(6, 3, 2, 1, 1, false), Some(3));
        assert_eq!(window_out(i64::MAX, 3, 1, i64::MAX, 1, false), None);
        assert_eq!(window_out(8, 3, 0, 0, 1, false), None);
    }
}

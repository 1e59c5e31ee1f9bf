//! `conv_transpose2d`: PyTorch's `ConvTranspose2d` over NCHW, weight
//! `[in, out/groups, kh, kw]`, output size
//! `(len − 1)·stride − 2·padding + dilation·(kernel − 1) + output_padding + 1`.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, Window2, nchw, pair, spatial};
use crate::dim::Dim;

/// A transposed 2-D convolution's geometry (the gradient of a conv with the same
/// window). The bias and a fused epilogue are the IR's and the plan kernel's business.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct ConvTranspose2d {
    pub in_channels: i64,
    pub out_channels: i64,
    /// Kernel, stride, padding (cropped from both sides of the output) and dilation.
    pub window: Window2,
    /// Extra rows and columns added at the bottom and right of the output; each less
    /// than its axis's stride or dilation, as PyTorch requires.
    pub output_padding: [i64; 2],
    pub groups: i64,
}

/// Output length of a transposed conv along one axis, PyTorch's
/// `(len − 1)·stride − 2·pad + dilation·(kernel − 1) + output_padding + 1`; `None` when a
/// value is out of range or the result is not at least 1.
pub fn transpose_out(len: i64, kernel: i64, stride: i64, pad: i64, dilation: i64, out_pad: i64) -> Option<i64> {
    if len < 1 || kernel < 1 || stride < 1 || dilation < 1 || pad < 0 || out_pad < 0 {
        return None;
    }
    let o = (len - 1)
        .checked_mul(stride)?
        .checked_sub(pad.checked_mul(2)?)?
        .checked_add(dilation.checked_mul(kernel - 1)?)?
        .checked_add(out_pad)?
        .checked_add(1)?;
    (o >= 1).then_some(o)
}

impl ConvTranspose2d {
    /// The PyTorch weight shape `[in, out/groups, kh, kw]`.
    pub fn weight_shape(&self) -> [i64; 4] {
        let w = &self.window;
        [self.in_channels, self.out_channels / self.groups.max(1), w.kernel[0], w.kernel[1]]
    }

    /// The output length along `axis` (0: height, 1: width) for an input of `len`.
    pub fn out_len(&self, axis: usize, len: i64) -> Option<i64> {
        let w = &self.window;
        transpose_out(len, w.kernel[axis], w.stride[axis], w.padding[axis], w.dilation[axis], self.output_padding[axis])
    }

    /// The kernel's view of the layer at an input of `n x in x h x w`. Sizes that do not
    /// fit give an output of 0, which the kernel's check refuses.
    pub fn shape(&self, n: usize, h: usize, w: usize) -> ConvTranspose2dShape {
        let win = &self.window;
        let u = |v: i64| usize::try_from(v).unwrap_or(0);
        let out = |axis: usize, len: usize| i64::try_from(len).ok().and_then(|l| self.out_len(axis, l)).map_or(0, u);
        ConvTranspose2dShape {
            n,
            cin: u(self.in_channels),
            h,
            w,
            cout: u(self.out_channels),
            kh: u(win.kernel[0]),
            kw: u(win.kernel[1]),
            stride_h: u(win.stride[0]),
            stride_w: u(win.stride[1]),
            pad_h: u(win.padding[0]),
            pad_w: u(win.padding[1]),
            dil_h: u(win.dilation[0]),
            dil_w: u(win.dilation[1]),
            groups: u(self.groups),
            oh: out(0, h),
            ow: out(1, w),
        }
    }
}

/// The geometry of one transposed conv layer: input `[n, cin, h, w]`, weight (PyTorch
/// layout) `[cin, cout/groups, kh, kw]`, output `[n, cout, oh, ow]`. Input pixel
/// `(iy, ix)` and tap `(ky, kx)` add to output pixel
/// `(iy·stride_h − pad_h + ky·dil_h, ix·stride_w − pad_w + kx·dil_w)` when it is inside.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvTranspose2dShape {
    pub n: usize,
    pub cin: usize,
    pub h: usize,
    pub w: usize,
    pub cout: usize,
    pub kh: usize,
    pub kw: usize,
    pub stride_h: usize,
    pub stride_w: usize,
    pub pad_h: usize,
    pub pad_w: usize,
    pub dil_h: usize,
    pub dil_w: usize,
    pub groups: usize,
    pub oh: usize,
    pub ow: usize,
}

impl ConvTranspose2dShape {
    /// Input channels per group.
    pub fn cin_g(&self) -> usize {
        self.cin / self.groups.max(1)
    }

    /// Output channels per group.
    pub fn cout_g(&self) -> usize {
        self.cout / self.groups.max(1)
    }

    /// Elements of the weight, `cin · cout/groups · kh · kw` (saturating).
    pub fn weight_len(&self) -> usize {
        self.cin.saturating_mul(self.cout_g()).saturating_mul(self.kh).saturating_mul(self.kw)
    }
}

impl Operator for ConvTranspose2d {
    fn kind_name(&self) -> &'static str {
        "conv_transpose2d"
    }

    /// Each input element is scattered through `out/groups x kh x kw` products.
    fn multiply_adds(&self, inputs: &[&[usize]], _output: &[usize]) -> u64 {
        let [_, cout_g, kh, kw] = self.weight_shape().map(|d| d.max(0) as u64);
        inputs.first().map_or(0, |x| super::count(x)).saturating_mul(cout_g * kh * kw)
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = "conv_transpose2d";
        let x = nchw(inputs[0], name)?;
        let cin =
            x.known_dim(1).ok_or_else(|| ShapeError::new(format!("{name} needs a known channel count, got {x}")))?;
        if cin != self.in_channels {
            return Err(ShapeError::new(format!("{name} expects {} input channels, got {x}", self.in_channels)));
        }
        if self.out_channels < 1 {
            return Err(ShapeError::new(format!(
                "{name} needs at least one output channel, not {}",
                self.out_channels
            )));
        }
        if self.groups < 1 || cin % self.groups != 0 || self.out_channels % self.groups != 0 {
            return Err(ShapeError::new(format!(
                "{name} groups={} must divide both {cin} input and {} output channels",
                self.groups, self.out_channels
            )));
        }
        let w = &self.window;
        if w.kernel.iter().chain(&w.stride).chain(&w.dilation).any(|&v| v < 1) || w.padding.iter().any(|&p| p < 0) {
            return Err(ShapeError::new(format!(
                "{name} kernel {}, stride {}, dilation {}: each must be at least 1, and padding {} at least 0",
                pair(w.kernel),
                pair(w.stride),
                pair(w.dilation),
                pair(w.padding)
            )));
        }
        for i in 0..2 {
            let (op, s, d) = (self.output_padding[i], w.stride[i], w.dilation[i]);
            if op < 0 || (op >= s && op >= d) {
                return Err(ShapeError::new(format!(
                    "{name} output_padding {} must be smaller than either stride {} or dilation {}",
                    pair(self.output_padding),
                    pair(w.stride),
                    pair(w.dilation)
                )));
            }
        }
        let mut out = vec![x.shape[0].clone(), Dim::known(self.out_channels)];
        for i in 0..2 {
            let len = spatial(x, 2 + i, name)?;
            match self.out_len(i, len) {
                Some(o) => out.push(Dim::known(o)),
                None => {
                    return Err(ShapeError::new(format!(
                        "{name} kernel {}x{} (stride {}, padding {}, dilation {}) gives no output for input {x}",
                        w.kernel[0],
                        w.kernel[1],
                        pair(w.stride),
                        pair(w.padding),
                        pair(w.dilation)
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
            ("output_padding", pair(self.output_padding)),
            ("dilation", pair(w.dilation)),
            ("groups", self.groups.to_string()),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    // Input elements x out/groups x kh x kw, by hand.
    #[test]
    fn multiply_adds_count_each_input_s_products() {
        assert_eq!(ct(4, 6, 2, 2, 0, 0, 1, 2).multiply_adds(&[&[1, 4, 5, 5]], &[1, 6, 10, 10]), 100 * 3 * 4);
    }

    #[allow(clippy::too_many_arguments)]
    fn ct(cin: i64, cout: i64, k: i64, s: i64, p: i64, op: i64, d: i64, g: i64) -> ConvTranspose2d {
        let window = Window2 { kernel: [k, k], stride: [s, s], padding: [p, p], dilation: [d, d] };
        ConvTranspose2d { in_channels: cin, out_channels: cout, window, output_padding: [op, op], groups: g }
    }

    // Expected sizes hand-computed with PyTorch's formula
    // (L - 1)·s - 2p + d(k - 1) + op + 1.
    #[test]
    fn output_sizes() {
        // SECOND's FPN deblock: k=2, s=2 doubles: (124-1)·2 + 1 + 1 = 248.
        assert_eq!(run(&ct(128, 128, 2, 2, 0, 0, 1, 1), &[t(&[1, 128, 124, 108])]), Ok(t(&[1, 128, 248, 216])));
        // (5-1)·2 - 2 + 2 + 1 + 1 = 10 (k=3, s=2, p=1, op=1: the exact double).
        assert_eq!(run(&ct(4, 6, 3, 2, 1, 1, 1, 2), &[t(&[2, 4, 5, 7])]), Ok(t(&[2, 6, 10, 14])));
        // Dilation 2, stride 1: (4-1) - 0 + 2·2 + 0 + 1 = 8; output_padding 1 < dilation 2.
        assert_eq!(run(&ct(3, 3, 3, 1, 0, 1, 2, 3), &[t(&[1, 3, 4, 4])]), Ok(t(&[1, 3, 9, 9])));
        // Rectangular: h: (3-1)·3 - 2 + 1 + 0 + 1 = 6; w: (5-1)·1 - 0 + 1 + 0 + 1 = 6.
        let w = Window2 { kernel: [2, 2], stride: [3, 1], padding: [1, 0], dilation: [1, 1] };
        let op = ConvTranspose2d { in_channels: 2, out_channels: 1, window: w, output_padding: [0, 0], groups: 1 };
        assert_eq!(run(&op, &[t(&[1, 2, 3, 5])]), Ok(t(&[1, 1, 6, 6])));
        assert_eq!(op.weight_shape(), [2, 1, 2, 2]);
    }

    #[test]
    fn rejects_bad_channels_groups_padding_and_sizes() {
        let e = run(&ct(3, 4, 3, 1, 0, 0, 1, 1), &[t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("3 input channels"), "{e:?}");
        let e = run(&ct(4, 6, 3, 1, 0, 0, 1, 4), &[t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("groups=4"), "{e:?}");
        // output_padding 2 with stride 2, dilation 1: PyTorch refuses it.
        let e = run(&ct(4, 4, 3, 2, 0, 2, 1, 1), &[t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("output_padding 2 must be smaller than either stride 2 or dilation 1"), "{e:?}");
        // (1-1)·1 - 2·2 + 0 + 0 + 1 = -3: no output.
        let e = run(&ct(4, 4, 1, 1, 2, 0, 1, 1), &[t(&[1, 4, 1, 1])]).expect_err("an error");
        assert!(e.message.contains("gives no output"), "{e:?}");
        let e = run(&ct(4, 4, 1, 1, 0, 0, 1, 1), &[t(&[4, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("4-D"), "{e:?}");
        let e = run(&ct(4, 4, 2, 0, 0, 0, 1, 1), &[t(&[1, 4, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("stride 0, dilation 1: each must be at least 1"), "{e:?}");
        assert_eq!(transpose_out(i64::MAX, 3, 2, 0, 1, 0), None);
        assert_eq!(transpose_out(4, 3, 0, 0, 1, 0), None);
    }
}

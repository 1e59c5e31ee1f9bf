//! `conv3d`: PyTorch's `Conv3d` over NCDHW, weight `[out, in/groups, kd, kh, kw]`. Each
//! spatial axis is sized by the sliding-window rule conv2d and pooling use
//! ([`window_out`]), so the output is PyTorch's
//! `floor((len + 2·padding − dilation·(kernel − 1) − 1) / stride) + 1` per axis.

use serde::{Deserialize, Serialize};

use super::{Operator, ShapeError, ShapeResult, TensorType, spatial, window_out};
use crate::dim::Dim;

/// A 3-D sliding window: per axis (depth, height, width) its kernel size, stride, zero
/// padding on both sides and dilation.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Window3 {
    pub kernel: [i64; 3],
    pub stride: [i64; 3],
    pub padding: [i64; 3],
    pub dilation: [i64; 3],
}

impl Window3 {
    /// A 1x1x1 window: stride 1, no padding, no dilation.
    pub const ONE: Window3 = Window3 { kernel: [1; 3], stride: [1; 3], padding: [0; 3], dilation: [1; 3] };

    /// The output length along `axis` (0: depth, 1: height, 2: width) for an input of
    /// `len`, or `None` when the window does not fit or a value is out of range.
    pub fn out_len(&self, axis: usize, len: i64) -> Option<i64> {
        window_out(len, self.kernel[axis], self.stride[axis], self.padding[axis], self.dilation[axis], false)
    }
}

/// A 3-D convolution's geometry. The bias and a fused epilogue are the IR's and the plan
/// kernel's business.
#[derive(Clone, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Conv3d {
    pub in_channels: i64,
    pub out_channels: i64,
    pub window: Window3,
    pub groups: i64,
}

impl Conv3d {
    /// The PyTorch weight shape `[out, in/groups, kd, kh, kw]`.
    pub fn weight_shape(&self) -> [i64; 5] {
        let k = self.window.kernel;
        [self.out_channels, self.in_channels / self.groups.max(1), k[0], k[1], k[2]]
    }

    /// Elements of the weight (saturating; 0 when a size is negative).
    pub fn weight_len(&self) -> u64 {
        self.weight_shape().iter().fold(1u64, |a, &d| a.saturating_mul(d.max(0) as u64))
    }

    /// The kernel's view of the layer at an input of `n x in x d x h x w`. Sizes that do
    /// not fit give an output of 0, which the kernel's check refuses.
    pub fn shape(&self, n: usize, d: usize, h: usize, w: usize) -> Conv3dShape {
        let win = &self.window;
        let u = |v: i64| usize::try_from(v).unwrap_or(0);
        let out = |axis: usize, len: usize| i64::try_from(len).ok().and_then(|l| win.out_len(axis, l)).map_or(0, u);
        Conv3dShape {
            n,
            cin: u(self.in_channels),
            cout: u(self.out_channels),
            groups: u(self.groups),
            input: [d, h, w],
            kernel: win.kernel.map(u),
            stride: win.stride.map(u),
            pad: win.padding.map(u),
            dil: win.dilation.map(u),
            out: [out(0, d), out(1, h), out(2, w)],
        }
    }
}

/// The geometry of one conv3d layer: input `[n, cin, d, h, w]`, weight (PyTorch layout)
/// `[cout, cin/groups, kd, kh, kw]`, output `[n, cout, od, oh, ow]`. Output voxel
/// `(z, y, x)` reads input voxel `(z·stride − pad + kz·dil, ...)` through tap
/// `(kz, ky, kx)`, zero outside. Per-axis arrays are ordered depth, height, width.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Conv3dShape {
    pub n: usize,
    pub cin: usize,
    pub cout: usize,
    pub groups: usize,
    /// Input depth, height, width.
    pub input: [usize; 3],
    pub kernel: [usize; 3],
    pub stride: [usize; 3],
    pub pad: [usize; 3],
    pub dil: [usize; 3],
    /// Output depth, height, width.
    pub out: [usize; 3],
}

impl Conv3dShape {
    /// Input channels per group.
    pub fn cin_g(&self) -> usize {
        self.cin / self.groups.max(1)
    }

    /// Output channels per group.
    pub fn cout_g(&self) -> usize {
        self.cout / self.groups.max(1)
    }

    /// Taps of the kernel, `kd · kh · kw` (saturating).
    pub fn taps(&self) -> usize {
        self.kernel.iter().fold(1usize, |a, &k| a.saturating_mul(k))
    }

    /// Rows of the unfolded (vol2col) matrix: one per (input channel of a group, tap).
    pub fn k(&self) -> usize {
        self.cin_g().saturating_mul(self.taps())
    }

    /// Elements of the weight, `cout · cin/groups · kd · kh · kw` (saturating).
    pub fn weight_len(&self) -> usize {
        self.cout.saturating_mul(self.k())
    }

    /// Voxels of one input channel (saturating).
    pub fn in_plane(&self) -> usize {
        self.input.iter().fold(1usize, |a, &d| a.saturating_mul(d))
    }

    /// Voxels of one output channel (saturating).
    pub fn out_plane(&self) -> usize {
        self.out.iter().fold(1usize, |a, &d| a.saturating_mul(d))
    }
}

/// `[a, a, a]` as `a`, else `axbxc`: how printouts show triples.
pub(crate) fn triple(p: [i64; 3]) -> String {
    if p[0] == p[1] && p[1] == p[2] { p[0].to_string() } else { format!("{}x{}x{}", p[0], p[1], p[2]) }
}

impl Operator for Conv3d {
    fn kind_name(&self) -> &'static str {
        "conv3d"
    }

    /// Each output element sums `in/groups x kd x kh x kw` products.
    fn multiply_adds(&self, _inputs: &[&[usize]], output: &[usize]) -> u64 {
        let [_, cin_g, kd, kh, kw] = self.weight_shape().map(|d| d.max(0) as u64);
        super::count(output).saturating_mul(cin_g * kd * kh * kw)
    }

    fn infer(&self, inputs: &[&TensorType]) -> ShapeResult<TensorType> {
        let name = "conv3d";
        let x = inputs[0];
        if x.rank() != 5 {
            return Err(ShapeError::new(format!("{name} expects a 5-D NCDHW tensor, got {x}")));
        }
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
                triple(w.kernel),
                triple(w.stride),
                triple(w.dilation),
                triple(w.padding)
            )));
        }
        let mut out = vec![x.shape[0].clone(), Dim::known(self.out_channels)];
        for i in 0..3 {
            let len = spatial(x, 2 + i, name)?;
            match w.out_len(i, len) {
                Some(o) => out.push(Dim::known(o)),
                None => {
                    let k = w.kernel;
                    return Err(ShapeError::new(format!(
                        "{name} kernel {}x{}x{} (dilation {}) does not fit input {x} with padding {}",
                        k[0],
                        k[1],
                        k[2],
                        triple(w.dilation),
                        triple(w.padding)
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
            ("kernel", triple(w.kernel)),
            ("stride", triple(w.stride)),
            ("padding", triple(w.padding)),
            ("dilation", triple(w.dilation)),
            ("groups", self.groups.to_string()),
        ]
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::{run, t};
    use super::*;

    // Output elements x in/groups x kd x kh x kw, by hand.
    #[test]
    fn multiply_adds_count_each_output_s_products() {
        let c = conv(2, 4, [3; 3], [1; 3], [0; 3], [1; 3], 1);
        assert_eq!(c.multiply_adds(&[&[1, 2, 5, 5, 5]], &[1, 4, 3, 3, 3]), 108 * 2 * 27);
    }

    fn conv(cin: i64, cout: i64, k: [i64; 3], s: [i64; 3], p: [i64; 3], d: [i64; 3], g: i64) -> Conv3d {
        let window = Window3 { kernel: k, stride: s, padding: p, dilation: d };
        Conv3d { in_channels: cin, out_channels: cout, window, groups: g }
    }

    // Expected sizes hand-computed with PyTorch's formula
    // floor((L + 2p - d(k-1) - 1) / s) + 1, per axis.
    #[test]
    fn output_sizes() {
        // SECOND's middle encoder: 3x3x3, padding 1 keeps [41, 16, 14].
        let same = conv(16, 16, [3; 3], [1; 3], [1; 3], [1; 3], 1);
        assert_eq!(run(&same, &[t(&[1, 16, 41, 16, 14])]), Ok(t(&[1, 16, 41, 16, 14])));
        // Its depth-downsampling conv: kernel (3, 1, 1), stride (2, 1, 1): (41 - 3) / 2 + 1 = 20.
        let down = conv(64, 64, [3, 1, 1], [2, 1, 1], [0; 3], [1; 3], 1);
        assert_eq!(run(&down, &[t(&[2, 64, 41, 8, 7])]), Ok(t(&[2, 64, 20, 8, 7])));
        // Stride 2, padding 1: (9 + 2 - 3) / 2 + 1 = 5; (8 + 2 - 3) / 2 + 1 = 4 (floor 3.5 + 1);
        // dilation 2 on width: (7 + 2 - 4 - 1) / 2 + 1 = 3.
        let mixed = conv(4, 6, [3; 3], [2; 3], [1; 3], [1, 1, 2], 2);
        assert_eq!(run(&mixed, &[t(&[1, 4, 9, 8, 7])]), Ok(t(&[1, 6, 5, 4, 3])));
        // Depthwise 1x1x1: the same size.
        let dw = conv(5, 10, [1; 3], [1; 3], [0; 3], [1; 3], 5);
        assert_eq!(run(&dw, &[t(&[3, 5, 2, 3, 4])]), Ok(t(&[3, 10, 2, 3, 4])));
        assert_eq!(dw.weight_shape(), [10, 1, 1, 1, 1]);
        assert_eq!(mixed.weight_shape(), [6, 2, 3, 3, 3]);
        assert_eq!(mixed.weight_len(), 324);
        let s = mixed.shape(1, 9, 8, 7);
        assert_eq!((s.out, s.k(), s.weight_len(), s.out_plane()), ([5, 4, 3], 54, 324, 60));
    }

    #[test]
    fn symbolic_batch_is_kept() {
        let x = TensorType::f32(vec![Dim::symbol("N"), Dim::known(2), Dim::known(4), Dim::known(4), Dim::known(4)]);
        let out = run(&conv(2, 3, [2; 3], [2; 3], [0; 3], [1; 3], 1), &[x]).expect("infers");
        assert_eq!(out.shape[0], Dim::symbol("N"));
        assert_eq!(&out.shape[1..], &[3, 2, 2, 2].map(Dim::known));
    }

    #[test]
    fn rejects_bad_channels_groups_windows_and_ranks() {
        let one = [1; 3];
        let e = run(&conv(3, 8, [3; 3], one, one, one, 1), &[t(&[1, 4, 8, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("3 input channels"), "{e:?}");
        let e = run(&conv(4, 6, [3; 3], one, one, one, 4), &[t(&[1, 4, 8, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("groups=4 must divide both 4 input and 6 output"), "{e:?}");
        // (3 + 0 - 4 - 1) / 1 + 1 = 0 on the height: no output.
        let e = run(&conv(4, 6, [1, 5, 1], one, [0; 3], one, 1), &[t(&[1, 4, 8, 3, 8])]).expect_err("an error");
        assert!(e.message.contains("kernel 1x5x1 (dilation 1) does not fit"), "{e:?}");
        let e = run(&conv(4, 6, one, one, [0; 3], one, 1), &[t(&[1, 4, 8, 8])]).expect_err("an error");
        assert!(e.message.contains("5-D NCDHW"), "{e:?}");
        let e = run(&conv(4, 6, [2; 3], [1, 0, 1], [0; 3], one, 1), &[t(&[1, 4, 3, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("stride 1x0x1, dilation 1: each must be at least 1"), "{e:?}");
        let e = run(&conv(4, 0, one, one, [0; 3], one, 1), &[t(&[1, 4, 3, 3, 3])]).expect_err("an error");
        assert!(e.message.contains("at least one output channel"), "{e:?}");
        let x = TensorType::f32(vec![Dim::known(1), Dim::known(4), Dim::symbol("D"), Dim::known(3), Dim::known(3)]);
        let e = run(&conv(4, 6, one, one, [0; 3], one, 1), &[x]).expect_err("an error");
        assert!(e.message.contains("known spatial sizes"), "{e:?}");
    }
}

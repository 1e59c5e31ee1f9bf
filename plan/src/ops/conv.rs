//! `conv2d`: 2-D convolution over NCHW, weight `[out, in/groups, kh, kw]`.

use serde::{Deserialize, Serialize};

use super::{Operator, PANEL, ShapeError, ShapeResult, TensorType, Window2, nchw, pair, spatial};
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

impl Conv2d {
    /// The output of the conv with its fused inputs (`Kernel::Conv2d { residual,
    /// channel_scale }`, the compiler's `fuse_residual` and `fuse_channel_scale`):
    /// `inputs` are its input, then the residual, of the output's shape, when `residual`,
    /// then the channel scale, `[N, in, 1, 1]` for an input of `N` images, when
    /// `channel_scale`.
    pub fn infer_fused(&self, inputs: &[&TensorType], residual: bool, channel_scale: bool) -> ShapeResult<TensorType> {
        let want = 1 + usize::from(residual) + usize::from(channel_scale);
        if inputs.len() != want {
            return Err(ShapeError::new(format!(
                "a conv{}{} takes {want} inputs, got {}",
                if residual { " with a residual" } else { "" },
                if channel_scale { " with a channel scale" } else { "" },
                inputs.len()
            )));
        }
        let x = inputs[0];
        let out = super::infer(self, &[x])?;
        if residual && inputs[1].shape != out.shape {
            return Err(ShapeError::new(format!(
                "its residual input has shape {}, not its output's {}",
                crate::show_shape(&inputs[1].shape),
                crate::show_shape(&out.shape)
            )));
        }
        if channel_scale {
            let s = inputs[want - 1];
            let one = crate::Dim::known(1);
            let fits = s.rank() == 4
                && x.rank() == 4
                && s.shape[0] == x.shape[0]
                && s.shape[1] == x.shape[1]
                && s.shape[2] == one
                && s.shape[3] == one;
            if !fits {
                return Err(ShapeError::new(format!(
                    "its channel scale has shape {}, not [N, C, 1, 1] of its input {}",
                    crate::show_shape(&s.shape),
                    crate::show_shape(&x.shape)
                )));
            }
        }
        Ok(out)
    }

    /// The kernel's view of the layer at an input of `n x in x h x w`: the one place a
    /// [`Conv2dShape`] is built (the compiler packs weights at `n = 1`, the runtime binds
    /// at the batch size). A window that does not fit gives an output size of 0, which
    /// every kernel and check refuses.
    pub fn shape(&self, n: usize, h: usize, w: usize) -> Conv2dShape {
        let win = &self.window;
        let u = |v: i64| usize::try_from(v).unwrap_or(0);
        let out =
            |axis: usize, len: usize| i64::try_from(len).ok().and_then(|l| win.out_len(axis, l, false)).map_or(0, u);
        Conv2dShape {
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

/// The geometry of one conv layer: input `[n, cin, h, w]`, weight (PyTorch layout)
/// `[cout, cin/groups, kh, kw]`, output `[n, cout, oh, ow]` with PyTorch's
/// `oh = (h + 2·pad_h − dil_h·(kh − 1) − 1) / stride_h + 1` (likewise `ow`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Conv2dShape {
    /// Batch size.
    pub n: usize,
    /// Input channels.
    pub cin: usize,
    /// Input height.
    pub h: usize,
    /// Input width.
    pub w: usize,
    /// Output channels.
    pub cout: usize,
    /// Kernel height.
    pub kh: usize,
    /// Kernel width.
    pub kw: usize,
    /// Vertical stride.
    pub stride_h: usize,
    /// Horizontal stride.
    pub stride_w: usize,
    /// Zero padding above and below.
    pub pad_h: usize,
    /// Zero padding left and right.
    pub pad_w: usize,
    /// Vertical dilation.
    pub dil_h: usize,
    /// Horizontal dilation.
    pub dil_w: usize,
    /// Channel groups; divides `cin` and `cout`.
    pub groups: usize,
    /// Output height.
    pub oh: usize,
    /// Output width.
    pub ow: usize,
}

impl Conv2dShape {
    /// Input channels per group.
    pub fn cin_g(&self) -> usize {
        self.cin / self.groups
    }

    /// Output channels per group.
    pub fn cout_g(&self) -> usize {
        self.cout / self.groups
    }

    /// Rows of the im2col matrix: one per (input channel of a group, ky, kx).
    pub fn k(&self) -> usize {
        self.cin_g().saturating_mul(self.kh).saturating_mul(self.kw)
    }

    /// A 3x3, stride-1, undilated layer: what Winograd computes.
    pub fn is_winograd_shape(&self) -> bool {
        self.kh == 3 && self.kw == 3 && self.stride_h == 1 && self.stride_w == 1 && self.dil_h == 1 && self.dil_w == 1
    }
}

/// How a conv layer is computed (see `readi_runtime::kernels::conv`). Chosen once per
/// layer by the compiler; the packed weight is specific to it. Plans name it as
/// [`ConvAlgo::name`] spells it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ConvAlgo {
    /// 1x1, stride 1, no padding: GEMM straight on the input. Weight as PyTorch's.
    Gemm1x1,
    /// General: unfold a tile of pixels, one GEMM, epilogue. Weight as PyTorch's.
    Im2col,
    /// Winograd F(2x2, 3x3) for 3x3 stride-1 undilated convs. Weight `[16, cout, cin/groups]`.
    Winograd2,
    /// Winograd F(4x4, 3x3) for 3x3 stride-1 undilated convs. Weight `[36, cout, cin/groups]`.
    Winograd4,
    /// Direct loop for one input channel per group (depthwise). Weight as PyTorch's.
    Depthwise,
    /// Small planes, one group: each image unfolded pixel by pixel, one GEMM with the
    /// output channels in the vector lanes. Weight `[ceil(cout / PANEL)][k][PANEL]`: the
    /// panels of a linear layer ([`PANEL`]), `k = cin · kh · kw`, padded with zeros.
    Panels,
}

impl Conv2dShape {
    /// A square layer without dilation: `n x cin x hw x hw` to `cout` channels with a
    /// `k x k` kernel; the output size follows PyTorch's formula.
    #[allow(clippy::too_many_arguments)]
    pub fn square(
        n: usize,
        cin: usize,
        hw: usize,
        cout: usize,
        k: usize,
        stride: usize,
        pad: usize,
        groups: usize,
    ) -> Self {
        let o = (hw + 2 * pad - k) / stride + 1;
        Conv2dShape {
            n,
            cin,
            h: hw,
            w: hw,
            cout,
            kh: k,
            kw: k,
            stride_h: stride,
            stride_w: stride,
            pad_h: pad,
            pad_w: pad,
            dil_h: 1,
            dil_w: 1,
            groups,
            oh: o,
            ow: o,
        }
    }
}

impl ConvAlgo {
    /// Every algorithm, for listings and tests.
    pub const ALL: [ConvAlgo; 6] = [
        ConvAlgo::Gemm1x1,
        ConvAlgo::Im2col,
        ConvAlgo::Winograd2,
        ConvAlgo::Winograd4,
        ConvAlgo::Depthwise,
        ConvAlgo::Panels,
    ];

    /// The name stored in plan files.
    pub fn name(self) -> &'static str {
        match self {
            ConvAlgo::Gemm1x1 => "gemm1x1",
            ConvAlgo::Im2col => "im2col",
            ConvAlgo::Winograd2 => "winograd2",
            ConvAlgo::Winograd4 => "winograd4",
            ConvAlgo::Depthwise => "depthwise",
            ConvAlgo::Panels => "panels",
        }
    }

    /// The algorithm called `name` (as [`ConvAlgo::name`] spells it).
    pub fn from_name(name: &str) -> Option<ConvAlgo> {
        ConvAlgo::ALL.into_iter().find(|a| a.name() == name)
    }

    /// Whether the algorithm can compute this layer.
    pub fn supports(self, s: &Conv2dShape) -> bool {
        match self {
            ConvAlgo::Gemm1x1 => {
                s.kh == 1 && s.kw == 1 && s.stride_h == 1 && s.stride_w == 1 && s.pad_h == 0 && s.pad_w == 0
            }
            ConvAlgo::Im2col => true,
            ConvAlgo::Winograd2 | ConvAlgo::Winograd4 => s.is_winograd_shape(),
            ConvAlgo::Depthwise => s.cin_g() == 1,
            ConvAlgo::Panels => s.groups == 1,
        }
    }

    /// Whether packing a weight for this algorithm keeps PyTorch's layout
    /// `[cout, cin/groups, kh, kw]` (the GEMM paths), so packing is a copy. A fused LoRA
    /// branch's `A` is stored packed for these and raw for the others
    /// ([`LoraSpec::a_raw`](crate::format::LoraSpec::a_raw)).
    pub fn packs_as_is(self) -> bool {
        matches!(self, ConvAlgo::Gemm1x1 | ConvAlgo::Im2col | ConvAlgo::Depthwise)
    }

    /// Length of the weight packed for this algorithm; saturates at `usize::MAX` (which
    /// no stored tensor has, so a plan declaring such a layer is refused).
    pub fn packed_len(self, s: &Conv2dShape) -> usize {
        let (rows, per) = match self {
            ConvAlgo::Gemm1x1 | ConvAlgo::Im2col | ConvAlgo::Depthwise => (s.cout, s.k()),
            ConvAlgo::Winograd2 => (s.cout, s.cin_g().saturating_mul(16)),
            ConvAlgo::Winograd4 => (s.cout, s.cin_g().saturating_mul(36)),
            ConvAlgo::Panels => (s.cout.div_ceil(PANEL).saturating_mul(PANEL), s.k()),
        };
        rows.saturating_mul(per)
    }

    /// The algorithm whose packing a fused LoRA branch's `A` takes for this one: its own,
    /// but PyTorch's layout (im2col's) for [`ConvAlgo::Panels`], whose kernel reads `A`'s
    /// few rows as they are (panels would pad them to [`PANEL`] rows).
    pub fn lora_a_layout(self) -> ConvAlgo {
        if self == ConvAlgo::Panels { ConvAlgo::Im2col } else { self }
    }
}

impl std::fmt::Display for ConvAlgo {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.pad(self.name())
    }
}

impl Operator for Conv2d {
    fn kind_name(&self) -> &'static str {
        "conv2d"
    }

    /// Each output element sums `in/groups x kh x kw` products.
    fn multiply_adds(&self, _inputs: &[&[usize]], output: &[usize]) -> u64 {
        let [_, cin_g, kh, kw] = self.weight_shape().map(|d| d.max(0) as u64);
        super::count(output).saturating_mul(cin_g * kh * kw)
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

    // Output elements x in/groups x kh x kw, by hand.
    #[test]
    fn multiply_adds_count_each_output_s_products() {
        assert_eq!(conv(8, 8, 3, 1, 1, 1, 8).multiply_adds(&[&[1, 8, 10, 10]], &[1, 8, 10, 10]), 800 * 9);
        assert_eq!(conv(4, 6, 3, 2, 0, 1, 2).multiply_adds(&[&[1, 4, 9, 8]], &[1, 6, 4, 3]), 72 * 2 * 9);
    }

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

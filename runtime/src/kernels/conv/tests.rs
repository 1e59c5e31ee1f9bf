//! Every algorithm against a plain f64 reference, on odd shapes, batches, groups,
//! dilation and each thread count and epilogue kind; plus the choices of [`choose`] on
//! ResNet-18's layers and the measured rounding error of each algorithm.

use super::split::split_shape;
use super::*;
use crate::kernels::Activation;
use crate::kernels::testutil::{assert_close, data};

/// Shape with PyTorch's output size.
#[allow(clippy::too_many_arguments)]
fn shape(
    n: usize,
    cin: usize,
    (h, w): (usize, usize),
    cout: usize,
    (kh, kw): (usize, usize),
    (stride_h, stride_w): (usize, usize),
    (pad_h, pad_w): (usize, usize),
    (dil_h, dil_w): (usize, usize),
    groups: usize,
) -> Conv2dShape {
    let oh = (h + 2 * pad_h - dil_h * (kh - 1) - 1) / stride_h + 1;
    let ow = (w + 2 * pad_w - dil_w * (kw - 1) - 1) / stride_w + 1;
    Conv2dShape { n, cin, h, w, cout, kh, kw, stride_h, stride_w, pad_h, pad_w, dil_h, dil_w, groups, oh, ow }
}

/// Plain 7-loop convolution in f64, PyTorch weight layout, then the epilogue.
fn reference(s: &Conv2dShape, x: &[f32], w: &[f32], ep: &Epilogue) -> Vec<f32> {
    let (cin_g, cout_g) = (s.cin / s.groups, s.cout / s.groups);
    let mut out = vec![0.0; s.n * s.cout * s.oh * s.ow];
    for n in 0..s.n {
        for co in 0..s.cout {
            let g = co / cout_g;
            for oy in 0..s.oh {
                for ox in 0..s.ow {
                    let mut acc = 0.0f64;
                    for ci in 0..cin_g {
                        for ky in 0..s.kh {
                            for kx in 0..s.kw {
                                let iy = (oy * s.stride_h + ky * s.dil_h) as isize - s.pad_h as isize;
                                let ix = (ox * s.stride_w + kx * s.dil_w) as isize - s.pad_w as isize;
                                if iy < 0 || ix < 0 || iy >= s.h as isize || ix >= s.w as isize {
                                    continue;
                                }
                                let xv = x[((n * s.cin + g * cin_g + ci) * s.h + iy as usize) * s.w + ix as usize];
                                let wv = w[((co * cin_g + ci) * s.kh + ky) * s.kw + kx];
                                acc += f64::from(xv) * f64::from(wv);
                            }
                        }
                    }
                    let mut y =
                        acc * ep.scale.map_or(1.0, |v| f64::from(v[co])) + ep.shift.map_or(0.0, |v| f64::from(v[co]));
                    if let Some(act) = ep.act {
                        y = act.reference(y);
                    }
                    out[((n * s.cout + co) * s.oh + oy) * s.ow + ox] = y as f32;
                }
            }
        }
    }
    out
}

/// Runs `algo` on `s` with each thread count and epilogue kind, against the reference.
fn check(s: &Conv2dShape, algo: ConvAlgo) {
    assert!(algo.supports(s), "{} does not support {s:?}", algo.name());
    let x = data(s.n * s.cin * s.h * s.w, 1);
    // Weights at a trained layer's scale (~1/sqrt(fan-in)), so outputs are O(1) and the
    // tolerance is relative to the output's scale; `error_levels` checks unscaled data.
    let fan_in = s.cin / s.groups * s.kh * s.kw;
    let w: Vec<f32> = data(fan_in * s.cout, 2).iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect();
    let scale: Vec<f32> = data(s.cout, 3).iter().map(|v| 0.5 + v).collect();
    let shift = data(s.cout, 4);
    let mut packed = vec![0.0; packed_weight_len(s, algo)];
    pack_weight(s, algo, &w, &mut packed);
    let eps = [
        Epilogue::default(),
        Epilogue { scale: None, shift: Some(&shift), act: None },
        Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) },
        Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Hardswish) },
        Epilogue { scale: None, shift: Some(&shift), act: Some(Activation::Silu) },
    ];
    for ep in &eps {
        let want = reference(s, &x, &w, ep);
        for threads in [1, 2, 3] {
            let mut out = vec![f32::NAN; want.len()];
            let mut scratch = vec![f32::NAN; scratch_len(s, algo, threads)];
            conv2d(s, algo, &packed, ep, &x, &mut out, &mut scratch, threads);
            assert_close(&out, &want, 1e-4);
        }
    }
}

/// Checks every algorithm that supports the shape; returns how many did.
fn check_all(s: &Conv2dShape) -> usize {
    let algos: Vec<ConvAlgo> = ConvAlgo::ALL.into_iter().filter(|a| a.supports(s)).collect();
    for &algo in &algos {
        check(s, algo);
    }
    algos.len()
}

#[test]
fn plain_3x3() {
    assert_eq!(check_all(&shape(1, 5, (9, 11), 7, (3, 3), (1, 1), (1, 1), (1, 1), 1)), 4);
}

#[test]
fn stride_2_padding_batch() {
    check_all(&shape(2, 3, (10, 7), 4, (3, 3), (2, 2), (1, 1), (1, 1), 1));
    check_all(&shape(3, 6, (9, 9), 5, (3, 3), (2, 1), (0, 2), (1, 1), 1));
}

#[test]
fn groups() {
    check_all(&shape(1, 4, (8, 9), 6, (3, 3), (1, 1), (1, 1), (1, 1), 2));
    check_all(&shape(2, 8, (9, 8), 8, (3, 3), (2, 2), (1, 1), (1, 1), 4));
    // Winograd per group, with enough channels per group.
    check(&shape(1, 34, (12, 10), 36, (3, 3), (1, 1), (1, 1), (1, 1), 2), ConvAlgo::Winograd4);
}

#[test]
fn depthwise() {
    assert_eq!(check_all(&shape(2, 6, (9, 10), 6, (3, 3), (1, 1), (1, 1), (1, 1), 6)), 4);
    check_all(&shape(1, 3, (11, 8), 6, (3, 3), (2, 2), (1, 1), (1, 1), 3));
    check_all(&shape(1, 4, (10, 10), 4, (5, 5), (2, 2), (2, 2), (2, 2), 4));
}

/// The GEMM paths call the `gemm` crate on pixel counts that are multiples of 16 and the
/// last few pixels on their own (`im2col::gemm_cols`) for deep inputs and narrow outputs:
/// parts of 392, 252 and 280 pixels (a 28x28 plane at 2 and 3 threads), a 399-pixel
/// plane, a remainder under 16, and batches, against the naive conv.
#[test]
fn gemm_tiles_split_off_their_remainder() {
    let cases = [
        shape(1, 100, (28, 28), 30, (1, 1), (1, 1), (0, 0), (1, 1), 1),
        shape(2, 64, (21, 19), 24, (1, 1), (1, 1), (0, 0), (1, 1), 1),
        shape(1, 12, (21, 19), 10, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        shape(1, 40, (5, 7), 16, (3, 3), (1, 1), (1, 1), (1, 1), 1),
    ];
    for s in &cases {
        assert!(im2col::split_remainder(s), "{s:?}");
        let algo = choose(s);
        assert!(matches!(algo, ConvAlgo::Gemm1x1 | ConvAlgo::Im2col), "{s:?} takes {}", algo.name());
        check(s, algo);
    }
}

/// With AVX-512, depthwise layers of output planes up to 28x28 take sixteen channels at a
/// time in the vector lanes (`depthwise/lanes.rs`): channel counts that leave a partial
/// group of sixteen, rows narrower and wider than sixteen pixels and than a block of
/// four outputs, strides 1 and 2, 3x3 to 7x7 kernels, paddings 0 to 3, batches, more
/// groups than one task holds; `check` runs five epilogues (SiLU on the sums in
/// registers, hardswish after) at 1 to 3 threads against the naive conv. Without AVX-512
/// the layers take the row path and only the naive comparison runs.
#[test]
fn depthwise_lanes() {
    let cases = [
        shape(1, 5, (7, 7), 5, (3, 3), (2, 2), (1, 1), (1, 1), 5),
        shape(2, 17, (14, 14), 17, (3, 3), (2, 2), (1, 1), (1, 1), 17),
        shape(1, 40, (14, 14), 40, (5, 5), (1, 1), (2, 2), (1, 1), 40),
        shape(3, 16, (9, 20), 16, (7, 7), (1, 1), (3, 3), (1, 1), 16),
        shape(1, 33, (28, 28), 33, (5, 5), (2, 2), (2, 2), (1, 1), 33),
        shape(1, 20, (13, 30), 20, (3, 3), (1, 1), (0, 0), (1, 1), 20),
        shape(1, 300, (4, 4), 300, (3, 3), (1, 1), (1, 1), (1, 1), 300),
        shape(2, 8, (2, 3), 8, (3, 3), (1, 1), (1, 1), (1, 1), 8),
        shape(1, 24, (56, 56), 24, (3, 3), (2, 2), (0, 0), (1, 1), 24),
        shape(1, 3, (15, 17), 3, (7, 7), (2, 2), (3, 3), (1, 1), 3),
    ];
    let lanes = depthwise::lanes_applies(&cases[0]);
    for s in &cases {
        assert_eq!(depthwise::lanes_applies(s), lanes, "{s:?}");
        check(s, ConvAlgo::Depthwise);
    }
    // Not: a 56x56 output, a 3x3 kernel with rows of 16 outputs or more (read in place
    // instead), a channel multiplier, dilation, a 4x4 kernel, stride 3.
    for s in [
        shape(1, 4, (56, 56), 4, (5, 5), (1, 1), (2, 2), (1, 1), 4),
        shape(1, 4, (56, 56), 4, (3, 3), (2, 2), (1, 1), (1, 1), 4),
        shape(1, 4, (14, 14), 8, (3, 3), (1, 1), (1, 1), (1, 1), 4),
        shape(1, 4, (14, 14), 4, (3, 3), (1, 1), (2, 2), (2, 2), 4),
        shape(1, 4, (14, 14), 4, (4, 4), (1, 1), (1, 1), (1, 1), 4),
        shape(1, 4, (14, 14), 4, (3, 3), (3, 3), (1, 1), (1, 1), 4),
    ] {
        assert!(!depthwise::lanes_applies(&s), "{s:?}");
    }
}

/// The lanes path moves sixteen channels through each transpose: a NaN in one channel's
/// input reaches that channel's outputs whose window holds it, and no other channel's.
#[test]
fn depthwise_lanes_keep_a_nan_in_its_channel() {
    let s = shape(1, 20, (14, 14), 20, (5, 5), (2, 2), (2, 2), (1, 1), 20);
    let (hw, plane) = (14, 49);
    let (chan, cy, cx) = (17, 6, 9);
    let mut x = data(20 * hw * hw, 1);
    x[chan * hw * hw + cy * hw + cx] = f32::NAN;
    let w = data(20 * 25, 2);
    for act in [None, Some(Activation::Relu6), Some(Activation::Silu)] {
        let ep = Epilogue { scale: None, shift: None, act };
        for threads in [1, 2] {
            let mut out = vec![0.0; 20 * plane];
            conv2d(&s, ConvAlgo::Depthwise, &w, &ep, &x, &mut out, &mut [], threads);
            for (i, v) in out.iter().enumerate() {
                let (c, oy, ox) = (i / plane, i % plane / 7, i % 7);
                // Output (oy, ox) reads input rows 2 oy - 2 ..= 2 oy + 2, columns likewise.
                let reached = c == chan && (2 * oy).abs_diff(cy) <= 2 && (2 * ox).abs_diff(cx) <= 2;
                assert_eq!(v.is_nan(), reached, "{act:?}, {threads} threads: channel {c} ({oy}, {ox}) = {v}");
            }
        }
    }
}

/// Stride-1 "same" layers of planes with rows of at most 8 pixels take the flat path
/// (`depthwise/flat.rs`): 7x7 planes with 3x3, 5x5 and 7x7 kernels (a plane's last
/// vector partly outside it), a kernel larger than the plane, a channel multiplier, a
/// plane of a few pixels, batches and more planes than one thread's task.
#[test]
fn depthwise_flat_small_planes() {
    let cases = [
        shape(2, 5, (7, 7), 5, (3, 3), (1, 1), (1, 1), (1, 1), 5),
        shape(1, 3, (7, 7), 6, (5, 5), (1, 1), (2, 2), (1, 1), 3),
        shape(1, 4, (7, 7), 4, (7, 7), (1, 1), (3, 3), (1, 1), 4),
        shape(1, 2, (3, 5), 2, (7, 5), (1, 1), (3, 2), (1, 1), 2),
        shape(3, 40, (4, 4), 40, (3, 3), (1, 1), (1, 1), (1, 1), 40),
        shape(1, 300, (6, 8), 300, (3, 3), (1, 1), (1, 1), (1, 1), 300),
    ];
    for s in &cases {
        assert!(depthwise::flat_applies(s), "{s:?} takes the flat path");
        check(s, ConvAlgo::Depthwise);
    }
    // Not: rows of more than 8, stride 2, an output smaller than the input.
    assert!(!depthwise::flat_applies(&shape(1, 2, (14, 14), 2, (3, 3), (1, 1), (1, 1), (1, 1), 2)));
    assert!(!depthwise::flat_applies(&shape(1, 2, (7, 7), 2, (3, 3), (2, 2), (1, 1), (1, 1), 2)));
    assert!(!depthwise::flat_applies(&shape(1, 2, (7, 7), 2, (3, 3), (1, 1), (0, 0), (1, 1), 2)));
}

/// Stride-2 depthwise layers whose output planes are too large for the channels-in-lanes
/// path, so the row path copies each input row split into its even and odd columns: an
/// even width, an odd one with a 5x5 kernel (padding 2, so the even columns go to phase
/// 0), no padding, and a batch, each against the reference. (On AVX-512 machines the ones
/// padded by half their kernel are read in place instead: [`depthwise_read_in_place`].)
/// The 7x7 one (padding 3) and the 5x5 one padded by 1 take the row path on every
/// machine: an odd padding, so the input's even columns go to phase 1.
#[test]
fn depthwise_strided_rows_split_by_phase() {
    let cases = [
        shape(1, 2, (60, 64), 2, (3, 3), (2, 2), (1, 1), (1, 1), 2),
        shape(1, 2, (58, 67), 2, (5, 5), (2, 2), (2, 2), (1, 1), 2),
        shape(1, 2, (102, 33), 2, (3, 3), (2, 2), (0, 0), (1, 1), 2),
        shape(2, 3, (100, 32), 3, (3, 3), (2, 2), (1, 1), (1, 1), 3),
        shape(1, 2, (64, 61), 2, (7, 7), (2, 2), (3, 3), (1, 1), 2),
        shape(1, 3, (66, 59), 3, (5, 5), (2, 2), (1, 1), (1, 1), 3),
    ];
    for s in &cases {
        assert!(s.oh * s.ow > 28 * 28 && !depthwise::lanes_applies(s), "{s:?} takes the row path");
        check(s, ConvAlgo::Depthwise);
    }
    for s in &cases[4..] {
        assert!(!depthwise::in_place_applies(s), "{s:?} takes the row path");
    }
}

/// Depthwise layers which AVX-512 machines read in place (`depthwise/in_place.rs`): 3x3,
/// 5x5 and 7x7 at stride 1 and 3x3 and 5x5 at stride 2 on planes larger than the lanes
/// path takes, and 3x3 on the 28x28 and 16-wide ones it would; odd and even widths (at stride
/// 2 an odd width's last window reaches into the padding), rows of exactly one vector and
/// of a vector and a few pixels (the last vector overlapping), output rows past the
/// blocks of four, two images. Elsewhere they take the row path or the lanes, which the
/// same cases check.
#[test]
fn depthwise_read_in_place() {
    let cases = [
        shape(2, 3, (40, 33), 3, (3, 3), (1, 1), (1, 1), (1, 1), 3),
        shape(1, 2, (31, 45), 2, (5, 5), (1, 1), (2, 2), (1, 1), 2),
        shape(1, 2, (30, 29), 2, (7, 7), (1, 1), (3, 3), (1, 1), 2),
        shape(1, 2, (53, 16), 2, (3, 3), (1, 1), (1, 1), (1, 1), 2),
        shape(2, 2, (75, 66), 2, (3, 3), (2, 2), (1, 1), (1, 1), 2),
        shape(1, 3, (61, 63), 3, (3, 3), (2, 2), (1, 1), (1, 1), 3),
        shape(1, 2, (102, 32), 2, (3, 3), (2, 2), (1, 1), (1, 1), 2),
        shape(1, 20, (56, 56), 20, (3, 3), (2, 2), (1, 1), (1, 1), 20),
        shape(2, 3, (28, 17), 3, (3, 3), (1, 1), (1, 1), (1, 1), 3),
        shape(1, 2, (66, 70), 2, (5, 5), (2, 2), (2, 2), (1, 1), 2),
        shape(2, 3, (63, 61), 3, (5, 5), (2, 2), (2, 2), (1, 1), 3),
    ];
    let avx512 = depthwise::in_place_applies(&cases[0]);
    for s in &cases {
        assert!(!depthwise::lanes_applies(s), "{s:?} takes no lanes");
        assert_eq!(depthwise::in_place_applies(s), avx512, "{s:?}");
        check(s, ConvAlgo::Depthwise);
    }
}

/// Rows wide enough for the depthwise kernel's register-blocked interior, at each stride
/// it has a copy for, with its remainder and borders: MobileNet's 3x3 (stride 1 and 2),
/// EfficientNet's 5x5 stride 2, ConvNeXt's 7x7, a dilated kernel, a channel multiplier,
/// no padding, a stride of 3, and a kernel taller than the 16 rows of taps kept at once.
#[test]
fn depthwise_wide_rows() {
    check(&shape(1, 3, (5, 37), 3, (3, 3), (1, 1), (1, 1), (1, 1), 3), ConvAlgo::Depthwise);
    check(&shape(2, 2, (6, 75), 2, (3, 3), (2, 2), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (9, 70), 2, (5, 5), (2, 2), (2, 2), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (8, 41), 2, (7, 7), (1, 1), (3, 3), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (9, 50), 2, (3, 3), (1, 1), (2, 2), (2, 2), 2), ConvAlgo::Depthwise);
    // Seven output rows: a block of four, then the last four again (narrow rows stored
    // a vector wide, and rows of two vectors).
    check(&shape(1, 2, (14, 14), 2, (3, 3), (2, 2), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(2, 3, (7, 20), 3, (5, 5), (1, 1), (2, 2), (1, 1), 3), ConvAlgo::Depthwise);
    // Blocks of eight rows (5x5 and 7x7 at stride 1, 16 rows or more), then of four,
    // then the rest.
    check(&shape(1, 2, (19, 18), 2, (5, 5), (1, 1), (2, 2), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (16, 33), 2, (7, 7), (1, 1), (3, 3), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (4, 33), 6, (3, 3), (1, 1), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (4, 34), 2, (3, 3), (1, 1), (0, 0), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (4, 52), 2, (3, 3), (3, 3), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 1, (20, 40), 1, (18, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Depthwise);
    // Row and column strides that differ, the column one outside the padded path.
    check(&shape(1, 2, (6, 40), 2, (3, 3), (2, 3), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (6, 40), 2, (3, 3), (3, 2), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    // A plane too large for the zero-padded copy (a BEV grid's): the border path.
    check(&shape(1, 1, (130, 131), 1, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Depthwise);
    // Interiors exactly one block of 16 wide, then the 8- and 4-column blocks (14x14 and
    // 7x7 planes, stride 1 and 2), and one too narrow for any block.
    check(&shape(1, 2, (3, 18), 2, (3, 3), (1, 1), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (3, 17), 2, (3, 3), (1, 1), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 3, (14, 14), 3, (3, 3), (1, 1), (1, 1), (1, 1), 3), ConvAlgo::Depthwise);
    check(&shape(1, 3, (7, 7), 3, (3, 3), (1, 1), (1, 1), (1, 1), 3), ConvAlgo::Depthwise);
    check(&shape(1, 2, (14, 14), 2, (5, 5), (2, 2), (2, 2), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (7, 7), 2, (7, 7), (1, 1), (3, 3), (1, 1), 2), ConvAlgo::Depthwise);
    check(&shape(1, 2, (5, 5), 2, (3, 3), (1, 1), (1, 1), (1, 1), 2), ConvAlgo::Depthwise);
}

#[test]
fn dilation() {
    check_all(&shape(1, 5, (13, 12), 6, (3, 3), (1, 1), (2, 2), (2, 2), 1));
    check_all(&shape(2, 3, (12, 15), 4, (3, 2), (2, 1), (1, 0), (2, 3), 1));
}

#[test]
fn one_by_one() {
    assert_eq!(check_all(&shape(2, 19, (7, 9), 21, (1, 1), (1, 1), (0, 0), (1, 1), 1)), 3);
    check_all(&shape(1, 16, (14, 13), 24, (1, 1), (2, 2), (0, 0), (1, 1), 1));
    check_all(&shape(1, 8, (5, 6), 8, (1, 1), (1, 1), (1, 1), (1, 1), 2));
}

#[test]
fn non_square() {
    check_all(&shape(1, 4, (6, 17), 5, (1, 3), (1, 1), (0, 1), (1, 1), 1));
    check_all(&shape(2, 3, (15, 5), 5, (3, 1), (1, 1), (1, 0), (1, 1), 1));
    check_all(&shape(1, 7, (11, 14), 9, (2, 5), (1, 2), (0, 2), (1, 1), 1));
}

#[test]
fn tiny_outputs() {
    // oh = ow = 1, and a 1-row output with more threads than rows.
    check_all(&shape(1, 19, (3, 3), 17, (3, 3), (1, 1), (0, 0), (1, 1), 1));
    check_all(&shape(1, 5, (1, 6), 3, (1, 3), (1, 1), (0, 0), (1, 1), 1));
    check_all(&shape(2, 3, (4, 4), 4, (3, 3), (4, 4), (1, 1), (1, 1), 1));
}

#[test]
fn first_layer_7x7() {
    check_all(&shape(1, 3, (23, 17), 8, (7, 7), (2, 2), (3, 3), (1, 1), 1));
}

#[test]
fn winograd_edges() {
    // Output sizes not multiples of the tile, padding 0 and 2, batch > 1.
    for s in [
        shape(2, 17, (13, 10), 19, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        shape(1, 16, (9, 7), 16, (3, 3), (1, 1), (0, 0), (1, 1), 1),
        shape(3, 16, (5, 6), 20, (3, 3), (1, 1), (2, 2), (1, 1), 1),
        shape(1, 18, (6, 30), 16, (3, 3), (1, 1), (1, 0), (1, 1), 1),
        // Rows narrower than a tile: no tile lies wholly inside a row (plan_fuzz found
        // the input transform slicing past such a row).
        shape(1, 32, (12, 2), 32, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        shape(2, 16, (5, 1), 16, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        shape(1, 16, (7, 3), 16, (3, 3), (1, 1), (2, 2), (1, 1), 1),
    ] {
        assert_eq!(check_all(&s), 4);
    }
}

#[test]
fn many_tiles_and_blocks() {
    // Several im2col tiles per image, tiles crossing rows, several Winograd blocks.
    let s = shape(1, 128, (30, 29), 128, (3, 3), (1, 1), (1, 1), (1, 1), 1);
    assert!(gemm_tile(&s, ConvAlgo::Im2col) < s.oh * s.ow / 2);
    assert!(Wino::new::<6, 4>(&s).rows < s.oh.div_ceil(4));
    assert!(Wino::new::<4, 2>(&s).rows < s.oh.div_ceil(2));
    assert_eq!(check_all(&s), 4);
    check_all(&shape(1, 48, (20, 20), 40, (1, 1), (1, 1), (0, 0), (1, 1), 1));
}

#[test]
fn channel_split() {
    // Small images with many output channels split the channels over the threads.
    for s in [
        shape(2, 20, (6, 5), 100, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        shape(1, 24, (7, 7), 96, (1, 1), (1, 1), (0, 0), (1, 1), 1),
        shape(1, 16, (8, 8), 128, (3, 3), (2, 2), (1, 1), (1, 1), 1),
    ] {
        for algo in ConvAlgo::ALL.into_iter().filter(|a| a.supports(&s) && *a != ConvAlgo::Depthwise) {
            assert_eq!(split_shape(&s, algo, 2), (1, 2), "{} {s:?}", algo.name());
        }
        check_all(&s);
    }
    // A 1x1 expansion (four times the input's channels) splits by channels up to larger
    // planes: 28x28 at two threads (392 pixels a thread), 30x30 at three (300), where a
    // layer that does not expand splits by rows; 56x56 by rows.
    let expand = shape(1, 32, (28, 28), 128, (1, 1), (1, 1), (0, 0), (1, 1), 1);
    assert_eq!(split_shape(&expand, ConvAlgo::Gemm1x1, 2), (1, 2));
    let wide = shape(1, 24, (30, 30), 96, (1, 1), (1, 1), (0, 0), (1, 1), 1);
    assert_eq!(split_shape(&wide, ConvAlgo::Gemm1x1, 3), (1, 3));
    for s in [
        shape(1, 104, (28, 28), 104, (1, 1), (1, 1), (0, 0), (1, 1), 1),
        shape(1, 24, (56, 56), 144, (1, 1), (1, 1), (0, 0), (1, 1), 1),
    ] {
        assert_eq!(split_shape(&s, ConvAlgo::Gemm1x1, 2), (2, 1), "{s:?}");
    }
    check_all(&expand);
    check_all(&wide);
}

/// Worst error relative to the output's RMS, unscaled data in [-1, 1): Winograd F(4x4)
/// rounds about 5x more than im2col (measured ≈1e-5 vs ≈3e-6 at 64..512 input
/// channels), F(2x2) like im2col.
#[test]
fn error_levels() {
    for (cin, hw) in [(64, 28), (256, 14), (512, 7)] {
        let s = shape(1, cin, (hw, hw), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1);
        let x = data(s.n * s.cin * s.h * s.w, 1);
        let w = data(s.cout * s.cin * 9, 2);
        let want = reference(&s, &x, &w, &Epilogue::default());
        let rms = (want.iter().map(|v| v * v).sum::<f32>() / want.len() as f32).sqrt();
        for (algo, bound) in [(ConvAlgo::Im2col, 1e-5), (ConvAlgo::Winograd2, 1e-5), (ConvAlgo::Winograd4, 4e-5)] {
            let mut packed = vec![0.0; packed_weight_len(&s, algo)];
            pack_weight(&s, algo, &w, &mut packed);
            let mut out = vec![0.0; want.len()];
            let mut scratch = vec![0.0; scratch_len(&s, algo, 1)];
            conv2d(&s, algo, &packed, &Epilogue::default(), &x, &mut out, &mut scratch, 1);
            let max = out.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0, f32::max);
            println!("cin {cin} {}: rms {rms:.3} max err {max:.2e} relative {:.2e}", algo.name(), max / rms);
            assert!(max / rms < bound, "cin {cin} {}: relative error {:.2e}", algo.name(), max / rms);
        }
    }
}

#[test]
fn names_round_trip_and_choose_supports() {
    for a in ConvAlgo::ALL {
        assert_eq!(ConvAlgo::from_name(a.name()), Some(a));
    }
    assert_eq!(ConvAlgo::from_name("fft"), None);
    let resnet = [
        (shape(1, 3, (224, 224), 64, (7, 7), (2, 2), (3, 3), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 64, (56, 56), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd4),
        (shape(1, 64, (56, 56), 128, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 64, (56, 56), 128, (1, 1), (2, 2), (0, 0), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 64, (56, 56), 256, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        // 16 tiles of 4x4, 49 of 2x2; then 16 of 2x2 (fewer than WINOGRAD_MIN_TILES), F(2x2)
        // only with WINOGRAD2_WIDE channels in and out.
        (shape(1, 256, (14, 14), 256, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 512, (7, 7), 512, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 512, (8, 8), 512, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 512, (6, 6), 512, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Panels),
        // At most PANELS_MAX_PLANE pixels: the weight in panels (but 1x1 kernels).
        (shape(1, 256, (7, 7), 512, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Panels),
        (shape(1, 512, (7, 7), 256, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Panels),
        (shape(1, 256, (14, 14), 512, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Panels),
        (shape(1, 384, (8, 8), 384, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 64, (7, 8), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 1024, (14, 14), 2048, (1, 1), (2, 2), (0, 0), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 64, (7, 7), 64, (3, 3), (1, 1), (1, 1), (1, 1), 2), ConvAlgo::Im2col),
        // At the tile bound: 36 tiles of 4x4; 25 of 4x4 and 100 of 2x2; 36 of 2x2; 25 of 2x2.
        (shape(1, 64, (24, 24), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd4),
        (shape(1, 64, (20, 20), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 64, (12, 12), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 64, (10, 10), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 512, (28, 28), 512, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 512, (4, 4), 512, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Panels),
        (shape(1, 16, (56, 56), 16, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 32, (56, 56), 32, (3, 3), (1, 1), (1, 1), (1, 1), 32), ConvAlgo::Depthwise),
    ];
    for (s, want) in resnet {
        assert_eq!(choose(&s), want, "{s:?}");
        assert!(choose(&s).supports(&s));
    }
}

#[test]
#[should_panic(expected = "scratch")]
fn short_scratch_panics() {
    let s = shape(1, 4, (8, 8), 4, (3, 3), (1, 1), (1, 1), (1, 1), 1);
    let w = vec![0.0; packed_weight_len(&s, ConvAlgo::Im2col)];
    let x = vec![0.0; 4 * 64];
    let mut out = vec![0.0; 4 * 64];
    conv2d(&s, ConvAlgo::Im2col, &w, &Epilogue::default(), &x, &mut out, &mut [], 1);
}

#[test]
#[should_panic(expected = "cannot compute")]
fn unsupported_algo_panics() {
    let s = shape(1, 4, (8, 8), 4, (3, 3), (2, 2), (1, 1), (1, 1), 1);
    let mut packed = vec![0.0; packed_weight_len(&s, ConvAlgo::Winograd4)];
    pack_weight(&s, ConvAlgo::Winograd4, &vec![0.0; 4 * 4 * 9], &mut packed);
}

/// The conv plus a separate LoRA branch, naively in f64: `acc = conv(x, W) +
/// conv1x1(conv(x, A), B)`, then the epilogue (the branch is added before its scale).
fn reference_lora(s: &Conv2dShape, x: &[f32], w: &[f32], a: &[f32], b: &[f32], rank: usize, ep: &Epilogue) -> Vec<f32> {
    let raw = |s: &Conv2dShape, w: &[f32]| -> Vec<f64> {
        let mut out = vec![0.0f64; s.n * s.cout * s.oh * s.ow];
        for n in 0..s.n {
            for co in 0..s.cout {
                for oy in 0..s.oh {
                    for ox in 0..s.ow {
                        let mut acc = 0.0f64;
                        for ci in 0..s.cin {
                            for ky in 0..s.kh {
                                for kx in 0..s.kw {
                                    let iy = (oy * s.stride_h + ky * s.dil_h) as isize - s.pad_h as isize;
                                    let ix = (ox * s.stride_w + kx * s.dil_w) as isize - s.pad_w as isize;
                                    if iy < 0 || ix < 0 || iy >= s.h as isize || ix >= s.w as isize {
                                        continue;
                                    }
                                    let xv = x[((n * s.cin + ci) * s.h + iy as usize) * s.w + ix as usize];
                                    let wv = w[((co * s.cin + ci) * s.kh + ky) * s.kw + kx];
                                    acc += f64::from(xv) * f64::from(wv);
                                }
                            }
                        }
                        out[((n * s.cout + co) * s.oh + oy) * s.ow + ox] = acc;
                    }
                }
            }
        }
        out
    };
    let base = raw(s, w);
    let t = raw(&lora_a_shape(s, rank), a);
    let plane = s.oh * s.ow;
    let mut out = vec![0.0f32; base.len()];
    for n in 0..s.n {
        for co in 0..s.cout {
            for p in 0..plane {
                let branch: f64 = (0..rank).map(|r| f64::from(b[co * rank + r]) * t[(n * rank + r) * plane + p]).sum();
                let acc = base[(n * s.cout + co) * plane + p] + branch;
                let mut y =
                    acc * ep.scale.map_or(1.0, |v| f64::from(v[co])) + ep.shift.map_or(0.0, |v| f64::from(v[co]));
                if let Some(act) = ep.act {
                    y = act.reference(y);
                }
                out[(n * s.cout + co) * plane + p] = y as f32;
            }
        }
    }
    out
}

/// Every algorithm that supports `s` (but depthwise) with a fused LoRA branch of `rank`,
/// each thread count and epilogue kind, against [`reference_lora`]. Returns how many.
fn check_lora(s: &Conv2dShape, rank: usize) -> usize {
    let x = data(s.n * s.cin * s.h * s.w, 11);
    let fan_in = s.cin * s.kh * s.kw;
    let at_scale = |v: Vec<f32>| -> Vec<f32> { v.iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect() };
    let w = at_scale(data(fan_in * s.cout, 12));
    let a = at_scale(data(fan_in * rank, 13));
    // A trained B is small but not negligible: here as large as W's entries.
    let b: Vec<f32> = data(s.cout * rank, 14).iter().map(|v| 0.7 * v).collect();
    let scale: Vec<f32> = data(s.cout, 15).iter().map(|v| 0.5 + v).collect();
    let shift = data(s.cout, 16);
    let eps = [
        Epilogue::default(),
        Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) },
        Epilogue { scale: Some(&scale), shift: None, act: None },
        Epilogue { scale: None, shift: Some(&shift), act: Some(Activation::Relu6) },
    ];
    let algos: Vec<ConvAlgo> =
        ConvAlgo::ALL.into_iter().filter(|a| a.supports(s) && *a != ConvAlgo::Depthwise).collect();
    for &algo in &algos {
        let mut packed = vec![0.0; packed_weight_len(s, algo)];
        pack_weight(s, algo, &w, &mut packed);
        let mut packed_a = vec![0.0; lora_a_len(s, algo, rank)];
        pack_lora_a(s, algo, rank, &a, &mut packed_a);
        let lora = Lora { a: &packed_a, b: &b, rank };
        let fields = Some((rank, packed_a.len(), b.len()));
        let x_len = x.len();
        for ep in &eps {
            let want = reference_lora(s, &x, &w, &a, &b, rank, ep);
            let vectors = [ep.scale.map(<[f32]>::len), ep.shift.map(<[f32]>::len)];
            assert_eq!(super::check(s, algo, packed.len(), x_len, want.len(), vectors, fields), Ok(()));
            for threads in [1, 2, 3] {
                let mut out = vec![f32::NAN; want.len()];
                let mut scratch = vec![f32::NAN; lora_scratch_len(s, algo, rank, threads)];
                conv2d_lora(s, algo, &packed, Some(&lora), ep, &x, &mut out, &mut scratch, threads);
                assert_close(&out, &want, 1e-4);
            }
        }
    }
    algos.len()
}

#[test]
fn lora_every_algorithm() {
    // 3x3 stride 1 (im2col, panels and both Winograds), odd sizes, batch > 1.
    assert_eq!(check_lora(&shape(2, 17, (13, 10), 19, (3, 3), (1, 1), (1, 1), (1, 1), 1), 4), 4);
    // Several Winograd blocks and im2col tiles, rank 1 and 8.
    assert_eq!(check_lora(&shape(1, 64, (30, 29), 40, (3, 3), (1, 1), (1, 1), (1, 1), 1), 8), 4);
    assert_eq!(check_lora(&shape(1, 16, (9, 7), 16, (3, 3), (1, 1), (0, 0), (1, 1), 1), 1), 4);
    // Winograd's branch takes input channels 8 at a time: fewer than 8 (only the
    // remainder), a multiple of 8 (none), 8 and a remainder; every other rank 2..7.
    assert_eq!(check_lora(&shape(1, 5, (11, 12), 7, (3, 3), (1, 1), (1, 1), (1, 1), 1), 3), 4);
    assert_eq!(check_lora(&shape(2, 24, (9, 14), 33, (3, 3), (1, 1), (1, 1), (1, 1), 1), 7), 4);
    for rank in [2, 5, 6] {
        assert_eq!(check_lora(&shape(1, 11, (8, 13), 9, (3, 3), (1, 1), (1, 1), (1, 1), 1), rank), 4);
    }
    // 1x1 (GEMM, im2col and panels), stride 2 1x1 (im2col and panels).
    assert_eq!(check_lora(&shape(2, 19, (7, 9), 21, (1, 1), (1, 1), (0, 0), (1, 1), 1), 4), 3);
    assert_eq!(check_lora(&shape(1, 16, (14, 13), 24, (1, 1), (2, 2), (0, 0), (1, 1), 1), 3), 2);
    // Stride, padding, dilation, non-square kernels: im2col and panels.
    assert_eq!(check_lora(&shape(3, 6, (9, 9), 5, (3, 3), (2, 1), (0, 2), (1, 1), 1), 2), 2);
    assert_eq!(check_lora(&shape(2, 3, (12, 15), 4, (3, 2), (2, 1), (1, 0), (2, 3), 1), 4), 2);
}

#[test]
fn lora_channel_split() {
    // Two or three threads split the output channels and share one unfolded tile or one
    // input transform; each part computes the branch's projection from all of it.
    for s in [
        shape(2, 20, (6, 5), 100, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        shape(1, 24, (7, 7), 96, (1, 1), (1, 1), (0, 0), (1, 1), 1),
        shape(1, 16, (8, 8), 128, (3, 3), (2, 2), (1, 1), (1, 1), 1),
        shape(1, 40, (6, 6), 100, (3, 3), (1, 1), (1, 1), (1, 1), 1),
    ] {
        assert_eq!(split_shape(&s, ConvAlgo::Im2col, 2), (1, 2));
        check_lora(&s, 4);
    }
    let s = shape(1, 40, (6, 6), 100, (3, 3), (1, 1), (1, 1), (1, 1), 1);
    for algo in [ConvAlgo::Winograd2, ConvAlgo::Winograd4] {
        assert_eq!(split_shape(&s, algo, 3), (1, 3), "{algo:?}");
    }
}

#[test]
fn lora_check_refuses_bad_branches() {
    let s = shape(1, 8, (6, 6), 8, (3, 3), (1, 1), (1, 1), (1, 1), 1);
    let ok = |algo: ConvAlgo, rank: usize| Some((rank, packed_weight_len(&lora_a_shape(&s, rank), algo), 8 * rank));
    let run =
        |algo: ConvAlgo, lora| super::check(&s, algo, packed_weight_len(&s, algo), 8 * 36, 8 * 36, [None, None], lora);
    assert_eq!(run(ConvAlgo::Im2col, ok(ConvAlgo::Im2col, 4)), Ok(()));
    assert_eq!(run(ConvAlgo::Winograd4, ok(ConvAlgo::Winograd4, 4)), Ok(()));
    // A packed for another algorithm, a short B, rank 0, a rank over the bound.
    let e = run(ConvAlgo::Winograd4, ok(ConvAlgo::Im2col, 4)).expect_err("A packed for im2col");
    assert!(e.contains("LoRA A has 288 values"), "{e}");
    assert!(run(ConvAlgo::Im2col, Some((4, 288, 31))).expect_err("short B").contains("B 31"));
    assert!(run(ConvAlgo::Im2col, Some((0, 0, 0))).expect_err("rank 0").contains("rank 0"));
    let big = MAX_LORA_RANK + 1;
    assert!(run(ConvAlgo::Im2col, Some((big, 72 * big, 8 * big))).expect_err("rank").contains("must be 1 to"));
    // Groups and depthwise have no fused branch.
    let g = shape(1, 8, (6, 6), 8, (3, 3), (1, 1), (1, 1), (1, 1), 8);
    let e = super::check(&g, ConvAlgo::Depthwise, 72, 288, 288, [None, None], Some((1, 72, 8))).expect_err("depthwise");
    assert!(e.contains("one group"), "{e}");
}

#[test]
fn winograd_packing_is_the_transform_of_each_kernel() {
    // `pack_winograd` works on blocks of 32 kernels in lanes; 4 x 37 kernels leave a
    // partial block per output channel. Each packed value must be exactly `G g Gᵀ` of its
    // own kernel, in f64 with the sums in order (what the packing promises bit for bit).
    let s = shape(1, 37, (6, 6), 4, (3, 3), (1, 1), (1, 1), (1, 1), 1);
    let w = data(4 * 37 * 9, 31);
    for (algo, g) in [(ConvAlgo::Winograd2, &F2_G[..]), (ConvAlgo::Winograd4, &F4_G[..])] {
        let a = g.len();
        let mut packed = vec![f32::NAN; packed_weight_len(&s, algo)];
        pack_weight(&s, algo, &w, &mut packed);
        for f in 0..4 * 37 {
            let k = &w[f * 9..][..9];
            for i in 0..a {
                for j in 0..a {
                    // t = G g (row i, column r), then u = t Gᵀ.
                    let t = |r: usize| {
                        g[i][0] * f64::from(k[r]) + g[i][1] * f64::from(k[3 + r]) + g[i][2] * f64::from(k[6 + r])
                    };
                    let u = (t(0) * g[j][0] + t(1) * g[j][1] + t(2) * g[j][2]) as f32;
                    assert_eq!(
                        packed[(i * a + j) * 4 * 37 + f].to_bits(),
                        u.to_bits(),
                        "kernel {f}, ({i}, {j}), {algo:?}"
                    );
                }
            }
        }
    }
}

/// Im2col layers with at most four input channels run the direct conv (`direct.rs`):
/// MobileNet's and ResNet's stems (3x3 and 7x7 at stride 2, an odd width, two images,
/// output channels past a group of eight), 5x5 at stride 1, no padding, rows narrower than
/// a vector, one input channel.
#[test]
fn few_input_channels() {
    for s in [
        shape(2, 3, (20, 37), 10, (3, 3), (2, 2), (1, 1), (1, 1), 1),
        shape(1, 3, (23, 23), 16, (7, 7), (2, 2), (3, 3), (1, 1), 1),
        shape(1, 1, (9, 40), 3, (5, 5), (1, 1), (2, 2), (1, 1), 1),
        shape(1, 4, (6, 6), 9, (3, 3), (1, 1), (0, 0), (1, 1), 1),
        shape(1, 2, (7, 9), 8, (3, 3), (2, 2), (1, 1), (1, 1), 1),
        shape(1, 3, (12, 18), 5, (5, 5), (2, 2), (1, 1), (1, 1), 1),
    ] {
        assert!(direct::applies(&s), "{s:?}");
        check(&s, ConvAlgo::Im2col);
    }
    // Five input channels in one group, dilation, sixteen a group: im2col itself.
    assert!(!direct::applies(&shape(1, 5, (8, 8), 4, (3, 3), (1, 1), (1, 1), (1, 1), 1)));
    assert!(!direct::applies(&shape(1, 3, (8, 8), 4, (3, 3), (1, 1), (2, 2), (2, 2), 1)));
    assert!(!direct::applies(&shape(1, 32, (8, 8), 32, (3, 3), (1, 1), (1, 1), (1, 1), 2)));
}

/// Grouped convs of narrow groups run the direct conv too: RegNet's (eight channels a
/// group, stride 1 and 2), groups of six in and twelve out (a group's channels in a chunk
/// of eight and one of four), two images, a 5x5 kernel.
#[test]
fn narrow_groups() {
    for s in [
        shape(1, 48, (14, 14), 48, (3, 3), (1, 1), (1, 1), (1, 1), 6),
        shape(2, 24, (15, 13), 24, (3, 3), (2, 2), (1, 1), (1, 1), 3),
        shape(1, 18, (9, 20), 36, (3, 3), (1, 1), (1, 1), (1, 1), 3),
        shape(1, 16, (11, 11), 16, (5, 5), (2, 2), (2, 2), (1, 1), 4),
    ] {
        assert!(direct::applies(&s), "{s:?}");
        check(&s, ConvAlgo::Im2col);
    }
}

/// `act(y + res)` element by element, `y` the conv's output before its activation.
fn with_residual(y: &[f32], res: &[f32], act: Option<Activation>) -> Vec<f32> {
    y.iter()
        .zip(res)
        .map(|(&y, &r)| {
            let v = f64::from(y) + f64::from(r);
            act.map_or(v, |a| a.reference(v)) as f32
        })
        .collect()
}

/// [`conv2d_fused`] with a residual input on `s` by `algo`, before each activation of
/// `acts`, at 1 to 3 threads, against the reference plus the sum.
fn check_residual(s: &Conv2dShape, algo: ConvAlgo, acts: &[Option<Activation>]) {
    let x = data(s.n * s.cin * s.h * s.w, 21);
    let fan_in = s.cin / s.groups * s.kh * s.kw;
    let w: Vec<f32> = data(fan_in * s.cout, 22).iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect();
    let (scale, shift) = (data(s.cout, 23), data(s.cout, 24));
    let res = data(s.n * s.cout * s.oh * s.ow, 25);
    let mut packed = vec![0.0; packed_weight_len(s, algo)];
    pack_weight(s, algo, &w, &mut packed);
    for &act in acts {
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act };
        let y = reference(s, &x, &w, &Epilogue { act: None, ..ep });
        let want = with_residual(&y, &res, act);
        for threads in [1, 2, 3] {
            let mut out = vec![f32::NAN; want.len()];
            let mut scratch = vec![f32::NAN; scratch_len(s, algo, threads)];
            conv2d_fused(s, algo, &packed, None, None, &ep, &x, Some(&res), &mut out, &mut scratch, threads);
            assert_close(&out, &want, 1e-4);
        }
    }
}

/// 1x1 layers of small planes take the register path (`pointwise.rs`): planes that end
/// in whole tiles, in narrower tiles, in a few pixels (dot products) or in part of a
/// vector (zero-padded); channel counts that leave micro-tile tails; input channels that
/// leave vector tails (the dot products) and blocks of its epilogue; batches split
/// across images and by channels;
/// with and without a residual, before each kind of activation.
#[test]
fn pointwise_tails_batches_and_residuals() {
    let cases = [
        (1, 5, (1, 1), 13),
        (1, 37, (2, 2), 6),
        (3, 16, (7, 7), 13),
        (1, 40, (5, 5), 9),
        (2, 24, (14, 14), 17),
        (1, 19, (16, 16), 8),
        (2, 33, (9, 10), 1),
        (1, 70, (3, 3), 64),
        // Dot products over more channels than a block of the epilogue, in groups
        // that leave tails: a squeeze-and-excitation conv's 1x1 plane, a 2x2 one.
        (2, 40, (1, 1), 150),
        (1, 37, (2, 2), 70),
    ];
    for (n, cin, hw, cout) in cases {
        let s = shape(n, cin, hw, cout, (1, 1), (1, 1), (0, 0), (1, 1), 1);
        assert!(pointwise::applies(&s, None), "{s:?} takes the register path");
        check(&s, ConvAlgo::Gemm1x1);
        check_residual(&s, ConvAlgo::Gemm1x1, &[None, Some(Activation::Relu6), Some(Activation::Silu)]);
    }
    // A 7x7 plane takes the tiles whatever its weight (416 x 400 floats streamed twice
    // per image, past the bound larger planes keep); a 14x14 expansion of that weight
    // does not.
    let heavy = shape(1, 416, (7, 7), 400, (1, 1), (1, 1), (0, 0), (1, 1), 1);
    assert!(pointwise::applies(&heavy, None), "{heavy:?} takes the register path");
    check(&heavy, ConvAlgo::Gemm1x1);
    check_residual(&heavy, ConvAlgo::Gemm1x1, &[Some(Activation::Relu6)]);
    assert!(!pointwise::applies(&shape(1, 400, (14, 14), 416, (1, 1), (1, 1), (0, 0), (1, 1), 1), None));
    // But a reduction (no more output channels than input ones) of that plane does,
    // whatever its weight (200 x 330 floats streamed five times per image).
    let reduction = shape(1, 330, (14, 14), 200, (1, 1), (1, 1), (0, 0), (1, 1), 1);
    assert!(pointwise::applies(&reduction, None), "{reduction:?} takes the register path");
    check(&reduction, ConvAlgo::Gemm1x1);
    check_residual(&reduction, ConvAlgo::Gemm1x1, &[Some(Activation::Relu)]);
    // Past the plane bound, a SiLU or sigmoid layer of a small weight takes the tiles too
    // (the activation computed on the sums in registers), a ReLU one the GEMM (unless an
    // expansion: below).
    let s = shape(2, 8, (21, 23), 12, (1, 1), (1, 1), (0, 0), (1, 1), 1);
    assert!(pointwise::applies(&s, Some(Activation::Silu)) && !pointwise::applies(&s, Some(Activation::Relu)));
    check_residual(&s, ConvAlgo::Gemm1x1, &[Some(Activation::Silu), Some(Activation::Sigmoid)]);
    assert_eq!(split_shape(&shape(1, 70, (3, 3), 64, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1, 2), (1, 2));
    // Im2col layers of small planes run the same tiles over their unfolded rows: strided
    // 3x3 and 1x1 (ResNet's downsampling), padding, dilation, a 5x5, batches.
    let unfolded = [
        shape(1, 12, (14, 14), 10, (3, 3), (2, 2), (1, 1), (1, 1), 1),
        shape(2, 9, (13, 13), 7, (1, 1), (2, 2), (0, 0), (1, 1), 1),
        shape(1, 6, (8, 7), 13, (3, 3), (1, 1), (2, 2), (2, 2), 1),
        shape(3, 5, (7, 7), 6, (5, 5), (1, 1), (2, 2), (1, 1), 1),
        shape(1, 40, (4, 4), 64, (3, 3), (1, 1), (1, 1), (1, 1), 1),
        // A strided 1x1 to a 7x7 plane past the weight bound (ResNet-50's last
        // downsampling, narrower).
        shape(1, 300, (14, 14), 600, (1, 1), (2, 2), (0, 0), (1, 1), 1),
    ];
    for s in &unfolded {
        assert!(pointwise::applies_unfolded(s) && !direct::applies(s), "{s:?} takes the register path");
        check(s, ConvAlgo::Im2col);
        check_residual(s, ConvAlgo::Im2col, &[None, Some(Activation::Relu6), Some(Activation::Silu)]);
    }
}

/// Expansions of few input channels take the tiles on planes of any size; on planes of
/// 56x56 and more (112x112 with an activation computed in registers) their whole tiles
/// run by chunks of pixels, six channels at a time over a chunk: planes that take two
/// chunks and leave a pair of vectors or a padded one after them, output channels that
/// leave a last block of fewer than six, an image split between threads, with and without
/// a residual, before each kind of activation. A deeper expansion keeps the GEMM.
#[test]
fn pointwise_expansions_of_large_planes() {
    // (batch, input channels, plane, output channels): 24 x 57x58 is two chunks and 42
    // pixels (a pair of vectors and 10 padded); 8 x 113x112 two chunks and a pair.
    let cases = [(1, 24, (57, 58), 50), (2, 8, (113, 112), 17)];
    for (n, cin, hw, cout) in cases {
        let s = shape(n, cin, hw, cout, (1, 1), (1, 1), (0, 0), (1, 1), 1);
        assert!(pointwise::applies(&s, None) && pointwise::applies(&s, Some(Activation::Relu6)), "{s:?}");
        check(&s, ConvAlgo::Gemm1x1);
        check_residual(&s, ConvAlgo::Gemm1x1, &[Some(Activation::Relu6), Some(Activation::Hardswish)]);
    }
    assert!(!pointwise::applies(&shape(1, 128, (28, 28), 512, (1, 1), (1, 1), (0, 0), (1, 1), 1), None));
}

/// The register path gives the same bits at every thread count: a split by rows cuts
/// the planes elsewhere than one thread's tiles do, and only the plane's last pixels sum
/// in the dot products' order; the epilogue rounds as `finish` does on the tails.
#[test]
fn pointwise_bits_do_not_depend_on_the_split() {
    let cases = [
        (shape(3, 24, (7, 7), 16, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        (shape(5, 20, (14, 14), 8, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        (shape(3, 12, (14, 14), 16, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
    ];
    // And Im2col layers of small planes (strided 1x1 and 3x3, a stride-1 3x3), batches
    // whose split falls inside an image.
    let mut cases = cases.to_vec();
    for (n, hw, cout) in [(1, 7, 16), (3, 8, 40), (6, 13, 96), (5, 3, 8)] {
        for (k, stride) in [(1, 2), (3, 2), (3, 1)] {
            let s = shape(n, 24, (hw, hw + 1), cout, (k, k), (stride, stride), (k / 2, k / 2), (1, 1), 1);
            if pointwise::applies_unfolded(&s) && split_shape(&s, ConvAlgo::Im2col, 2).1 == 1 {
                cases.push((s, ConvAlgo::Im2col));
            }
        }
    }
    assert!(cases.len() > 8, "{} cases", cases.len());
    for (s, algo) in &cases {
        let x = data(s.n * s.cin * s.h * s.w, 41);
        let w = data(s.cout * s.k(), 42);
        let mut packed = vec![0.0; packed_weight_len(s, *algo)];
        pack_weight(s, *algo, &w, &mut packed);
        let (scale, shift, res) = (data(s.cout, 43), data(s.cout, 44), data(s.n * s.cout * s.oh * s.ow, 45));
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) };
        let runs: Vec<Vec<f32>> = [1, 2, 3]
            .iter()
            .map(|&threads| {
                let mut out = vec![f32::NAN; s.n * s.cout * s.oh * s.ow];
                let mut scratch = vec![f32::NAN; scratch_len(s, *algo, threads)];
                conv2d_fused(s, *algo, &packed, None, None, &ep, &x, Some(&res), &mut out, &mut scratch, threads);
                out
            })
            .collect();
        for run in &runs[1..] {
            assert!(run.iter().zip(&runs[0]).all(|(a, b)| a.to_bits() == b.to_bits()), "{s:?}: bits differ");
        }
    }
}

/// A residual input on every path: added as the rows are written (the GEMM paths, both
/// Winograds, a split by channels, weight panels, with a LoRA branch) and in a pass after
/// (depthwise, the direct conv), before a ReLU, another activation or none, at 1 to 3 threads, against the
/// references plus the sum.
#[test]
fn residual_on_every_path() {
    let cases = [
        (shape(2, 8, (9, 7), 16, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        (shape(1, 12, (11, 9), 16, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(2, 6, (13, 12), 8, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(2, 6, (13, 12), 8, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd4),
        (shape(2, 8, (10, 9), 8, (3, 3), (1, 1), (1, 1), (1, 1), 8), ConvAlgo::Depthwise),
        // A stem: the direct conv.
        (shape(2, 3, (12, 10), 8, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        // A small image and many channels: split by output channels at 2 and 3 threads
        // (Winograd's parts then share one input transform).
        (shape(1, 16, (4, 4), 96, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(2, 16, (9, 8), 96, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(2, 16, (9, 8), 96, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd4),
        // Weight panels: two images, 40 channels (a panel and a part of one) shared by 2
        // and 3 threads.
        (shape(2, 16, (9, 8), 40, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Panels),
        (shape(1, 16, (7, 7), 96, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Panels),
    ];
    assert!(direct::applies(&cases[5].0), "the stem case takes the direct conv");
    for (s, algo) in &cases[6..9] {
        assert_eq!(split_shape(s, *algo, 2), (1, 2), "{} splits by channels", algo.name());
        assert_eq!(split_shape(s, *algo, 3), (1, 3), "{} splits by channels", algo.name());
    }
    for (s, algo) in &cases {
        check_residual(s, *algo, &[None, Some(Activation::Relu), Some(Activation::Hardswish)]);
    }
    // With a LoRA branch, whose sum comes before the scale and the residual after it.
    for algo in [ConvAlgo::Gemm1x1, ConvAlgo::Winograd4, ConvAlgo::Panels] {
        let k = if algo == ConvAlgo::Gemm1x1 { 1 } else { 3 };
        let s = shape(2, 9, (10, 11), 12, (k, k), (1, 1), (k / 2, k / 2), (1, 1), 1);
        let (rank, fan_in) = (3, 9 * k * k);
        let at_scale = |v: Vec<f32>| -> Vec<f32> { v.iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect() };
        let (x, w, a) =
            (data(s.n * s.cin * s.h * s.w, 31), at_scale(data(fan_in * 12, 32)), at_scale(data(fan_in * rank, 33)));
        let b = data(12 * rank, 34);
        let (scale, shift, res) = (data(12, 35), data(12, 36), data(s.n * 12 * s.oh * s.ow, 37));
        let mut packed = vec![0.0; packed_weight_len(&s, algo)];
        pack_weight(&s, algo, &w, &mut packed);
        let mut packed_a = vec![0.0; lora_a_len(&s, algo, rank)];
        pack_lora_a(&s, algo, rank, &a, &mut packed_a);
        let lora = Lora { a: &packed_a, b: &b, rank };
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) };
        let y = reference_lora(&s, &x, &w, &a, &b, rank, &Epilogue { act: None, ..ep });
        let want = with_residual(&y, &res, ep.act);
        for threads in [1, 2] {
            let mut out = vec![f32::NAN; want.len()];
            let mut scratch = vec![f32::NAN; lora_scratch_len(&s, algo, rank, threads)];
            conv2d_fused(&s, algo, &packed, Some(&lora), None, &ep, &x, Some(&res), &mut out, &mut scratch, threads);
            assert_close(&out, &want, 1e-4);
        }
    }
}

/// The register paths' store keeps a NaN sum NaN under every clamp (ReLU, ReLU6, a clamp),
/// as the element-wise activations do, and clamps the other lanes.
#[test]
fn a_clamped_store_keeps_nan() {
    use crate::kernels::testutil::backends;
    struct Store(Option<(f32, f32)>, Vec<f32>);
    impl pulp::WithSimd for Store {
        type Output = Vec<f32>;
        fn with_simd<S: pulp::Simd>(self, simd: S) -> Vec<f32> {
            let lanes = size_of::<S::f32s>() / size_of::<f32>();
            let input: Vec<f32> = (0..lanes).map(|i| self.1[i % self.1.len()]).collect();
            let acc = S::as_simd_f32s(&input).0[0];
            let mut out = vec![0.0; lanes];
            store_vector(simd, acc, simd.splat_f32s(1.0), simd.splat_f32s(0.0), self.0, &mut out);
            out
        }
    }
    let values = vec![f32::NAN, -3.0, 0.5, 9.0];
    for clamp in [(0.0, f32::INFINITY), (0.0, 6.0), (-1.0, 1.0)] {
        for b in backends() {
            let got = b.run(Store(Some(clamp), values.clone()));
            for (g, v) in got.iter().zip(values.iter().cycle()) {
                if v.is_nan() {
                    assert!(g.is_nan(), "{b:?} {clamp:?}: NaN became {g}");
                } else {
                    assert_eq!(*g, v.max(clamp.0).min(clamp.1), "{b:?} {clamp:?}");
                }
            }
        }
    }
}

/// A channel scale on the input (`conv2d_scaled`, a squeeze-and-excitation's multiply
/// fused): against the reference conv of the input multiplied first, per image and
/// channel, for each algorithm that keeps PyTorch's weight layout, with batches (a scale
/// per image), groups, a residual and activations, at 1 to 3 threads; its scratch is
/// what `scaled_scratch_len` says.
#[test]
fn channel_scale_matches_scaling_the_input() {
    let cases = [
        (shape(2, 24, (7, 7), 40, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        (shape(1, 16, (28, 28), 24, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        (shape(2, 12, (9, 8), 10, (1, 1), (1, 1), (0, 0), (1, 1), 2), ConvAlgo::Gemm1x1),
        (shape(2, 8, (9, 10), 6, (3, 3), (2, 2), (1, 1), (1, 1), 2), ConvAlgo::Im2col),
        (shape(2, 6, (8, 8), 6, (3, 3), (1, 1), (1, 1), (1, 1), 6), ConvAlgo::Depthwise),
    ];
    for (s, algo) in &cases {
        let x = data(s.n * s.cin * s.h * s.w, 31);
        let fan_in = s.cin / s.groups * s.kh * s.kw;
        let w: Vec<f32> = data(fan_in * s.cout, 32).iter().map(|v| v * (3.0 / fan_in as f32).sqrt()).collect();
        let sc: Vec<f32> = data(s.n * s.cin, 33).iter().map(|v| 0.5 + v).collect();
        let (scale, shift) = (data(s.cout, 34), data(s.cout, 35));
        let res = data(s.n * s.cout * s.oh * s.ow, 36);
        let plane = s.h * s.w;
        let xs: Vec<f32> = x.iter().enumerate().map(|(i, &v)| v * sc[i / plane]).collect();
        let mut packed = vec![0.0; packed_weight_len(s, *algo)];
        pack_weight(s, *algo, &w, &mut packed);
        for act in [None, Some(Activation::Relu), Some(Activation::Hardswish)] {
            let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act };
            let plain = reference(s, &xs, &w, &ep);
            let y = reference(s, &xs, &w, &Epilogue { act: None, ..ep });
            let with_res = with_residual(&y, &res, act);
            for (r, want) in [(None, &plain), (Some(&res[..]), &with_res)] {
                for threads in [1, 2, 3] {
                    let mut out = vec![f32::NAN; want.len()];
                    let len = scaled_scratch_len(s, *algo, 0, threads).expect("scratch length");
                    let mut scratch = vec![f32::NAN; len];
                    conv2d_scaled(s, *algo, &packed, None, &ep, &x, &sc, r, &mut out, &mut scratch, threads);
                    assert_close(&out, want, 1e-4);
                }
            }
        }
    }
}

/// A NaN in the input reaches, through a fused ReLU (with and without a residual, and
/// with an adapter), every output whose receptive field holds it, as PyTorch's ReLU keeps
/// NaN: on every algorithm's epilogue (GEMM rows, the 1x1 and im2col tiles, Winograd, the
/// depthwise registers and loops, the direct conv, weight panels), at 1 and 2 threads.
#[test]
fn a_nan_input_stays_nan_through_a_fused_relu() {
    let cases = [
        (shape(1, 8, (9, 9), 16, (1, 1), (1, 1), (0, 0), (1, 1), 1), ConvAlgo::Gemm1x1),
        (shape(1, 8, (9, 9), 16, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 3, (12, 12), 16, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Im2col),
        (shape(1, 8, (10, 10), 8, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd2),
        (shape(1, 8, (10, 10), 8, (3, 3), (1, 1), (1, 1), (1, 1), 1), ConvAlgo::Winograd4),
        (shape(1, 4, (10, 10), 4, (3, 3), (1, 1), (1, 1), (1, 1), 4), ConvAlgo::Depthwise),
        (shape(1, 4, (10, 10), 4, (3, 3), (1, 1), (2, 2), (2, 2), 4), ConvAlgo::Depthwise),
        (shape(1, 8, (9, 9), 40, (3, 3), (2, 2), (1, 1), (1, 1), 1), ConvAlgo::Panels),
    ];
    for (s, algo) in &cases {
        assert!(algo.supports(s), "{} on {s:?}", algo.name());
        let (cy, cx) = (s.h / 2, s.w / 2);
        let mut x = data(s.n * s.cin * s.h * s.w, 41);
        x[cy * s.w + cx] = f32::NAN;
        let w = data(s.cout * s.cin / s.groups * s.kh * s.kw, 42);
        let mut packed = vec![0.0; packed_weight_len(s, *algo)];
        pack_weight(s, *algo, &w, &mut packed);
        let (scale, shift) = (data(s.cout, 43), data(s.cout, 44));
        let ep = Epilogue { scale: Some(&scale), shift: Some(&shift), act: Some(Activation::Relu) };
        let res = data(s.n * s.cout * s.oh * s.ow, 45);
        let mid = 2;
        let (down, up) = (data(mid * s.cout, 46), data(s.cout * mid, 47));
        let (bd, bu) = (data(mid, 48), data(s.cout, 49));
        let ad = Adapter { down: &down, down_bias: &bd, up: &up, up_bias: &bu, mid, act: Activation::Relu };
        let reaches = |o: usize, oy: usize, ox: usize| {
            // Input channel 0 feeds group 0's outputs; the adapter mixes every channel.
            let hit = |o: usize, step: usize, k: usize, d: usize, p: usize, c: usize| {
                (0..k).any(|t| (o * step + t * d).checked_sub(p) == Some(c))
            };
            hit(oy, s.stride_h, s.kh, s.dil_h, s.pad_h, cy)
                && hit(ox, s.stride_w, s.kw, s.dil_w, s.pad_w, cx)
                && o < s.cout / s.groups
        };
        for (res, adapter) in [(None, None), (Some(&res[..]), None), (None, Some(&ad))] {
            for threads in [1, 2] {
                let need = adapter_scratch_len(s, *algo, 0, mid, threads).expect("a size");
                let mut scratch = vec![0.0; need];
                let mut out = vec![0.0; s.n * s.cout * s.oh * s.ow];
                conv2d_fused(s, *algo, &packed, None, adapter, &ep, &x, res, &mut out, &mut scratch, threads);
                for (i, v) in out.iter().enumerate() {
                    let (o, p) = (i / (s.oh * s.ow), i % (s.oh * s.ow));
                    let reached = reaches(o, p / s.ow, p % s.ow) || adapter.is_some() && reaches(0, p / s.ow, p % s.ow);
                    if reached {
                        assert!(
                            v.is_nan(),
                            "{} {s:?} res {} adapter {}: out[{i}] = {v}",
                            algo.name(),
                            res.is_some(),
                            adapter.is_some()
                        );
                    }
                }
            }
        }
    }
}

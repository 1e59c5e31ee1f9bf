//! Shape inference of the windowed ops against PyTorch: random conv2d, max/avg pool and
//! upsample configurations with the output size PyTorch computed, or `error` where PyTorch
//! refused them (tests/fixtures/make_fixtures.py writes the file).

mod common;

use readi_compiler::ir::{Conv2d, Dim, Op, Pool2d, PoolKind, Pure, TensorType, UpsampleMode, Window2};
use readi_compiler::ops::ConvOp;
use readi_grammar::ast::DType;
use readi_plan::ops::Upsample;

fn nchw(c: i64, h: i64, w: i64) -> TensorType {
    TensorType::new(DType::F32, vec![Dim::known(1), Dim::known(c), Dim::known(h), Dim::known(w)])
}

#[test]
fn window_shapes_match_pytorch() {
    let path = common::root().join("tests/fixtures/torch/window_shapes.txt");
    let text = std::fs::read_to_string(&path).expect("window_shapes.txt");
    let mut checked = 0;
    for line in text.lines() {
        let (case, expected) = line.split_once(" -> ").expect("case -> result");
        let f: Vec<&str> = case.split_whitespace().collect();
        let n = |i: usize| f[i].parse::<i64>().expect("int field");
        let (op, input) = match f[0] {
            "conv" => (
                Op::Conv2d(ConvOp::new(
                    Conv2d {
                        in_channels: n(1),
                        out_channels: n(4),
                        window: Window2 {
                            kernel: [n(5), n(6)],
                            stride: [n(7), n(8)],
                            padding: [n(9), n(10)],
                            dilation: [n(11), n(12)],
                        },
                        groups: n(13),
                    },
                    true,
                )),
                nchw(n(1), n(2), n(3)),
            ),
            kind @ ("maxpool" | "avgpool") => (
                Op::Pure(Pure::Pool(Pool2d {
                    kind: if kind == "maxpool" { PoolKind::Max } else { PoolKind::Avg },
                    window: Window2 {
                        kernel: [n(3), n(4)],
                        stride: [n(5), n(6)],
                        padding: [n(7), n(8)],
                        dilation: [1, 1],
                    },
                    ceil_mode: n(9) == 1,
                    count_include_pad: true,
                })),
                nchw(2, n(1), n(2)),
            ),
            "upsample" => {
                // readi computes the size when the op is built: floor(len * scale).
                let scale: f64 = f[3].parse().expect("scale");
                let size = [(n(1) as f64 * scale).floor() as i64, (n(2) as f64 * scale).floor() as i64];
                (
                    Op::Pure(Pure::Upsample(Upsample {
                        size,
                        scale: Some([scale, scale]),
                        mode: UpsampleMode::Nearest,
                        align_corners: false,
                    })),
                    nchw(2, n(1), n(2)),
                )
            }
            other => panic!("unknown case kind {other}"),
        };
        let got = match op.infer(&[&input]) {
            Ok(out) => format!("{} {}", out[0].shape[2], out[0].shape[3]),
            Err(_) => "error".to_string(),
        };
        assert_eq!(got, expected, "{case}");
        checked += 1;
    }
    assert!(checked >= 300, "only {checked} cases");
}

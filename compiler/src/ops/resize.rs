//! `upsample(x, scale= | size=, mode="nearest", align_corners=false)`,
//! `pixel_shuffle(x, upscale_factor)` and `pixel_unshuffle(x, downscale_factor)`.

use readi_grammar::diag::{Code, Diagnostic};
use readi_plan::ops::{PixelShuffle, Pure, Upsample, UpsampleMode};

use super::{Args, Builtin, Def, P, R, absent, boolean, positive_float, req};
use crate::ir::{Op, ValueRef};

const UPSAMPLE: &[P] = &[
    req("x"),
    absent("scale"),
    absent("size"),
    P { name: "mode", default: Def::Str("nearest") },
    boolean("align_corners", false),
];

const SHUFFLE: &[P] = &[req("x"), req("upscale_factor")];
const UNSHUFFLE: &[P] = &[req("x"), req("downscale_factor")];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![
        Builtin::new("upsample", UPSAMPLE, upsample),
        Builtin::new("pixel_shuffle", SHUFFLE, pixel_shuffle),
        Builtin::new("pixel_unshuffle", UNSHUFFLE, pixel_shuffle),
    ]
}

fn pixel_shuffle(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let inverse = args.sig.name == "pixel_unshuffle";
    let factor = args.int_at_least(if inverse { "downscale_factor" } else { "upscale_factor" }, 1)?;
    if factor > 1 << 15 {
        return Err(args.bad_value(args.sig.params[1].name, format!("{factor} is too large")));
    }
    Ok((Op::Pure(Pure::PixelShuffle(PixelShuffle { factor, inverse })), vec![args.tensor("x")?]))
}

fn upsample(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let t = args.ttype("x")?;
    let mut factor = None;
    let size = match (args.present("scale"), args.present("size")) {
        (true, false) => {
            let scale = positive_float(args, "scale")?;
            let mut out = [0i64; 2];
            for (i, o) in out.iter_mut().enumerate() {
                let len = t.known_dim(2 + i).filter(|_| t.rank() == 4).ok_or_else(|| {
                    args.bad_value("x", format!("upsample needs an NCHW tensor with known spatial sizes, got {t}"))
                })?;
                // PyTorch: floor(len * scale).
                let v = (len as f64 * scale).floor();
                if !(1.0..=1e9).contains(&v) {
                    return Err(args.bad_value("scale", format!("gives an output size of {v}")));
                }
                *o = v as i64;
            }
            factor = Some([scale, scale]);
            out
        }
        (false, true) => args.pair("size", 1)?,
        _ => {
            return Err(Diagnostic::error(Code::BadArgument, "upsample takes exactly one of `scale` and `size`")
                .with_primary(args.call_span, "give `scale=2` or `size=[h, w]`"));
        }
    };
    let mode = match args.string("mode")?.as_str() {
        "nearest" => UpsampleMode::Nearest,
        "bilinear" => UpsampleMode::Bilinear,
        other => {
            return Err(args.bad_value("mode", format!("must be \"nearest\" or \"bilinear\", got \"{other}\"")));
        }
    };
    let align_corners = args.boolean("align_corners")?;
    if align_corners && mode == UpsampleMode::Nearest {
        return Err(args.bad_value("align_corners", "applies to bilinear mode only".into()));
    }
    let op = Op::Pure(Pure::Upsample(Upsample { size, scale: factor, mode, align_corners }));
    Ok((op, vec![args.tensor("x")?]))
}

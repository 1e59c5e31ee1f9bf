//! `upsample(x, scale= | size=, mode="nearest", align_corners=false)`.

use readi_grammar::diag::{Code, Diagnostic};
use readi_plan::ops::{Pure, Upsample, UpsampleMode};

use super::{Args, Builtin, Def, P, R, absent, boolean, positive_float, req};
use crate::ir::{Op, ValueRef};

const UPSAMPLE: &[P] = &[
    req("x"),
    absent("scale"),
    absent("size"),
    P { name: "mode", default: Def::Str("nearest") },
    boolean("align_corners", false),
];

pub(super) fn builtins() -> Vec<Builtin> {
    vec![Builtin::new("upsample", UPSAMPLE, upsample)]
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

//! `add`, `sub`, `mul`, `div` (the function forms of `+ - * /`; constants go through the
//! operators, which make a `Scalar`), `pow(x, exponent)` (`x ** exponent`), and the
//! activations: `gelu(x, approximate="none")`, `clamp(x, min=, max=)`,
//! `hardtanh(x, min_val=-1.0, max_val=1.0)` (a clamp), `leaky_relu(x, negative_slope=0.01)`,
//! `elu(x, alpha=1.0)` and, for every other [`Activation`], `name(x)`. Names, parameters
//! and defaults are PyTorch's.

use readi_plan::ops::{Activation, BinaryOp, Pure, Scalar};

use super::{Args, Builtin, Def, P, R, absent, flt, req};
use crate::ir::{Op, ValueRef};
use crate::value::Value;

const BINARY: &[P] = &[req("a"), req("b")];
const UNARY: &[P] = &[req("x")];
const GELU: &[P] = &[req("x"), P { name: "approximate", default: Def::Str("none") }];
const CLAMP: &[P] = &[req("x"), absent("min"), absent("max")];
const HARDTANH: &[P] = &[req("x"), flt("min_val", -1.0), flt("max_val", 1.0)];
const LEAKY_RELU: &[P] = &[req("x"), flt("negative_slope", 0.01)];
const ELU: &[P] = &[req("x"), flt("alpha", 1.0)];
const POW: &[P] = &[req("x"), req("exponent")];

pub(super) fn builtins() -> Vec<Builtin> {
    let binary = BinaryOp::ALL.iter().map(|op| Builtin::new(op.name(), BINARY, binary));
    let acts = Activation::ALL.iter().filter(|a| !a.has_options());
    let unary = acts.map(|a| Builtin::new(a.name(), UNARY, activation));
    let with_options = [
        Builtin::new("gelu", GELU, gelu),
        Builtin::new("clamp", CLAMP, clamp),
        Builtin::new("hardtanh", HARDTANH, hardtanh).alias(),
        Builtin::new("leaky_relu", LEAKY_RELU, leaky_relu),
        Builtin::new("elu", ELU, elu),
        Builtin::new("pow", POW, pow),
    ];
    binary.chain(unary).chain(with_options).collect()
}

fn binary(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let op = BinaryOp::ALL.into_iter().find(|o| o.name() == args.sig.name).ok_or_else(|| unknown(args))?;
    Ok((Op::Pure(Pure::Binary(op)), vec![args.tensor("a")?, args.tensor("b")?]))
}

fn activation(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let act = Activation::ALL.into_iter().find(|a| a.name() == args.sig.name).ok_or_else(|| unknown(args))?;
    act_node(act, args)
}

fn act_node(act: Activation, args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    Ok((Op::Pure(Pure::Activation(act)), vec![args.tensor("x")?]))
}

fn gelu(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let act = match args.string("approximate")?.as_str() {
        "none" => Activation::Gelu,
        "tanh" => Activation::GeluTanh,
        other => {
            return Err(args.bad_value("approximate", format!("must be \"none\" or \"tanh\", got \"{other}\"")));
        }
    };
    act_node(act, args)
}

/// A number argument as the f32 PyTorch applies it in; NaN refused.
fn number(args: &Args<'_>, name: &str) -> R<f32> {
    let v = args.float(name)? as f32;
    if v.is_nan() {
        return Err(args.bad_value(name, "must be a number, got NaN".into()));
    }
    Ok(v)
}

/// A finite number argument.
fn finite(args: &Args<'_>, name: &str) -> R<f32> {
    let v = number(args, name)?;
    if !v.is_finite() {
        return Err(args.bad_value(name, format!("must be finite, got {v}")));
    }
    Ok(v)
}

fn clamp(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let bound = |name| if args.present(name) { number(args, name).map(Some) } else { Ok(None) };
    let (min, max) = (bound("min")?, bound("max")?);
    if min.is_none() && max.is_none() {
        return Err(readi_grammar::diag::Diagnostic::error(
            readi_grammar::diag::Code::BadValue,
            "`clamp` needs `min`, `max` or both (as torch.clamp)",
        )
        .with_primary(args.call_span, "neither bound given"));
    }
    act_node(Activation::Clamp { min, max }, args)
}

fn hardtanh(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let (min, max) = (number(args, "min_val")?, number(args, "max_val")?);
    if min > max {
        // torch.nn.functional.hardtanh refuses this too.
        return Err(args.bad_value("max_val", format!("must be at least min_val ({min}), got {max}")));
    }
    act_node(Activation::Clamp { min: Some(min), max: Some(max) }, args)
}

fn leaky_relu(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    act_node(Activation::LeakyRelu { negative_slope: finite(args, "negative_slope")? }, args)
}

fn elu(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    act_node(Activation::Elu { alpha: finite(args, "alpha")? }, args)
}

/// `pow(x, exponent)`: a tensor to a tensor's power (broadcast), to a constant power, or
/// a constant to a tensor's power, as torch.pow.
fn pow(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let scalar = |value: f64, scalar_first| Op::Pure(Pure::Scalar(Scalar { op: BinaryOp::Pow, value, scalar_first }));
    match (args.value("x"), args.value("exponent")) {
        (Some(Value::Tensor { value: x, .. }), Some(Value::Tensor { value: e, .. })) => {
            Ok((Op::Pure(Pure::Binary(BinaryOp::Pow)), vec![*x, *e]))
        }
        (Some(Value::Tensor { value: x, .. }), _) => Ok((scalar(args.float("exponent")?, false), vec![*x])),
        (_, Some(Value::Tensor { value: e, .. })) => Ok((scalar(args.float("x")?, true), vec![*e])),
        _ => Err(match args.tensor("x") {
            Err(e) => e,
            Ok(_) => unknown(args),
        }),
    }
}

/// A builtin made from a name that no longer names an operator: a compiler bug.
fn unknown(args: &Args<'_>) -> readi_grammar::diag::Diagnostic {
    readi_grammar::diag::Diagnostic::error(
        readi_grammar::diag::Code::Internal,
        format!("internal compiler error: builtin `{}` names no operator", args.sig.name),
    )
    .with_primary(args.call_span, "please report this with the input file")
}

//! `add`, `sub`, `mul`, `div` (the function forms of `+ - * /`; constants go through the
//! operators, which make a `Scalar`), and the activations: `gelu(x, approximate="none")`
//! and, for every other [`Activation`], `name(x)`.

use readi_plan::ops::{Activation, BinaryOp, Pure};

use super::{Args, Builtin, Def, P, R, req};
use crate::ir::{Op, ValueRef};

const BINARY: &[P] = &[req("a"), req("b")];
const UNARY: &[P] = &[req("x")];
const GELU: &[P] = &[req("x"), P { name: "approximate", default: Def::Str("none") }];

pub(super) fn builtins() -> Vec<Builtin> {
    let binary = BinaryOp::ALL.iter().map(|op| Builtin::new(op.name(), BINARY, binary));
    let acts = Activation::ALL.iter().filter(|a| !matches!(a, Activation::Gelu | Activation::GeluTanh));
    let unary = acts.map(|a| Builtin::new(a.name(), UNARY, activation));
    binary.chain(unary).chain([Builtin::new("gelu", GELU, gelu)]).collect()
}

fn binary(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let op = BinaryOp::ALL.into_iter().find(|o| o.name() == args.sig.name).ok_or_else(|| unknown(args))?;
    Ok((Op::Pure(Pure::Binary(op)), vec![args.tensor("a")?, args.tensor("b")?]))
}

fn activation(args: &Args<'_>) -> R<(Op, Vec<ValueRef>)> {
    let act = Activation::ALL.into_iter().find(|a| a.name() == args.sig.name).ok_or_else(|| unknown(args))?;
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
    Ok((Op::Pure(Pure::Activation(act)), vec![args.tensor("x")?]))
}

/// A builtin made from a name that no longer names an operator: a compiler bug.
fn unknown(args: &Args<'_>) -> readi_grammar::diag::Diagnostic {
    readi_grammar::diag::Diagnostic::error(
        readi_grammar::diag::Code::Internal,
        format!("internal compiler error: builtin `{}` names no operator", args.sig.name),
    )
    .with_primary(args.call_span, "please report this with the input file")
}

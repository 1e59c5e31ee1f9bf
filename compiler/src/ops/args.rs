//! Builtin signatures and the arguments of a call, bound and checked.
//!
//! Argument names follow PyTorch where it has one (`stride`, `padding`, `groups`,
//! `ceil_mode`, `align_corners`); `out` is the output channel/feature count. The
//! elaborator binds a call's arguments to a [`Sig`] (positional, keyword, defaults) and
//! hands the result to the builtin's builder as [`Args`], whose accessors check each
//! argument's type and range with an error pointing at it.

use readi_grammar::diag::{Code, Diagnostic, Span};

use crate::ir::*;
use crate::value::Value;

/// A default value of an op parameter.
#[derive(Clone, Copy, Debug)]
pub enum Def {
    Required,
    Int(i64),
    Float(f64),
    Bool(bool),
    Str(&'static str),
    /// Optional without a value (`stride` of pools defaults to the kernel).
    Absent,
}

/// A parameter of a builtin.
#[derive(Clone, Copy, Debug)]
pub struct P {
    pub name: &'static str,
    pub default: Def,
}

pub const fn req(name: &'static str) -> P {
    P { name, default: Def::Required }
}
pub const fn int(name: &'static str, v: i64) -> P {
    P { name, default: Def::Int(v) }
}
pub const fn flt(name: &'static str, v: f64) -> P {
    P { name, default: Def::Float(v) }
}
pub const fn boolean(name: &'static str, v: bool) -> P {
    P { name, default: Def::Bool(v) }
}
pub const fn absent(name: &'static str) -> P {
    P { name, default: Def::Absent }
}

/// Signature of a builtin op or function: its name and parameters in order.
#[derive(Debug)]
pub struct Sig {
    pub name: &'static str,
    pub params: &'static [P],
}

/// Arguments bound to a builtin's parameters, defaults filled in.
pub struct Args<'g> {
    pub sig: &'static Sig,
    /// One entry per parameter: the value and where it came from (`None`: absent).
    pub values: Vec<Option<(Value, Span)>>,
    pub call_span: Span,
    pub graph: &'g Graph,
}

/// A builder's result: the value, or an error pointing at the argument at fault.
pub type R<T> = Result<T, Diagnostic>;

impl Args<'_> {
    fn idx(&self, name: &str) -> usize {
        self.sig.params.iter().position(|p| p.name == name).unwrap_or(usize::MAX)
    }

    fn get(&self, name: &str) -> Option<&(Value, Span)> {
        self.values.get(self.idx(name)).and_then(|v| v.as_ref())
    }

    fn span(&self, name: &str) -> Span {
        self.get(name).map(|(_, s)| *s).unwrap_or(self.call_span)
    }

    pub fn mismatch(&self, name: &str, expected: &str, found: &Value) -> Diagnostic {
        let ty = match found {
            Value::Tensor { value, .. } => {
                self.graph.value_type(*value).map(|t| format!("a tensor {t}")).unwrap_or_default()
            }
            v => v.kind().to_string(),
        };
        Diagnostic::error(
            Code::TypeMismatch,
            format!("argument `{name}` of `{}` must be {expected}, found {ty}", self.sig.name),
        )
        .with_primary(self.span(name), format!("expected {expected}"))
    }

    pub fn bad_value(&self, name: &str, message: String) -> Diagnostic {
        Diagnostic::error(Code::BadValue, format!("argument `{name}` of `{}`: {message}", self.sig.name))
            .with_primary(self.span(name), message)
    }

    pub fn present(&self, name: &str) -> bool {
        self.get(name).is_some()
    }

    pub fn value(&self, name: &str) -> Option<&Value> {
        self.get(name).map(|(v, _)| v)
    }

    pub fn tensor(&self, name: &str) -> R<ValueRef> {
        match self.value(name) {
            Some(Value::Tensor { value, .. }) => Ok(*value),
            Some(v) => Err(self.mismatch(name, "a tensor", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    pub fn ttype(&self, name: &str) -> R<&TensorType> {
        let v = self.tensor(name)?;
        self.graph.value_type(v).ok_or_else(|| self.bad_value(name, "has no type".into()))
    }

    pub fn int(&self, name: &str) -> R<i64> {
        match self.value(name) {
            Some(Value::Int(i)) => Ok(*i),
            Some(v) => Err(self.mismatch(name, "an int", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    /// An int at least `min`.
    pub fn int_at_least(&self, name: &str, min: i64) -> R<i64> {
        let v = self.int(name)?;
        if v < min {
            return Err(self.bad_value(name, format!("must be at least {min}, got {v}")));
        }
        Ok(v)
    }

    pub fn float(&self, name: &str) -> R<f64> {
        match self.value(name) {
            Some(Value::Float(f)) => Ok(*f),
            Some(Value::Int(i)) => Ok(*i as f64),
            Some(v) => Err(self.mismatch(name, "a number", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    pub fn boolean(&self, name: &str) -> R<bool> {
        match self.value(name) {
            Some(Value::Bool(b)) => Ok(*b),
            Some(v) => Err(self.mismatch(name, "`true` or `false`", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    pub fn string(&self, name: &str) -> R<String> {
        match self.value(name) {
            Some(Value::Str(s)) => Ok(s.to_string()),
            Some(v) => Err(self.mismatch(name, "a string", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    /// An int or a two-element list of ints, each at least `min`: `3` or `[3, 1]`.
    pub fn pair(&self, name: &str, min: i64) -> R<[i64; 2]> {
        let p = match self.value(name) {
            Some(Value::Int(i)) => [*i, *i],
            Some(Value::List(l)) if l.len() == 2 => match (&l[0], &l[1]) {
                (Value::Int(a), Value::Int(b)) => [*a, *b],
                _ => return Err(self.mismatch(name, "an int or a pair of ints", &Value::List(l.clone()))),
            },
            Some(v) => return Err(self.mismatch(name, "an int or a pair of ints", v)),
            None => return Err(self.bad_value(name, "missing".into())),
        };
        if p[0] < min || p[1] < min {
            return Err(self.bad_value(name, format!("must be at least {min}, got {}", show_pair(p))));
        }
        Ok(p)
    }

    /// An int or a list of ints.
    pub fn int_list(&self, name: &str) -> R<Vec<i64>> {
        match self.value(name) {
            Some(Value::Int(i)) => Ok(vec![*i]),
            Some(Value::List(l)) => l
                .iter()
                .map(|v| match v {
                    Value::Int(i) => Ok(*i),
                    other => Err(self.mismatch(name, "a list of ints", other)),
                })
                .collect(),
            Some(v) => Err(self.mismatch(name, "a list of ints", v)),
            None => Err(self.bad_value(name, "missing".into())),
        }
    }

    /// An axis index for a tensor of the given rank; negative counts from the end.
    pub fn axis(&self, name: &str, rank: usize) -> R<usize> {
        let a = self.int(name)?;
        self.normalize_axis(name, a, rank)
    }

    fn normalize_axis(&self, name: &str, a: i64, rank: usize) -> R<usize> {
        let r = rank as i64;
        let n = if a < 0 { a + r } else { a };
        if n < 0 || n >= r {
            return Err(self.bad_value(name, format!("axis {a} is out of range for a tensor of rank {rank}")));
        }
        Ok(n as usize)
    }

    pub fn axes(&self, name: &str, rank: usize) -> R<Vec<usize>> {
        let list = self.int_list(name)?;
        list.iter().map(|&a| self.normalize_axis(name, a, rank)).collect()
    }
}

fn show_pair(p: [i64; 2]) -> String {
    if p[0] == p[1] { p[0].to_string() } else { format!("[{}, {}]", p[0], p[1]) }
}

/// A positive, finite float argument.
pub fn positive_float(args: &Args<'_>, name: &str) -> R<f64> {
    let v = args.float(name)?;
    if v <= 0.0 || !v.is_finite() {
        return Err(args.bad_value(name, format!("must be a positive number, got {v}")));
    }
    Ok(v)
}

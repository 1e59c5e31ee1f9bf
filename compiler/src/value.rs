//! Values of the elaboration-time language: what an expression evaluates to while the
//! graph is built, and what a builtin's arguments are (`crate::ops`).

use std::rc::Rc;

use crate::ir::{Dim, ScopeId, ValueRef};

/// What an expression evaluates to while the graph is being built.
#[derive(Clone, Debug)]
pub enum Value {
    Int(i64),
    Float(f64),
    Bool(bool),
    Str(Rc<str>),
    /// A dimension with a symbolic factor (`N`, `6*N`), from `dim(x, 0)` or an input shape.
    Dim(Dim),
    /// A tensor: one output of a node. `scope` is set when the tensor is the value of a
    /// block instance or `seq`, so that `name.child` can reach the layers inside.
    Tensor {
        value: ValueRef,
        scope: Option<ScopeId>,
    },
    List(Rc<Vec<Value>>),
    /// A block instance without `return`, or a namespace: only its layers are reachable.
    Scope(ScopeId),
    /// The result of an expression that already produced an error. Every use of a poison
    /// value is poison too, silently, so one mistake gives one diagnostic.
    Poison,
}

impl Value {
    /// A short description for type errors: "an int", "a tensor".
    pub fn kind(&self) -> &'static str {
        match self {
            Value::Int(_) => "an int",
            Value::Float(_) => "a float",
            Value::Bool(_) => "a bool",
            Value::Str(_) => "a string",
            Value::Dim(_) => "a symbolic dimension",
            Value::Tensor { .. } => "a tensor",
            Value::List(_) => "a list",
            Value::Scope(_) => "a block instance without `return`",
            Value::Poison => "an invalid value",
        }
    }

    pub fn is_poison(&self) -> bool {
        matches!(self, Value::Poison)
    }
}

//! Tensor subscripts: `x[:, 0:64]`, `x[..., 1]`, `qkv[0]`, `x[:, ::2]`, `x[-1]`, Python's
//! basic indexing, elaborated to one `slice` node (none when every axis is kept whole).
//!
//! Separate because it is the one place where an index expression becomes a node: list
//! and sequence indexing (`blocks[i]`) stay in `eval.rs`, and come first: a block's or
//! `seq`'s output indexed by one int names its layer; `x[0, ...]` slices it.

use readi_grammar::ast::{Expr, Subscript};
use readi_grammar::diag::{Code, Diagnostic, Span};
use readi_plan::ops::{Pure, Slice, SliceAxis};

use super::{Elab, Frame, Hint, Value};
use crate::ir::*;

/// One evaluated subscript entry.
enum Entry {
    Axis(SliceAxis, Span),
    Ellipsis(Span),
}

impl<'a> Elab<'a> {
    /// `base[subs]` on a tensor.
    pub(super) fn subscript(
        &mut self,
        base: &'a Expr,
        subs: &'a [Subscript],
        span: Span,
        hint: Option<Hint>,
        frame: &mut Frame<'a>,
    ) -> Value {
        let b = self.eval(base, frame, None);
        let mut entries = Vec::with_capacity(subs.len());
        let mut poisoned = false;
        for s in subs {
            match self.subscript_entry(s, frame) {
                Some(e) => entries.push(e),
                None => poisoned = true,
            }
        }
        if poisoned || b.is_poison() {
            return Value::Poison;
        }
        self.slice_tensor(b, entries, base.span, span, hint, frame.scope)
    }

    /// `base[i]` with a tensor base: the element `i` along the first axis.
    pub(super) fn index_tensor(
        &mut self,
        b: Value,
        i: i64,
        idx_span: Span,
        base_span: Span,
        hint: Option<Hint>,
        scope: ScopeId,
    ) -> Value {
        let span = base_span.to(idx_span);
        self.slice_tensor(b, vec![Entry::Axis(SliceAxis::Index(i), idx_span)], base_span, span, hint, scope)
    }

    fn subscript_entry(&mut self, s: &'a Subscript, frame: &mut Frame<'a>) -> Option<Entry> {
        let mut int = |this: &mut Self, e: &'a Expr, what: &str| -> Option<i64> {
            match this.eval(e, frame, None) {
                Value::Int(i) => Some(i),
                Value::Poison => None,
                v => {
                    this.error(
                        Diagnostic::error(
                            Code::TypeMismatch,
                            format!("a tensor {what} must be an int, found {}", v.kind()),
                        )
                        .with_primary(e.span, "not an int"),
                    );
                    None
                }
            }
        };
        match s {
            Subscript::Ellipsis(span) => Some(Entry::Ellipsis(*span)),
            Subscript::Index(e) => Some(Entry::Axis(SliceAxis::Index(int(self, e, "index")?), e.span)),
            Subscript::Range { start, stop, step, span } => {
                let start = match start {
                    Some(e) => Some(int(self, e, "slice bound")?),
                    None => None,
                };
                let stop = match stop {
                    Some(e) => Some(int(self, e, "slice bound")?),
                    None => None,
                };
                let step = match step {
                    Some(e) => {
                        let v = int(self, e, "slice step")?;
                        if v < 1 {
                            self.error(
                                Diagnostic::error(Code::BadValue, format!("slice step must be at least 1, got {v}"))
                                    .with_primary(e.span, "step below 1")
                                    .with_note("PyTorch refuses negative steps too"),
                            );
                            return None;
                        }
                        v
                    }
                    None => 1,
                };
                Some(Entry::Axis(SliceAxis::Range { start, stop, step }, *span))
            }
        }
    }

    fn slice_tensor(
        &mut self,
        b: Value,
        entries: Vec<Entry>,
        base_span: Span,
        span: Span,
        hint: Option<Hint>,
        scope: ScopeId,
    ) -> Value {
        let Value::Tensor { value, .. } = b else {
            return self.error(
                Diagnostic::error(Code::TypeMismatch, format!("cannot slice {}", b.kind()))
                    .with_primary(base_span, "not a tensor"),
            );
        };
        let Some(t) = self.graph.value_type(value).cloned() else { return Value::Poison };
        let ellipses: Vec<Span> =
            entries.iter().filter_map(|e| if let Entry::Ellipsis(s) = e { Some(*s) } else { None }).collect();
        if ellipses.len() > 1 {
            return self.error(
                Diagnostic::error(Code::BadValue, "a subscript has at most one `...`")
                    .with_primary(ellipses[1], "second `...`"),
            );
        }
        let written = entries.len() - ellipses.len();
        if written > t.rank() {
            let extra = entries.iter().filter(|e| matches!(e, Entry::Axis(..))).nth(t.rank());
            let at = match extra {
                Some(Entry::Axis(_, s)) => *s,
                _ => span,
            };
            return self.error(
                Diagnostic::error(
                    Code::BadValue,
                    format!("too many indices for {t}: {written} given, it has {} axes", t.rank()),
                )
                .with_primary(at, "one index too many"),
            );
        }
        let mut axes = Vec::with_capacity(t.rank());
        for e in entries {
            match e {
                Entry::Ellipsis(_) => axes.extend(std::iter::repeat_n(SliceAxis::FULL, t.rank() - written)),
                Entry::Axis(a, s) => {
                    let axis = axes.len();
                    if let (SliceAxis::Index(i), Some(d)) = (a, t.known_dim(axis))
                        && (i >= d || i < -d)
                    {
                        return self.error(
                            Diagnostic::error(
                                Code::BadValue,
                                format!("index {i} is out of range for axis {axis} of {t}"),
                            )
                            .with_primary(s, format!("axis {axis} has size {d}")),
                        );
                    }
                    axes.push(a);
                }
            }
        }
        axes.resize(t.rank(), SliceAxis::FULL);
        if axes.iter().all(|a| *a == SliceAxis::FULL) {
            return Value::Tensor { value, scope: None };
        }
        self.add_node_in(Op::Pure(Pure::Slice(Slice { axes })), vec![value], hint, span, scope)
    }
}

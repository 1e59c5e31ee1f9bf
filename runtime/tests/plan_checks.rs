//! The checks the executor relies on: plans are untrusted, and a step that reads the
//! buffer it writes, breaks its operator's shape rule or uses an undeclared symbol is
//! refused when the plan is built, with the step named.

mod common;

use readi_plan::Dim;
use readi_runtime::plan::{Plan, Storage};

use common::*;

// ---------------------------------------------------------------------------------------
// Checks the executor relies on (plans are untrusted)
// ---------------------------------------------------------------------------------------

#[test]
fn a_step_reading_the_buffer_it_writes_is_refused() {
    let (mut m, tensors) = edited(Vec::clear);
    // `ln` reads value 1 (slot 0); make it write slot 0 too.
    m.values[2].storage = Storage::Slot(0);
    let e = Plan::new(m, tensors).expect_err("must be refused").to_string();
    assert!(e.contains("`ln`") && e.contains("reads buffer 0, which it writes"), "{e}");
}

#[test]
fn a_step_whose_shapes_break_its_operator_rule_is_refused() {
    let (mut m, tensors) = edited(Vec::clear);
    // `fc` maps 4 features to 3; claim its output has 5.
    m.values[1].shape = dims(&[5]);
    let e = Plan::new(m, tensors).expect_err("must be refused").to_string();
    assert!(e.contains("step 0 (`fc`)") && e.contains("[N, 5]") && e.contains("[N, 3]"), "{e}");
}

#[test]
fn an_input_with_an_undeclared_symbol_is_refused() {
    let (mut m, tensors) = edited(Vec::clear);
    m.inputs[0].shape[0] = Dim::symbol("M");
    let e = Plan::new(m, tensors).expect_err("must be refused").to_string();
    assert!(e.contains("input `x` has an invalid dimension M"), "{e}");
}

#[test]
fn a_symbol_that_is_not_an_identifier_is_refused() {
    // Symbols are printed in every shape: one that could hold escape sequences is refused.
    let (mut m, tensors) = edited(Vec::clear);
    m.symbols[0] = "N\u{1b}[2J".into();
    let e = Plan::new(m, tensors).expect_err("must be refused").to_string();
    assert!(e.contains("symbol `N\\u{1b}[2J` is not an identifier"), "{e}");
}

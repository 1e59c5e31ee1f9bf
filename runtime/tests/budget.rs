//! The memory budget: binding computes a run's footprint before allocating and refuses a
//! footprint over the session's limit; the plan records its footprint at batch 1.

mod common;

use std::sync::Arc;

use readi_runtime::exec::{self, Input, RunError, Session, SessionOptions};

use common::*;

#[test]
fn the_footprint_counts_every_part_and_grows_with_the_batch() {
    let plan = Arc::new(mlp(4, 3).plan);
    let f2 = exec::footprint(&plan, 2, 1).expect("a footprint");
    // x: [2, 4], y: [2, 3], floats of 4 bytes.
    assert_eq!(f2.inputs, 2 * 4 * 4);
    assert_eq!(f2.outputs, 2 * 3 * 4);
    assert_eq!(f2.total, f2.activations + f2.scratch + f2.lora + f2.working + f2.zeros + f2.inputs + f2.outputs);
    let f4 = exec::footprint(&plan, 4, 1).expect("a footprint");
    assert_eq!(f4.activations, 2 * f2.activations);
    assert!(!f2.largest.is_empty() && f2.largest.windows(2).all(|w| w[0].1 >= w[1].1), "{:?}", f2.largest);
    // What Plan::new recorded: batch 1 on one thread.
    let f1 = exec::footprint(&plan, 1, 1).expect("a footprint");
    let recorded = plan.manifest.footprint.expect("recorded by Plan::new");
    assert_eq!((recorded.batch, recorded.total, recorded.activations), (1, f1.total as u64, f1.activations as u64));
}

#[test]
fn a_run_over_the_limit_is_refused_and_one_within_it_runs() {
    let plan = Arc::new(mlp(4, 3).plan);
    let need = exec::footprint(&plan, 2, 1).expect("a footprint").total;
    let x = vec![0.5f32; 8];
    let given = [Input { name: "x", data: &x, shape: &[2, 4] }];
    let options = SessionOptions::default().threads(1).max_memory(need - 1);
    let mut s = Session::with_options(Arc::clone(&plan), options).expect("session");
    match s.run(&given) {
        Err(RunError::OverBudget { needed, limit, at, largest }) => {
            assert_eq!((needed, limit, at.as_str()), (need, need - 1, "N = 2"));
            assert!(!largest.is_empty());
        }
        other => panic!("expected OverBudget, got {other:?}"),
    }
    let e = exec::check_fits(&plan, &given, &options).expect_err("over the limit").to_string();
    assert!(e.contains("over the limit of") && e.contains("largest: "), "{e}");
    let mut s = Session::with_options(Arc::clone(&plan), options.max_memory(need)).expect("session");
    assert_eq!(s.run(&given).expect("runs").len(), 1);
    assert_eq!(s.bind_batch(2).expect("bound").total, need);
    assert!(matches!(s.bind_batch(usize::MAX), Err(RunError::TooLarge { .. })));
}

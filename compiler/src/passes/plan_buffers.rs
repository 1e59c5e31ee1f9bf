//! `plan_buffers`: assigns every computed value an activation buffer (slot) so that
//! values whose lifetimes do not overlap share one (rule `plan_buffers`).
//!
//! A value lives from the step that writes it to the last step that reads it (graph
//! outputs live to the end). Steps are visited in order; a step's output takes a free slot
//! before the step's own inputs are released, so no step ever writes a buffer it reads.
//! Among free slots the best fit is taken: the smallest slot at least as large as the
//! value (sizes compared at batch size 1), else the largest one, which then grows. The
//! runtime sizes each slot as the largest value assigned to it at the bound batch size.
//!
//! A reshape of a computed value takes no buffer: it is a view of its input's, which then
//! lives until the last reader of the input or of any of its views, and the runtime runs
//! the step as nothing ([`Step::is_view`]).
//!
//! Assumes `lower` ran (it gives every value a buffer of its own). The lowered plan's
//! manifest changes; its tensors do not.

use readi_grammar::diag::Diagnostics;
use readi_plan::format::{Kernel, Step, Storage, ValueSpec};
use readi_plan::ops::Pure;

use super::{BackendInputs, Output};
use crate::module::Module;

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let mut lowered = module.lowered.clone().ok_or_else(|| super::internal("the module is not lowered"))?;
    let m = &mut lowered.manifest;
    let outputs: Vec<usize> = m.outputs.iter().map(|o| o.value).collect();
    m.slots = plan_buffers(&mut m.values, &m.steps, &outputs);
    Ok(Output::Lowered(Box::new(lowered)))
}

/// Rewrites the storage of every slot value; returns the number of slots.
pub fn plan_buffers(values: &mut [ValueSpec], steps: &[Step], outputs: &[usize]) -> usize {
    // Elements at batch size 1 (every symbol taken as 1), at least one.
    let size = |v: &ValueSpec| -> usize { v.shape.iter().map(|d| d.coef().max(0) as usize).product::<usize>().max(1) };
    // A reshape of a computed value is a view of its buffer: `root[v]` is the value whose
    // buffer `v` is (itself, unless `v` is a view), and the buffer lives until the last
    // reader of any of its views.
    let mut root: Vec<usize> = (0..values.len()).collect();
    let computed: Vec<bool> = values.iter().map(|v| matches!(v.storage, Storage::Slot(_))).collect();
    let view: Vec<bool> = steps
        .iter()
        .map(|s| matches!(s.kernel, Kernel::Pure(Pure::Reshape(_))) && s.inputs.len() == 1 && computed[s.inputs[0]])
        .collect();
    for (s, _) in steps.iter().zip(&view).filter(|(_, v)| **v) {
        root[s.output] = root[s.inputs[0]];
    }
    let mut last_use: Vec<Option<usize>> = vec![None; values.len()];
    for (k, s) in steps.iter().enumerate() {
        for &i in &s.inputs {
            last_use[root[i]] = Some(k);
        }
    }
    for &o in outputs {
        last_use[root[o]] = Some(usize::MAX);
    }
    let mut slot_size: Vec<usize> = Vec::new();
    let mut free: Vec<usize> = Vec::new();
    for (k, s) in steps.iter().enumerate() {
        let slot = if view[k] {
            let Storage::Slot(slot) = values[root[s.output]].storage else {
                unreachable!("a view of a computed value")
            };
            slot
        } else {
            let need = size(&values[s.output]);
            let fit = free
                .iter()
                .enumerate()
                .filter(|(_, slot)| slot_size[**slot] >= need)
                .min_by_key(|(_, slot)| slot_size[**slot])
                .or_else(|| free.iter().enumerate().max_by_key(|(_, slot)| slot_size[**slot]))
                .map(|(i, _)| i);
            let slot = match fit {
                Some(i) => free.swap_remove(i),
                None => {
                    slot_size.push(0);
                    slot_size.len() - 1
                }
            };
            slot_size[slot] = slot_size[slot].max(need);
            slot
        };
        values[s.output].storage = Storage::Slot(slot);
        // Release the buffers this step reads for the last time (once, even if read twice).
        let mut released: Vec<usize> = Vec::new();
        for &i in &s.inputs {
            let r = root[i];
            if last_use[r] == Some(k) && !released.contains(&r) {
                released.push(r);
                if let Storage::Slot(sl) = values[r].storage {
                    free.push(sl);
                }
            }
        }
        // A value nobody reads is free as soon as it is written.
        if last_use[root[s.output]].is_none() && !released.contains(&root[s.output]) {
            free.push(slot);
        }
    }
    slot_size.len()
}

#[cfg(test)]
mod tests {
    use readi_plan::Dim;
    use readi_plan::ops::{Activation, Reshape};

    use super::*;

    fn value(n: i64, storage: Storage) -> ValueSpec {
        let shape = Dim::known(n).checked_mul(&Dim::symbol("N")).into_iter().collect();
        ValueSpec { shape, storage }
    }

    fn step(inputs: Vec<usize>, output: usize) -> Step {
        let kernel = Kernel::Pure(Pure::Activation(Activation::Relu));
        Step { path: format!("v{output}"), kernel, inputs, output }
    }

    fn reshape(input: usize, output: usize) -> Step {
        let kernel = Kernel::Pure(Pure::Reshape(Reshape { shape: Vec::new() }));
        Step { path: format!("v{output}"), kernel, inputs: vec![input], output }
    }

    /// The steps that write a buffer while a value in it (or a view of it) is still read:
    /// what a correct assignment never has.
    fn clobbered(values: &[ValueSpec], steps: &[Step], outputs: &[usize]) -> Vec<String> {
        let mut last_read = vec![None; values.len()];
        for (k, s) in steps.iter().enumerate() {
            for &i in &s.inputs {
                last_read[i] = Some(k);
            }
        }
        for &o in outputs {
            last_read[o] = Some(usize::MAX);
        }
        let mut bad = Vec::new();
        for (k, s) in steps.iter().enumerate().filter(|(_, s)| !s.is_view(values)) {
            for (j, w) in steps[..k].iter().enumerate() {
                let v = w.output;
                let live = last_read[v].is_some_and(|l| l >= k);
                if live && values[v].storage == values[s.output].storage {
                    bad.push(format!("{} overwrites {} (written by step {j}) while it is read", s.path, w.path));
                }
            }
        }
        bad
    }

    #[test]
    fn a_chain_needs_two_buffers() {
        // x -> a -> b -> c -> d: each step reads the previous value only.
        let mut values = vec![value(8, Storage::Input(0))];
        values.extend((0..4).map(|_| value(8, Storage::Slot(0))));
        let steps: Vec<Step> = (1..5).map(|i| step(vec![i - 1], i)).collect();
        let slots = plan_buffers(&mut values, &steps, &[4]);
        assert_eq!(slots, 2);
        for s in &steps {
            for &i in &s.inputs {
                assert_ne!(values[i].storage, values[s.output].storage, "step {} writes what it reads", s.path);
            }
        }
    }

    #[test]
    fn live_values_never_share_a_buffer() {
        // a = f(x); b = g(a); c = h(a, b): a is live across b.
        let mut values = vec![value(4, Storage::Input(0)), value(4, Storage::Slot(0)), value(4, Storage::Slot(0))];
        values.push(value(4, Storage::Slot(0)));
        let steps = vec![step(vec![0], 1), step(vec![1], 2), step(vec![1, 2], 3)];
        let slots = plan_buffers(&mut values, &steps, &[3]);
        assert_eq!(slots, 3);
        let s: Vec<_> = values[1..].iter().map(|v| v.storage).collect();
        assert!(s[0] != s[1] && s[1] != s[2] && s[0] != s[2], "{s:?}");
    }

    #[test]
    fn outputs_are_never_reused() {
        // a = f(x) is an output; b = g(x), c = h(b) must not take a's buffer.
        let mut values: Vec<ValueSpec> = vec![value(4, Storage::Input(0))];
        values.extend((0..3).map(|_| value(4, Storage::Slot(0))));
        let steps = vec![step(vec![0], 1), step(vec![0], 2), step(vec![2], 3)];
        plan_buffers(&mut values, &steps, &[1, 3]);
        assert_ne!(values[1].storage, values[3].storage);
        assert_ne!(values[1].storage, values[2].storage);
    }

    #[test]
    fn a_reshape_is_a_view_of_its_input() {
        // a = f(x); v = reshape(a); b = g(v): v takes a's buffer, and the step is a view.
        let mut values = vec![value(8, Storage::Input(0))];
        values.extend((0..3).map(|_| value(8, Storage::Slot(0))));
        let steps = vec![step(vec![0], 1), reshape(1, 2), step(vec![2], 3)];
        let slots = plan_buffers(&mut values, &steps, &[3]);
        assert_eq!(values[2].storage, values[1].storage);
        assert!(steps[1].is_view(&values) && !steps[0].is_view(&values));
        assert_ne!(values[3].storage, values[2].storage, "g writes what it reads");
        assert_eq!(slots, 2);
    }

    #[test]
    fn a_buffer_lives_as_long_as_its_views() {
        // a = f(x); v = reshape(a); w = reshape(v); b = g(a); c = h(b); d = k(w, c): a's
        // buffer is read through w at the last step, so neither b nor c may take it.
        let mut values = vec![value(4, Storage::Input(0))];
        values.extend((0..6).map(|_| value(4, Storage::Slot(0))));
        let steps = vec![
            step(vec![0], 1),
            reshape(1, 2),
            reshape(2, 3),
            step(vec![1], 4),
            step(vec![4], 5),
            step(vec![3, 5], 6),
        ];
        plan_buffers(&mut values, &steps, &[6]);
        assert_eq!(values[3].storage, values[1].storage);
        assert_eq!(clobbered(&values, &steps, &[6]), Vec::<String>::new());
        // An output's view keeps it too.
        let mut values = vec![value(4, Storage::Input(0))];
        values.extend((0..4).map(|_| value(4, Storage::Slot(0))));
        let steps = vec![step(vec![0], 1), reshape(1, 2), step(vec![1], 3), step(vec![3], 4)];
        plan_buffers(&mut values, &steps, &[2, 4]);
        assert_eq!(clobbered(&values, &steps, &[2, 4]), Vec::<String>::new());
        assert_ne!(values[4].storage, values[2].storage);
    }

    #[test]
    fn a_reshape_of_an_input_is_copied() {
        // The caller's buffer is not the plan's to alias: reshape(x) gets a buffer.
        let mut values = vec![value(4, Storage::Input(0)), value(4, Storage::Slot(0))];
        let steps = vec![reshape(0, 1)];
        assert_eq!(plan_buffers(&mut values, &steps, &[1]), 1);
        assert!(!steps[0].is_view(&values));
    }
}

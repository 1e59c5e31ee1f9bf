//! `drop_inactive`: removes the LoRA branches and adapters that no variant uses.
//!
//! An injection whose added parameters are zero in the base and in every variant adds
//! zero wherever it runs: `y + scale * B(A(x))` is `y`, `L(x + up(act(down(x))))` is
//! `L(x)`. Rules `drop_lora` (uses of the sum read the base layer again) and
//! `drop_adapter` (the adapted layer reads `x` again) remove its nodes. Without variants
//! every injection is dropped, so a base plan is the model without adaptations.
//!
//! Does nothing when every injection has a non-zero parameter somewhere. Assumes the
//! variants are bound (`bind_variants`, `meld`).

use readi_grammar::diag::Diagnostics;

use super::bind_variants::not_bound;
use super::{BackendInputs, Output, Patch};
use crate::adapt::Injection;
use crate::ir::{Graph, ValueRef};
use crate::module::Module;
use crate::weights::tensors::TensorTable;

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let Some(plan) = &module.adapt else { return Ok(Output::Patches(Vec::new())) };
    let mut patches = Vec::new();
    for inj in plan.injections.iter().filter(|inj| zero_everywhere(g, table, inj)) {
        let out = |node| ValueRef { node, port: 0 };
        let mut p = match *inj {
            Injection::Lora { base, add, .. } => {
                let mut p = Patch::new("drop_lora");
                p.replace_uses.push((out(add), out(base)));
                p
            }
            Injection::Adapter { target, add, .. } => {
                let mut p = Patch::new("drop_adapter");
                let Some(&x) = g.inputs(add).first() else { continue };
                p.set_inputs.push((target, 0, x));
                p
            }
        };
        p.remove.extend(inj.nodes());
        patches.push(p);
    }
    Ok(Output::Patches(patches))
}

/// Whether every parameter of the injection's nodes is zero in the base and in every
/// variant.
fn zero_everywhere(g: &Graph, table: &TensorTable, inj: &Injection) -> bool {
    inj.nodes().iter().all(|&n| {
        let node = g.node(n);
        node.params.iter().all(|slot| {
            let Some(t) = table.get(&node.param_name(slot)) else { return true };
            (0..=table.variant_count()).all(|v| t.value(v).iter().all(|x| *x == 0.0))
        })
    })
}

//! A module: the graph and what the passes have learned about it.
//!
//! The graph is the IR ([`crate::ir`]); everything else is a side table a pass filled in,
//! `None` until then:
//!
//! | field      | set by           | holds                                                    |
//! |------------|------------------|----------------------------------------------------------|
//! | `adapt`    | `resolve_adapt`  | the adaptation rules bound to layers, and `inject_adapt`'s injections |
//! | `variants` | `check_variants` | the checked `variants` section (axes, selectors, meld rule) |
//! | `tensors`  | `bind_weights`   | every tensor's base value and the variants' values        |
//! | `strategy` | `choose_strategy`| per LoRA layer merge or branch, per variant-owned conv its algorithm |
//! | `lowered`  | `lower`          | the schedule and its stored tensors: the plan in the making |

use readi_plan::format::Manifest;

use crate::ir::Graph;
use crate::weights::tensors::TensorTable;
use readi_plan::conditions::Conditions as VariantSpec;

use crate::adapt::AdaptPlan;

/// See the module documentation.
#[derive(Clone, Debug)]
pub struct Module {
    pub graph: Graph,
    /// Set by `resolve_adapt` when the file has an `adapt` section.
    pub adapt: Option<AdaptPlan>,
    /// Set by `check_variants` when the file has a `variants` section.
    pub variants: Option<VariantSpec>,
    /// Set by `bind_weights`; `bind_variants` and `meld` add the variants.
    pub tensors: Option<TensorTable>,
    /// Set by `lower`; `plan_buffers` assigns its buffers.
    pub lowered: Option<Lowered>,
    /// Set by `choose_strategy` when a layer has a choice.
    pub strategy: Option<crate::passes::choose_strategy::Strategy>,
}

impl Module {
    /// A module of a graph, with no side tables yet.
    pub fn new(graph: Graph) -> Module {
        Module { graph, adapt: None, variants: None, tensors: None, lowered: None, strategy: None }
    }
}

/// A lowered module: the plan's manifest (schedule, values, tensors, variant tables) and
/// the data of each stored tensor, in manifest order.
#[derive(Clone, Debug)]
pub struct Lowered {
    pub manifest: Manifest,
    /// Per manifest tensor, its data: f32, or f16 for a variant's replacement the
    /// strategy stores at half precision.
    pub data: Vec<readi_runtime::plan::TensorData>,
}

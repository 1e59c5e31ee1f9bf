//! `pack_weights`: stores each weight in the layout its kernel reads, once, at compile
//! time, for the base and every variant that changes it.
//!
//! * rule `pack_conv`: a conv's weight packed for its algorithm
//!   (`readi_runtime::kernels::conv::pack_weight`: Winograd-transformed, or as PyTorch's
//!   for the GEMM paths), as `<path>.weight@<algo>`, and a fused LoRA branch's `A` for
//!   the same algorithm (a conv to `rank` channels), as `<path>.lora_A.weight@<algo>`,
//!   where packing keeps PyTorch's layout (`ConvAlgo::packs_as_is`: the GEMM paths); a
//!   Winograd layer's `A` stays raw (`lower` marks it `a_raw`) and the runtime packs it;
//! * rule `keep_raw`: a conv `choose_strategy` merges on switch keeps its weight and its
//!   fused LoRA `A` raw (the plan's variants store only raw tensors) and is marked
//!   `switch`; the runtime packs `W + B A` into a per-session working copy when the
//!   variant changes;
//! * rule `pack_linear`: a linear with few rows per image ([`PANEL_ROWS`]) whose outputs
//!   fill their panels (at most 1/8 padding) has its weight packed in panels
//!   (`readi_runtime::kernels::panel::pack`), as `<path>.weight@panels`: the runtime's
//!   product then reads it without packing it on every call;
//! * rule `transpose_linear`: any other linear's weight transposed to `[in, out]`, the
//!   layout the `gemm` crate reads fastest, as `<path>.weight@t`.
//!
//! Does nothing when every weight is packed. Assumes every conv has an algorithm
//! (`choose_conv_algo`).

use readi_grammar::diag::Diagnostics;
use readi_plan::ops::PANEL;
use readi_runtime::kernels::{conv, panel};

use super::bind_variants::not_bound;
use super::choose_conv_algo::spatial;
use super::{BackendInputs, Output, Patch, internal, rebind};
use crate::ir::{Graph, NodeId, Op};
use crate::module::Module;
use crate::ops::{ConvOp, LinearOp};

pub fn run(module: &Module, _: &BackendInputs<'_>, _: &mut Diagnostics) -> Result<Output, Diagnostics> {
    let table = module.tensors.as_ref().ok_or_else(not_bound)?;
    let g = &module.graph;
    let mut patches = Vec::new();
    for id in g.node_ids() {
        let node = g.node(id);
        let Some(slot) = node.params.iter().find(|s| s.name == "weight") else { continue };
        let weight = node.param_name(slot);
        match &node.op {
            Op::Conv2d(c) if !c.packed && module.strategy.as_ref().is_some_and(|s| s.switch_of(&node.path)) => {
                if c.algo.is_none() {
                    return Err(internal(format!("conv `{}` has no algorithm", node.path)));
                }
                let new = Op::Conv2d(ConvOp { packed: true, switch: true, ..c.clone() });
                let mut p = Patch::new("keep_raw");
                p.rewrite.push((id, new.clone(), rebind(&new, &node.params, &[])));
                patches.push(p);
            }
            Op::Conv2d(c) if !c.packed => {
                let Some(algo) = c.algo else { return Err(internal(format!("conv `{}` has no algorithm", node.path))) };
                let (h, w) = spatial(g, id);
                let s = c.conv.shape(1, h, w);
                let len = algo.packed_len(&s);
                let packed = table
                    .derive_one(&[&weight], "packed as", vec![len], |v| {
                        let mut out = vec![0.0; len];
                        conv::pack_weight(&s, algo, v[0], &mut out);
                        out
                    })
                    .map_err(internal)?;
                let name = format!("{}.weight@{}", node.path, algo.name());
                let new = Op::Conv2d(ConvOp { packed: true, ..c.clone() });
                let mut bind = vec![("weight", name.clone())];
                let mut p = Patch::new("pack_conv");
                p.tensors.push((name, packed));
                // `A` is packed only where that keeps its layout; a Winograd `A` stays raw
                // (16/9 or 36/9 smaller per variant) and the runtime packs it per session.
                if let (Some(rank), Some(slot), true) =
                    (c.lora, node.params.iter().find(|s| s.name == "lora_A"), algo.packs_as_is())
                {
                    let a = node.param_name(slot);
                    let sa = conv::lora_a_shape(&s, rank.max(0) as usize);
                    let len = algo.packed_len(&sa);
                    let packed = table
                        .derive_one(&[&a], "packed as", vec![len], |v| {
                            let mut out = vec![0.0; len];
                            conv::pack_weight(&sa, algo, v[0], &mut out);
                            out
                        })
                        .map_err(internal)?;
                    let name = format!("{a}@{}", algo.name());
                    bind.push(("lora_A", name.clone()));
                    p.tensors.push((name, packed));
                }
                p.rewrite.push((id, new.clone(), rebind(&new, &node.params, &bind)));
                patches.push(p);
            }
            Op::Linear(l) if !l.packed => {
                let (fin, fout) = (l.linear.in_features.max(0) as usize, l.linear.out_features.max(0) as usize);
                let p = if in_panels(g, id, fout) {
                    let len =
                        l.linear.panel_len().ok_or_else(|| internal(format!("linear `{}` too large", node.path)))?;
                    let packed = table
                        .derive_one(&[&weight], "packed as", vec![len], |v| {
                            let mut out = vec![0.0; len];
                            panel::pack(v[0], fin, fout, &mut out);
                            out
                        })
                        .map_err(internal)?;
                    let name = format!("{}.weight@panels", node.path);
                    let new = Op::Linear(LinearOp { packed: true, panels: true, ..l.clone() });
                    let mut p = Patch::new("pack_linear");
                    p.rewrite.push((id, new.clone(), rebind(&new, &node.params, &[("weight", name.clone())])));
                    p.tensors.push((name, packed));
                    p
                } else {
                    let transposed = table
                        .derive_one(&[&weight], "transposed as", vec![fin, fout], |v| {
                            let mut t = vec![0.0f32; fin * fout];
                            for o in 0..fout {
                                for i in 0..fin {
                                    t[i * fout + o] = v[0][o * fin + i];
                                }
                            }
                            t
                        })
                        .map_err(internal)?;
                    let name = format!("{}.weight@t", node.path);
                    let new = Op::Linear(LinearOp { packed: true, ..l.clone() });
                    let mut p = Patch::new("transpose_linear");
                    p.rewrite.push((id, new.clone(), rebind(&new, &node.params, &[("weight", name.clone())])));
                    p.tensors.push((name, transposed));
                    p
                };
                patches.push(p);
            }
            _ => {}
        }
    }
    Ok(Output::Patches(patches))
}

/// Whether rule `pack_linear` packs the weight of linear `id` (of `fout` outputs) in panels.
fn in_panels(g: &Graph, id: NodeId, fout: usize) -> bool {
    few_rows(g, id) && fout.div_ceil(PANEL) * PANEL * 8 <= fout * 9
}

/// The floats the plan stores for the weight of linear `id`: padded panels or `[in, out]`.
pub fn linear_weight_len(g: &Graph, id: NodeId, l: &LinearOp) -> Option<usize> {
    let (fin, fout) = (l.linear.in_features.max(0) as usize, l.linear.out_features.max(0) as usize);
    if in_panels(g, id, fout) { l.linear.panel_len() } else { fin.checked_mul(fout) }
}

/// Rows per image at most which a linear's weight goes in panels. On its own, with the
/// weight in cache, the panel product takes 0.78-0.82x the time of `sgemm` (which packs
/// the weight on every call) at 49 rows (Swin-T's last stage), about 1.0x at 196 and 1.25x
/// at 3136 (`cargo run --release -p readi-runtime --example panel_gemm`, one thread). In
/// a whole model, where each weight comes from memory once a run, panels pay further at
/// batch 1 and lose at batch 8 (`benches/ab.py` and alternating `readi bench --batch 8`
/// rounds, 2026-12-05, against the bound of 64 before; 1 / 2 threads):
///
/// | bound | ViT-B/16, batch 1 | Swin-T, batch 1 | ConvNeXt-T, batch 1 | Swin-T, batch 8 | ConvNeXt-T, batch 8 |
/// | --- | --- | --- | --- | --- | --- |
/// | 256 | 0.936 / 0.936 | 0.983 / 0.969 | 0.986 / 0.967 | 1.015 / 1.015 | 1.037 / 1.025 |
/// | 1024 | | 0.979 / 0.966 | 0.981 / 0.963 | 1.029 / 1.034 | 1.028 / 1.026 |
///
/// 256 takes ViT-B/16's 197 tokens (at batch 8 1.016 at two threads, within noise) and
/// the last two stages of Swin-T and ConvNeXt-T; 4096 (their 3136-row first stage) ran
/// 1.01-1.02x the time of 1024 at batch 1.
const PANEL_ROWS: i64 = 256;

/// Whether the linear `id` multiplies at most [`PANEL_ROWS`] rows per image: the product
/// of its input's axes but the last, a symbolic one (the batch) counted by its factor.
fn few_rows(g: &Graph, id: NodeId) -> bool {
    let Some(t) = g.inputs(id).first().and_then(|v| g.value_type(*v)) else { return false };
    let Some((_, lead)) = t.shape.split_last() else { return false };
    lead.iter().try_fold(1i64, |acc, d| acc.checked_mul(d.coef())).is_some_and(|rows| rows <= PANEL_ROWS)
}

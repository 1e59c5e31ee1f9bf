//! Binding a plan to one set of symbol values: the symbols read from the inputs' shapes,
//! every value's shape, the activation buffers and scratch, and each conv step's
//! parameters at those shapes. Done at a session's first run and whenever a run's symbol
//! values (its batch size) differ from the last binding's.

use std::collections::HashMap;

use crate::kernels::conv::{self, Conv2dShape, ConvAlgo};
use crate::plan::{Kernel, Manifest, Plan, Step, Storage, show_shape};

use super::{Input, RunError, bad};

/// Everything that depends on the bound symbol values.
pub(crate) struct Bound {
    /// The symbol values the buffers were made for, in `manifest.symbols` order.
    pub(super) symbols: Vec<usize>,
    pub(crate) shapes: Vec<Vec<usize>>,
    pub(crate) slots: Vec<Vec<f32>>,
    pub(crate) scratch: Vec<f32>,
    /// Per step, the conv parameters (for conv steps).
    pub(crate) convs: Vec<Option<(Conv2dShape, ConvAlgo)>>,
    /// Zero-filled buffers for absent optional inputs, by input index.
    pub(super) zeros: Vec<Vec<f32>>,
}

/// Binds the symbols from the given inputs' shapes into `symbols` (in `m.symbols` order)
/// and checks every given input; `given` holds, per plan input, the position in `inputs`
/// of the input of that name. Allocates nothing unless it fails.
pub(super) fn bind_symbols(
    m: &Manifest,
    given: &[Option<usize>],
    inputs: &[Input<'_>],
    symbols: &mut [usize],
) -> Result<(), RunError> {
    symbols.fill(0);
    for (spec, g) in m.inputs.iter().zip(given) {
        let Some(inp) = g.map(|pos| &inputs[pos]) else {
            if !spec.optional {
                return Err(RunError::MissingInput { name: spec.name.clone() });
            }
            continue;
        };
        let shape_err = |detail: String| RunError::InputShape {
            name: spec.name.clone(),
            expected: show_shape(&spec.shape),
            got: inp.shape.to_vec(),
            detail,
        };
        if inp.shape.len() != spec.shape.len() {
            return Err(shape_err(format!("{} axes instead of {}", inp.shape.len(), spec.shape.len())));
        }
        let numel = inp.shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d));
        if numel != Some(inp.data.len()) {
            return Err(RunError::InputLength {
                name: spec.name.clone(),
                len: inp.data.len(),
                shape: inp.shape.to_vec(),
            });
        }
        for (axis, (d, &got)) in spec.shape.iter().zip(inp.shape).enumerate() {
            match d.symbols() {
                [] => {
                    if d.coef() as usize != got {
                        return Err(shape_err(format!("axis {axis} must be {}", d.coef())));
                    }
                }
                [s] => {
                    let c = d.coef().max(1) as usize;
                    if got == 0 || got % c != 0 {
                        return Err(shape_err(format!("axis {axis} must be a positive multiple of {c}")));
                    }
                    let v = got / c;
                    // Validation: every symbol of an input's shape is one of the plan's.
                    let Some(k) = m.symbols.iter().position(|x| x == s) else {
                        return Err(bad(&format!("input `{}`", spec.name), format!("unknown symbol `{s}`")));
                    };
                    match symbols[k] {
                        0 => symbols[k] = v,
                        prev if prev != v => {
                            return Err(shape_err(format!("axis {axis} gives {s} = {v}, another input gave {prev}")));
                        }
                        _ => {}
                    }
                }
                _ => {
                    return Err(shape_err(format!("axis {axis} has a product of symbols, which inputs cannot bind")));
                }
            }
        }
    }
    for v in symbols.iter_mut().filter(|v| **v == 0) {
        // Every input that carries this symbol is absent: a batch of one.
        *v = 1;
    }
    Ok(())
}

/// Evaluates shapes, checks the steps, and allocates buffers for one binding of the
/// symbols (values in `manifest.symbols` order).
///
/// The checks read the base's tensors. Every variant's replacement has exactly its base
/// tensor's shape (checked when the plan was built), so they hold under every variant
/// and a switch needs no new check.
pub(super) fn bind(plan: &Plan, symbols: &[usize], threads: usize) -> Result<Bound, RunError> {
    let m = &plan.manifest;
    let base = plan.base_tensors();
    let bindings: HashMap<String, usize> = m.symbols.iter().cloned().zip(symbols.iter().copied()).collect();
    let mut shapes = Vec::with_capacity(m.values.len());
    for (i, v) in m.values.iter().enumerate() {
        let s: Option<Vec<usize>> = v.shape.iter().map(|d| d.eval(&bindings)).collect();
        let s = s.ok_or_else(|| bad(&format!("value {i}"), "a dimension cannot be evaluated"))?;
        if s.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).is_none_or(|n| n > (1usize << 36)) {
            return Err(bad(&format!("value {i}"), format!("shape {s:?} is too large")));
        }
        shapes.push(s);
    }
    let numel = |i: usize| shapes[i].iter().product::<usize>();
    let mut slot_len = vec![0usize; m.slots];
    for (i, v) in m.values.iter().enumerate() {
        match v.storage {
            Storage::Slot(s) => slot_len[s] = slot_len[s].max(numel(i)),
            Storage::Tensor(t) => {
                if base.get(t).len() != numel(i) {
                    return Err(bad(&format!("value {i}"), "stored tensor does not match the value's shape"));
                }
            }
            Storage::Input(_) => {}
        }
    }
    let mut convs = Vec::with_capacity(m.steps.len());
    let mut scratch = 0usize;
    for (k, step) in m.steps.iter().enumerate() {
        let at = format!("step {k} (`{}`)", step.path);
        let conv = conv_params(step, &shapes, &at)?;
        if let Some((s, algo)) = &conv {
            scratch = scratch.max(conv::scratch_len(s, *algo, threads));
        }
        convs.push(conv);
    }
    let zeros =
        m.inputs.iter().map(|spec| if spec.optional { vec![0.0; numel(spec.value)] } else { Vec::new() }).collect();
    Ok(Bound {
        symbols: symbols.to_vec(),
        shapes,
        slots: slot_len.into_iter().map(|n| vec![0.0; n]).collect(),
        scratch: vec![0.0; scratch],
        convs,
        zeros,
    })
}

/// The conv parameters of a conv step at the bound shapes. Every other requirement of a
/// step (its shapes against its operator's rule, its tensors' sizes, the conv's algorithm
/// and packed weight) was checked when the plan was built, on its symbolic shapes, so it
/// holds at every batch size.
fn conv_params(step: &Step, shapes: &[Vec<usize>], at: &str) -> Result<Option<(Conv2dShape, ConvAlgo)>, RunError> {
    let Kernel::Conv2d { conv, algo, .. } = &step.kernel else { return Ok(None) };
    let algo = *algo;
    let x = &shapes[step.inputs[0]];
    let s = conv::layer_shape(conv, x[0], x[2], x[3]);
    if shapes[step.output] != [s.n, s.cout, s.oh, s.ow] {
        return Err(bad(at, "conv2d output shape"));
    }
    Ok(Some((s, algo)))
}

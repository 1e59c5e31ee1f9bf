//! Running the steps of a bound plan: each step's kernel called on its inputs' data,
//! stored tensors resolved under the run's variant, into its output's buffer.

use rayon::prelude::*;

use readi_plan::ops::{ArgKind, Pure};

use crate::kernels::bev_pool;
use crate::kernels::conv;
use crate::kernels::conv_transpose;
use crate::kernels::conv3d;
use crate::kernels::pool::{self, Pool2dShape};
use crate::kernels::resize;
use crate::kernels::sparse;
use crate::kernels::voxel;
use crate::kernels::{Epilogue, elementwise, index, layout, linear, movement, norm, reduce, select, softmax};
use crate::plan::{AdapterSpec, EpilogueSpec, Kernel, LoraSpec, Plan, Step, Storage, VariantTensors};

use super::bind::Bound;
use super::{Input, RunError, bad};

/// What one run reads besides its buffers: the stored tensors under the run's variant
/// and the caller's inputs.
#[derive(Clone, Copy)]
pub(crate) struct Run<'a> {
    pub(crate) plan: &'a Plan,
    pub(super) weights: VariantTensors<'a>,
    pub(super) inputs: &'a [Input<'a>],
    /// Per plan input, the position in `inputs` of the input of that name
    /// (`Session::given`).
    pub(super) given: &'a [Option<usize>],
}

/// The data of a value, stored tensors resolved under the run's variant.
pub(crate) fn value_slice<'a>(run: &Run<'a>, bound: &'a Bound, v: usize) -> &'a [f32] {
    let n: usize = bound.shapes[v].iter().product();
    match run.plan.manifest.values[v].storage {
        Storage::Input(i) => match run.given[i] {
            Some(pos) => run.inputs[pos].data,
            None => &bound.zeros[i],
        },
        Storage::Slot(s) => &bound.slots[s][..n],
        Storage::Tensor(t) => run.weights.get(t),
    }
}

fn epilogue<'a>(w: VariantTensors<'a>, e: &EpilogueSpec) -> Epilogue<'a> {
    Epilogue { scale: e.scale.map(|t| w.get(t)), shift: e.shift.map(|t| w.get(t)), act: e.act }
}

/// A conv step's fused adapter, its tensors resolved under the run's variant.
pub(crate) fn adapter_of<'a>(run: &Run<'a>, a: &AdapterSpec) -> conv::Adapter<'a> {
    conv_adapter(run.weights, a)
}

/// The adapter `a` names, its tensors resolved through `w`.
pub(super) fn conv_adapter<'a>(w: VariantTensors<'a>, a: &AdapterSpec) -> conv::Adapter<'a> {
    conv::Adapter {
        down: w.get(a.down),
        down_bias: w.get(a.down_bias),
        up: w.get(a.up),
        up_bias: w.get(a.up_bias),
        mid: a.mid,
        act: a.act,
    }
}

/// Runs every step in order. Allocates nothing: inputs are fetched by each kernel as
/// it needs them.
pub(super) fn execute(
    run: &Run<'_>,
    bound: &mut Bound,
    threads: usize,
    mut profile: Option<&mut [f64]>,
) -> Result<(), RunError> {
    let m = &run.plan.manifest;
    for (k, step) in m.steps.iter().enumerate() {
        let start = profile.is_some().then(std::time::Instant::now);
        let Storage::Slot(out_slot) = m.values[step.output].storage else {
            return Err(bad(&step.path, "output is not an activation buffer"));
        };
        if step.is_view(&m.values) {
            // Its data are its input's, in place.
            continue;
        }
        // Take the output buffer out so inputs can be borrowed alongside it; `bind`
        // checked that no step but a view reads the slot it writes.
        let mut out_buf = std::mem::take(&mut bound.slots[out_slot]);
        let out_len: usize = bound.shapes[step.output].iter().product();
        let mut scratch = std::mem::take(&mut bound.scratch);
        let result = {
            let b: &Bound = bound;
            let out = &mut out_buf[..out_len];
            run_step(run, b, k, step, out, &mut scratch, threads)
        };
        bound.scratch = scratch;
        bound.slots[out_slot] = out_buf;
        result.map_err(|detail| RunError::Step { step: step.path.clone(), detail })?;
        if let (Some(p), Some(t)) = (profile.as_deref_mut(), start) {
            p[k] += t.elapsed().as_secs_f64();
        }
    }
    Ok(())
}

/// Runs `step`, the `k`-th (or a stand-in for it), its shapes checked at bind time; a
/// raw LoRA `A` is read from `b`'s buffer, packed for the run's variant
/// ([`Bound::pack_lora`]). An `Err` says why the step refused its data (see
/// [`RunError::Step`]); what bind checks never fails here.
pub(crate) fn run_step(
    run: &Run<'_>,
    b: &Bound,
    k: usize,
    step: &Step,
    out: &mut [f32],
    scratch: &mut [f32],
    threads: usize,
) -> Result<(), String> {
    let w = run.weights;
    let conv_params = b.convs[k].as_ref();
    let input = |j: usize| {
        let v = step.inputs[j];
        (value_slice(run, b, v), b.shapes[v].as_slice())
    };
    let out_shape = b.shapes[step.output].as_slice();
    // Every kernel takes at least one input (checked at bind time).
    let (x, xs) = input(0);
    match &step.kernel {
        Kernel::Conv2d { weight, epilogue: ep, lora, switch, adapter, residual, channel_scale, .. } => {
            if let Some((s, algo)) = conv_params {
                let a = |l: &LoraSpec| if l.a_raw { b.lora_a[k].as_slice() } else { w.get(l.a) };
                // Merged on switch: the working copy, `B A` in it (`Bound::pack_lora`).
                // A branch or an adapter the variant does not give is zero: skipped.
                let lora = lora.filter(|l| !switch && !w.reads_zero(l.b)).map(|l| conv::Lora {
                    a: a(&l),
                    b: w.get(l.b),
                    rank: l.rank,
                });
                let wt = if *switch { b.working[k].as_slice() } else { w.get(*weight) };
                let adapter = adapter
                    .as_ref()
                    .filter(|a| !(w.reads_zero(a.up) && w.reads_zero(a.up_bias)))
                    .map(|a| conv_adapter(w, a));
                let e = epilogue(w, ep);
                // Bind checked the arity: a residual conv reads two inputs.
                let res = residual.then(|| input(1).0);
                if *channel_scale {
                    // Bind checked: the scale is the last input, no LoRA branch.
                    let sc = input(step.inputs.len() - 1).0;
                    conv::conv2d_scaled(s, *algo, wt, adapter.as_ref(), &e, x, sc, res, out, scratch, threads);
                } else {
                    conv::conv2d_fused(
                        s,
                        *algo,
                        wt,
                        lora.as_ref(),
                        adapter.as_ref(),
                        &e,
                        x,
                        res,
                        out,
                        scratch,
                        threads,
                    );
                }
            }
        }
        Kernel::ConvTranspose2d { conv: c, weight, epilogue: ep } => {
            let s = c.shape(xs[0], xs[2], xs[3]);
            conv_transpose::conv_transpose2d(&s, w.get(*weight), &epilogue(w, ep), x, out, scratch, threads);
        }
        Kernel::Conv3d { conv: c, weight, epilogue: ep } => {
            let s = c.shape(xs[0], xs[2], xs[3], xs[4]);
            conv3d::conv3d(&s, w.get(*weight), &epilogue(w, ep), x, out, scratch, threads);
        }
        // Rows from the leading axes, not by dividing the length: a last axis may be 0.
        Kernel::Linear { linear: l, weight, epilogue: ep, lora, panels } => {
            let fin = xs.last().copied().unwrap_or(1);
            let rows = xs[..xs.len().saturating_sub(1)].iter().product();
            let layout = if *panels { linear::WeightLayout::Panels } else { linear::WeightLayout::InOut };
            let fout = l.out_features as usize;
            let lora = lora.filter(|r| !w.reads_zero(r.b)).map(|r| linear::Lora {
                a: w.get(r.a),
                b: w.get(r.b),
                rank: r.rank,
            });
            let (wt, e) = (w.get(*weight), epilogue(w, ep));
            linear::linear_lora(x, rows, fin, wt, layout, lora.as_ref(), fout, &e, out, threads);
        }
        Kernel::ChannelAffine { epilogue: ep, .. } => {
            let (n, c) = (xs[0], xs[1]);
            let inner = xs[2..].iter().product();
            let e = epilogue(w, ep);
            norm::channel_affine(x, n, c, inner, e.scale, e.shift, e.act, out);
        }
        Kernel::LayerNorm { norm: ln, weight, bias } => {
            let f = xs.last().copied().unwrap_or(1);
            let rows = xs[..xs.len().saturating_sub(1)].iter().product();
            norm::layernorm(x, rows, f, weight.map(|t| w.get(t)), bias.map(|t| w.get(t)), ln.eps as f32, out);
        }
        Kernel::GroupNorm { norm: gn, weight, bias } => {
            let (n, c, inner) = (xs[0], xs[1], xs[2..].iter().product());
            let (wt, bs) = (weight.map(|t| w.get(t)), bias.map(|t| w.get(t)));
            norm::groupnorm(x, n, c, inner, gn.num_groups as usize, wt, bs, gn.eps as f32, out);
        }
        Kernel::Pure(Pure::LssBevPool(op)) => {
            // The session's geometry for this step, recomputed only when the calibration
            // inputs changed since the last run.
            let Some(cache) = b.bev[k].as_ref() else { return Err("no geometry cache was bound for it".into()) };
            let mut g = cache.lock().unwrap_or_else(|e| e.into_inner());
            g.update(op, [input(2).0, input(3).0, input(4).0, input(5).0])?;
            bev_pool::lss_bev_pool(&g, x, input(1).0, out, threads);
        }
        Kernel::Pure(Pure::Voxelize(op)) => {
            // The session's hash table for this step, sized at bind time.
            let Some(table) = b.voxel[k].as_ref() else { return Err("no hash table was bound for it".into()) };
            let mut t = table.lock().unwrap_or_else(|e| e.into_inner());
            voxel::voxelize(op, voxel::check(op, xs, out_shape)?, x, &mut t, out)?;
        }
        Kernel::Pure(op @ (Pure::SparseConv3d(_) | Pure::SparseOutCoords(_))) => {
            // The session's hash table and rulebook for this step, rebuilt every run.
            let Some(cell) = b.sparse[k].as_ref() else { return Err("no rulebook was bound for it".into()) };
            let mut s = cell.lock().unwrap_or_else(|e| e.into_inner());
            // At most 5 inputs (`check_step`); no list is allocated per run.
            let mut shapes: [&[usize]; 5] = [&[]; 5];
            let n = step.inputs.len().min(5);
            for (j, sh) in shapes.iter_mut().enumerate().take(n) {
                *sh = input(j).1;
            }
            return run_sparse(op, &mut s, &shapes[..n], input, out, out_shape);
        }
        Kernel::Pure(op) => return run_pure(op, step.inputs.len(), input, out, out_shape, threads),
    }
    Ok(())
}

/// Runs the pure operator `op` on `count` inputs (`input(j)`: the data and shape of input
/// `j`) into `out` of shape `out_shape`, its shapes checked ([`check_pure`](super::check_pure)):
/// what every step of a pure kernel calls, and what the compiler folds constants with,
/// so a folded tensor is the value the step would have computed. An `Err` says why the
/// operator refused its inputs' values (an index out of range).
pub fn run_pure<'a>(
    op: &Pure,
    count: usize,
    input: impl Fn(usize) -> (&'a [f32], &'a [usize]),
    out: &mut [f32],
    out_shape: &[usize],
    threads: usize,
) -> Result<(), String> {
    if let Pure::Fill(f) = op {
        index::fill(f.start, f.step, out);
        return Ok(());
    }
    let (x, xs) = input(0);
    match op {
        Pure::MatMul(_) => {
            let (y, ys) = input(1);
            linear::matmul(x, xs, y, ys, out, out_shape, threads);
        }
        Pure::Binary(op) => {
            let (y, ys) = input(1);
            elementwise::binary(*op, x, xs, y, ys, out, out_shape);
        }
        Pure::Scalar(s) => elementwise::scalar(s.op, x, s.value as f32, s.scalar_first, out),
        Pure::Activation(act) => elementwise::activation(*act, x, out),
        Pure::Softmax(s) => {
            let outer: usize = xs[..s.axis].iter().product();
            let inner: usize = xs[s.axis + 1..].iter().product();
            softmax::softmax(x, outer, xs[s.axis], inner, out);
        }
        Pure::Concat(c) => concat(count, &input, c.axis, out, out_shape),
        Pure::Reshape(_) => out.copy_from_slice(x),
        Pure::Permute(p) => layout::permute(x, xs, &p.perm, out),
        Pure::Pool(p) => {
            let s = Pool2dShape::of(p, xs[0] * xs[1], xs[2], xs[3]);
            pool::pool2d(p.kind, &s, x, out);
        }
        Pure::GlobalAvgPool(_) => pool::global_avgpool(x, xs[0] * xs[1], xs[2] * xs[3], out),
        Pure::Upsample(u) => {
            let scale = u.scale.map(|s| (s[0], s[1]));
            let (nc, h, wd) = (xs[0] * xs[1], xs[2], xs[3]);
            resize::upsample(u.mode, u.align_corners, scale, x, nc, h, wd, out, out_shape[2], out_shape[3]);
        }
        Pure::Reduce(r) => reduce::reduce(r.kind, x, xs, &r.axes, out),
        Pure::AdaptivePool(p) => {
            let (oh, ow) = (out_shape[2], out_shape[3]);
            pool::adaptive_pool2d(p.kind, x, xs[0] * xs[1], xs[2], xs[3], oh, ow, out);
        }
        Pure::PixelShuffle(p) => {
            let small = if p.inverse { out_shape } else { xs };
            let r = p.factor as usize;
            resize::pixel_shuffle(p.inverse, r, x, small[0], small[1] / (r * r), small[2], small[3], out);
        }
        Pure::Pad(p) => movement::pad(p, x, xs, out),
        Pure::Roll(r) => movement::roll(r, x, xs, out),
        Pure::Slice(s) => movement::slice(s, x, xs, out),
        Pure::Expand(_) => movement::expand(x, xs, out, out_shape),
        Pure::IndexSelect(s) => index::index_select(x, xs, s.axis, &s.index, out),
        Pure::Where(_) => index::where_select((x, xs), input(1), input(2), out, out_shape),
        Pure::Cast(c) => index::cast(c.to, x, out),
        Pure::Fill(_) => {}
        Pure::LssBevPool(op) => {
            // Outside a session (a folded constant): the geometry computed for this call.
            let shapes: Vec<&[usize]> = (0..count).map(|j| input(j).1).collect();
            let mut g = bev_pool::Geometry::new(bev_pool::check(op, &shapes, out_shape)?);
            g.update(op, [input(2).0, input(3).0, input(4).0, input(5).0])?;
            bev_pool::lss_bev_pool(&g, x, input(1).0, out, threads);
        }
        Pure::ArgReduce(a) => select::arg_reduce(a.kind == ArgKind::Max, x, xs, a.axis, out),
        Pure::TopK(t) => select::topk(x, xs, t.k, t.axis, t.largest, t.indices, out),
        Pure::Gather(g) => return select::gather((x, xs), input(1), g.axis, out, out_shape),
        Pure::IndexSelectAt(s) => return select::index_select_at(x, xs, s.axis, input(1).0, out),
        Pure::OneHot(h) => return select::one_hot(x, h.num_classes, out),
        Pure::SparseConv3d(_) | Pure::SparseOutCoords(_) => {
            // Outside a session (a folded constant): scratch for this call.
            let shapes: Vec<&[usize]> = (0..count).map(|j| input(j).1).collect();
            let mut s = match op {
                Pure::SparseConv3d(c) => sparse::Scratch::conv(&sparse::check_conv(c, &shapes, out_shape)?, threads),
                Pure::SparseOutCoords(c) => {
                    sparse::Scratch::out_coords(&sparse::check_out_coords(c, &shapes, out_shape)?)
                }
                _ => unreachable!("matched above"),
            };
            return run_sparse(op, &mut s, &shapes, input, out, out_shape);
        }
        Pure::SparseToDense(o) => return sparse::sparse_to_dense(o, x, input(1).0, out),
        Pure::WhereScalar(w) => {
            // A number branch is a tensor of shape [], which broadcasts.
            let (a, b) = (w.input.map(|v| [v as f32]), w.other.map(|v| [v as f32]));
            let mut next = 1;
            let mut branch = |v: &Option<[f32; 1]>| match v {
                Some(_) => None,
                None => {
                    next += 1;
                    Some(input(next - 1))
                }
            };
            let (ta, tb) = (branch(&a), branch(&b));
            let none: &[usize] = &[];
            let pa = ta.unwrap_or_else(|| (a.as_ref().map_or(&[][..], |v| &v[..]), none));
            let pb = tb.unwrap_or_else(|| (b.as_ref().map_or(&[][..], |v| &v[..]), none));
            index::where_select((x, xs), pa, pb, out, out_shape);
        }
        Pure::Voxelize(v) => {
            // Outside a session (a folded constant): a table for this call.
            let d = voxel::check(v, xs, out_shape)?;
            return voxel::voxelize(v, d, x, &mut voxel::Table::new(v.max_voxels), out);
        }
        Pure::LidarDepthMap(op) => {
            // On the stack: a session's run allocates nothing.
            let shapes = [0, 1, 2, 3, 4].map(|j| if j < count { input(j).1 } else { &[][..] });
            let dims = voxel::check_depth_map(op, &shapes, out_shape)?;
            let mats = [input(1).0, input(2).0, input(3).0, input(4).0];
            return voxel::lidar_depth_map(op, dims, x, mats, out, threads);
        }
    }
    Ok(())
}

/// A sparse conv or `sparse_out_coords` step with its scratch `s`, sized for these
/// shapes (checked at bind time).
fn run_sparse<'a>(
    op: &Pure,
    s: &mut sparse::Scratch,
    shapes: &[&[usize]],
    input: impl Fn(usize) -> (&'a [f32], &'a [usize]),
    out: &mut [f32],
    out_shape: &[usize],
) -> Result<(), String> {
    match op {
        Pure::SparseConv3d(c) => {
            let d = sparse::check_conv(c, shapes, out_shape)?;
            let bias = c.bias.then(|| input(4).0);
            sparse::sparse_conv3d(&d, s, input(0).0, input(1).0, input(2).0, input(3).0, bias, out)
        }
        Pure::SparseOutCoords(c) => {
            let d = sparse::check_out_coords(c, shapes, out_shape)?;
            sparse::sparse_out_coords(&d, s, input(0).0, out)
        }
        _ => Err(format!("`{}` is not a sparse conv step", op.op().kind_name())),
    }
}

/// Outputs at least this long are copied in parallel.
const CONCAT_PAR_MIN: usize = 1 << 15;
/// Elements per parallel task.
const CONCAT_CHUNK: usize = 1 << 14;

/// Concatenation along `axis` of `count` inputs given by `part`, each copied into its
/// place in turn, so no list of inputs is built (the result is
/// [`layout::concat`]'s). Shapes were checked at bind time.
fn concat<'a>(
    count: usize,
    part: impl Fn(usize) -> (&'a [f32], &'a [usize]),
    axis: usize,
    out: &mut [f32],
    out_shape: &[usize],
) {
    let inner: usize = out_shape[axis + 1..].iter().product();
    let row = out_shape[axis] * inner;
    if row == 0 || out.is_empty() {
        return;
    }
    let outer = out.len() / row;
    let mut at = 0;
    for j in 0..count {
        let (d, s) = part(j);
        let n = s[axis] * inner;
        if n == 0 {
            continue;
        }
        let copy = |dst: &mut [f32], src: &[f32]| dst[at..at + n].copy_from_slice(src);
        if out.len() < CONCAT_PAR_MIN {
            out.chunks_mut(row).zip(d.chunks(n)).for_each(|(dst, src)| copy(dst, src));
        } else if outer > 1 {
            let min_rows = (CONCAT_CHUNK / row).max(1);
            out.par_chunks_mut(row).zip(d.par_chunks(n)).with_min_len(min_rows).for_each(|(dst, src)| copy(dst, src));
        } else {
            // One block per input: split the copy instead.
            out[at..at + n]
                .par_chunks_mut(CONCAT_CHUNK)
                .zip(d.par_chunks(CONCAT_CHUNK))
                .for_each(|(dst, src)| dst.copy_from_slice(src));
        }
        at += n;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn concat_by_parts_matches_the_kernel() {
        use crate::testdata::data;
        // (shapes of the parts, axis): small, empty parts, one big block per part and
        // many rows (both parallel paths).
        let cases: [(&[&[usize]], usize); 5] = [
            (&[&[2, 3, 4], &[2, 1, 4], &[2, 2, 4]], 1),
            (&[&[2, 0, 4], &[2, 3, 4], &[2, 0, 4]], 1),
            (&[&[3, 5], &[4, 5]], 0),
            (&[&[1, 40_000], &[1, 30_000]], 1),
            (&[&[600, 40, 2], &[600, 7, 2], &[600, 1, 2]], 1),
        ];
        for (k, (shapes, axis)) in cases.into_iter().enumerate() {
            let datas: Vec<Vec<f32>> =
                shapes.iter().enumerate().map(|(i, s)| data(s.iter().product(), (10 * k + i) as u64)).collect();
            let parts: Vec<(&[f32], &[usize])> = datas.iter().map(Vec::as_slice).zip(shapes.iter().copied()).collect();
            let mut out_shape = shapes[0].to_vec();
            out_shape[axis] = shapes.iter().map(|s| s[axis]).sum();
            let len = out_shape.iter().product();
            let mut want = vec![f32::NAN; len];
            layout::concat(&parts, axis, &mut want);
            let mut got = vec![f32::NAN; len];
            concat(parts.len(), |j| parts[j], axis, &mut got, &out_shape);
            assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "case {k}");
        }
    }
}

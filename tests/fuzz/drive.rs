//! Driving the back end: compiling specs with seeded weights and running their plans
//! through every execution path.

use super::*;

/// The inputs of a run: name, shape, data.
pub(super) type Data = Vec<(String, Vec<usize>, Vec<f32>)>;

/// Seeded finite inputs in [-1, 1) for every input of the plan, at batch size 1, a
/// function of the seed and each input's name.
pub(super) fn seeded_inputs(plan: &Plan, seed: u64) -> Data {
    plan.manifest
        .input_shapes(1)
        .into_iter()
        .map(|(name, shape)| {
            let n: usize = shape.iter().product();
            let data = (0..n as u64).map(|k| unit(seed ^ fnv1a64(name) ^ k)).collect();
            (name.to_string(), shape, data)
        })
        .collect()
}

/// FNV-1a: inputs are seeded by name, so that an input gets the same values in every
/// plan that has it.
pub(super) fn fnv1a64(s: &str) -> u64 {
    s.bytes().fold(0xcbf2_9ce4_8422_2325, |h, b| (h ^ b as u64).wrapping_mul(0x0000_0100_0000_01b3))
}

/// SplitMix64 of `x`, as a float uniform in [-1, 1).
pub(super) fn unit(x: u64) -> f32 {
    let mut z = x.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^= z >> 31;
    ((z >> 40) as f32 / (1u64 << 24) as f32) * 2.0 - 1.0
}

/// Runs under variant `key`, with the inputs not in `absent`.
pub(super) fn run_as(
    s: &mut Session,
    key: &str,
    data: &Data,
    absent: Option<usize>,
    src: &str,
) -> Vec<(String, Tensor)> {
    s.set_variant(key).unwrap_or_else(|e| panic!("variant `{key}` of the plan: {e}\n--- source ---\n{src}"));
    let given: Vec<Input<'_>> = data
        .iter()
        .enumerate()
        .filter(|(i, _)| Some(*i) != absent)
        .map(|(_, (name, shape, data))| Input { name, data, shape })
        .collect();
    s.run(&given).unwrap_or_else(|e| {
        panic!("a compiled plan fails to run (variant `{key}`, {} threads): {e}\n--- source ---\n{src}", s.threads())
    })
}

pub(super) fn bits(outs: &[(String, Tensor)]) -> Vec<(&str, &[usize], Vec<u32>)> {
    outs.iter().map(|(n, t)| (n.as_str(), &t.shape[..], t.data.iter().map(|v| v.to_bits()).collect())).collect()
}

pub(super) fn assert_bit_identical(a: &[(String, Tensor)], b: &[(String, Tensor)], what: &str, src: &str) {
    if bits(a) != bits(b) {
        let names: Vec<&str> = a.iter().zip(b).filter(|(x, y)| x != y).map(|(x, _)| x.0.as_str()).collect();
        panic!("{what}: outputs {names:?} are not bit-identical\n--- source ---\n{src}");
    }
}

/// Why two computations of one value differ by more than rounding, if they do: the
/// largest difference must be at most `1e-4 * max(m, 1)`, where `m` is the value's
/// largest magnitude.
///
/// Relative to `m` for values of magnitude 1 or more; absolute below, because rounding
/// noise can make up a small value. A `layernorm` over a row whose values are equal up to
/// rounding (after `upsample` from width 1, say) divides the noise by `sqrt(eps)`,
/// amplifying a 1-ulp difference in its input ~316 times, and its output is then only its
/// bias plus that noise: a 2e-5 difference on an output of magnitude 0.1 is rounding
/// there. A wrong result (a lost partial sum, a misplaced tile) differs by about the
/// values themselves.
pub(super) fn differs(x: &[f32], y: &[f32]) -> Option<String> {
    let scale = x.iter().fold(0.0f32, |m, v| m.max(v.abs()));
    let err = x.iter().zip(y).fold(0.0f32, |m, (p, q)| m.max((p - q).abs()));
    (err > 1e-4 * scale.max(1.0)).then(|| format!("differs by {err:e} (largest magnitude {scale:e})"))
}

/// The same outputs, equal up to rounding ([`differs`]): thread counts change the order
/// of floating-point sums, nothing else.
pub(super) fn assert_close(a: &[(String, Tensor)], b: &[(String, Tensor)], what: &str, src: &str) {
    assert_eq!(a.len(), b.len(), "{what}: output count\n--- source ---\n{src}");
    for ((name, x), (_, y)) in a.iter().zip(b) {
        assert_eq!(x.shape, y.shape, "{what}: shape of `{name}`\n--- source ---\n{src}");
        if let Some(why) = differs(&x.data, &y.data) {
            panic!("{what}: `{name}` {why}\n--- source ---\n{src}");
        }
    }
}

pub(super) fn finite(outs: &[(String, Tensor)]) -> bool {
    outs.iter().all(|(_, t)| t.data.iter().all(|v| v.is_finite()))
}

/// A plan written with `to_bytes`, stored in a temporary file and loaded (memory-mapped).
pub(super) fn reload(plan: &Plan, src: &str) -> Plan {
    static COUNT: AtomicUsize = AtomicUsize::new(0);
    let bytes = plan.to_bytes().unwrap_or_else(|e| panic!("serialise: {e}\n--- source ---\n{src}"));
    let n = COUNT.fetch_add(1, Ordering::Relaxed);
    let path = std::env::temp_dir().join(format!("readi-fuzz-{}-{n}.plan", std::process::id()));
    std::fs::write(&path, bytes).expect("write the plan");
    let loaded = Plan::load(&path);
    // The mapping outlives the file's name.
    let _ = std::fs::remove_file(&path);
    loaded.unwrap_or_else(|e| panic!("a written plan does not load: {e}\n--- source ---\n{src}"))
}

/// Checks and compiles a spec with seeded weights, and seeded parameters for up to three
/// of its variants when it has an `adapt` section (without one, variant files are a user
/// error). Fails on an internal error or a panic; a user error, or a spec too large to run
/// in a few milliseconds, is `Err` with the reason and the rendered diagnostics.
pub(super) fn compile_spec(src: &str, seed: u64) -> Result<Plan, String> {
    let (sources, out) = exercise(src);
    let context =
        |why: &str, d: &Diagnostics| format!("{why}:\n{}\n--- source ---\n{src}", sources.render_all(d, false));
    if out.diagnostics.has_errors() {
        return Err(context("does not check", &out.diagnostics));
    }
    let module: Module = out.module.expect("a module without errors");
    let params: u64 = module.graph.param_table().iter().map(|(_, _, s)| s.numel()).sum();
    if params > MAX_ELEMENTS {
        return Err(format!("has {params} parameters"));
    }
    let weights = backend::seeded_weights(&module.graph, seed);
    let keys = if module.adapt.is_some() { variant_keys(&module, 3) } else { vec![] };
    let variants = backend::seeded_variants(&module, &keys, seed + 1);
    let plan = match backend::compile_variants(&module, &weights, "seeded", &variants, &CompileOptions::default()) {
        Ok((plan, warnings)) => {
            assert_no_ice(&warnings, &sources, "the back end", src);
            plan
        }
        Err(diags) => {
            assert_no_ice(&diags, &sources, "the back end", src);
            return Err(context("does not compile", &diags));
        }
    };
    let b = plan.manifest.batch_bindings(1);
    let elements: u64 = plan
        .manifest
        .values
        .iter()
        .map(|v| v.shape.iter().map(|d| d.eval(&b).unwrap_or(1) as u64).product::<u64>())
        .sum();
    if elements > MAX_ELEMENTS {
        return Err(format!("has {elements} activation elements"));
    }
    Ok(plan)
}

/// What [`drive_backend`] did with a case.
#[derive(Debug, PartialEq)]
pub(super) enum Outcome {
    Ran,
    Skipped(&'static str),
}

/// Most parameters and activation elements a case may have, so that an edit that makes a
/// layer wide (`conv2d(x, 1616, ...)`) does not make a case take seconds.
pub(super) const MAX_ELEMENTS: u64 = 1 << 20;

/// Compiles a spec with seeded weights (and seeded parameters for up to three of its
/// variants), and runs the plan on seeded inputs on every path, for the base and every
/// variant:
///
/// * in memory on 1 thread, and written, reloaded and run on 1 thread: bit-identical;
/// * the same on 2 threads: bit-identical; 1, 2 and 3 threads agree within
///   [`assert_close`];
/// * a second run of a session reproduces its first bit for bit (buffers are reused), and
///   switching back to the base after every variant reproduces the first base run;
/// * an absent `optional` input is the same as zeros;
/// * every output is finite.
///
/// `strict` (generated models): the spec must check and compile. Otherwise a spec with
/// user errors, from the front end or the back end, is skipped. An internal error, a
/// panic, or a compiled plan that fails to load or run fails in both cases.
pub(super) fn drive_backend(src: &str, strict: bool, seed: u64) -> Outcome {
    let plan = match compile_spec(src, seed) {
        Ok(plan) => plan,
        Err(why) => {
            assert!(!strict, "a generated model {why}");
            return Outcome::Skipped("user error");
        }
    };
    let data = seeded_inputs(&plan, seed);
    let keys: Vec<String> = plan.variant_keys().map(str::to_string).collect();
    let mem = Arc::new(plan);
    let loaded = Arc::new(reload(&mem, src));
    let session = |p: &Arc<Plan>, threads| {
        Session::new(Arc::clone(p), threads).unwrap_or_else(|e| panic!("session: {e}\n--- source ---\n{src}"))
    };
    let (mut mem1, mut mem2, mut load1, mut load2) =
        (session(&mem, 1), session(&mem, 2), session(&loaded, 1), session(&loaded, 2));
    // More threads than this machine may have cores, and an uneven split of the work.
    let mut mem3 = session(&mem, 3);
    let mut first_base = None;
    for key in &keys {
        let a1 = run_as(&mut mem1, key, &data, None, src);
        let b1 = run_as(&mut load1, key, &data, None, src);
        let a2 = run_as(&mut mem2, key, &data, None, src);
        let b2 = run_as(&mut load2, key, &data, None, src);
        assert_bit_identical(&a1, &b1, &format!("variant `{key}`, 1 thread: in memory vs reloaded"), src);
        assert_bit_identical(&a2, &b2, &format!("variant `{key}`, 2 threads: in memory vs reloaded"), src);
        let again = run_as(&mut mem1, key, &data, None, src);
        assert_bit_identical(&a1, &again, &format!("variant `{key}`: a second run of one session"), src);
        if !finite(&a1) || !finite(&a2) {
            // Inputs are finite and weights are seeded in PyTorch's init ranges, so a
            // non-finite output from a generated model is a bug. An edited spec can
            // overflow legitimately (`a / (a + 2.0)` in `all_ops` with the 2.0 edited to
            // 0 divides by zero where `a` is 0): such a case says nothing about the
            // paths and is skipped, rather than comparing non-finite values loosely.
            assert!(!strict, "variant `{key}`: an output is not finite\n--- source ---\n{src}");
            return Outcome::Skipped("non-finite output");
        }
        assert_close(&a1, &a2, &format!("variant `{key}`: 1 vs 2 threads"), src);
        let a3 = run_as(&mut mem3, key, &data, None, src);
        assert_close(&a1, &a3, &format!("variant `{key}`: 1 vs 3 threads"), src);
        first_base.get_or_insert(a1);
    }
    let first_base = first_base.expect("the base variant");
    let base = &keys[0];
    let back = run_as(&mut mem1, base, &data, None, src);
    assert_bit_identical(&first_base, &back, "back to the base after every variant", src);
    for (i, spec) in mem.manifest.inputs.iter().enumerate() {
        if spec.optional {
            let absent = run_as(&mut mem1, base, &data, Some(i), src);
            let mut zeros = data.clone();
            zeros[i].2.fill(0.0);
            let given = run_as(&mut mem1, base, &zeros, None, src);
            assert_bit_identical(&absent, &given, &format!("optional input `{}` absent vs zeros", spec.name), src);
        }
    }
    Outcome::Ran
}

/// The base variant's outputs by name, on 1 thread, for seeded inputs; all finite.
pub(super) fn run_base(src: &str, seed: u64) -> HashMap<String, Tensor> {
    let plan = compile_spec(src, seed).unwrap_or_else(|why| panic!("a generated model {why}"));
    let data = seeded_inputs(&plan, seed);
    let out = run_as(&mut Session::new(Arc::new(plan), 1).expect("session"), "base", &data, None, src);
    assert!(finite(&out), "an output is not finite\n--- source ---\n{src}");
    out.into_iter().collect()
}

/// Output `a` of spec `sa` and output `b` of spec `sb` are one value, computed by plans
/// that fuse differently (so round differently): equal up to rounding ([`differs`]).
pub(super) fn assert_same_value(a: (&str, &HashMap<String, Tensor>, &str), b: (&str, &HashMap<String, Tensor>, &str)) {
    let (x, y) = (&a.1[a.0], &b.1[b.0]);
    let srcs = format!("--- source ---\n{}\n--- and ---\n{}", a.2, b.2);
    assert_eq!(x.shape, y.shape, "the shapes of `{}` and `{}`\n{srcs}", a.0, b.0);
    if let Some(why) = differs(&x.data, &y.data) {
        panic!("`{}` and `{}`: {why}\n{srcs}", a.0, b.0);
    }
}

/// A value does not depend on what else the model computes: for a generated model,
/// * every output is the same when every trunk value is an output too (fusing a layer
///   into its consumer must not change what another consumer sees);
/// * trunk value `l<k>` is the output of the model cut after layer `k`;
/// * the base of a spec with `adapt` and `variants` sections is the spec without them
///   (LoRA branches and adapters are zero in the base, wherever they were moved);
/// * a batch of two is two batches of one (no op of the generator mixes batch items, and
///   every input and output has the batch axis first).
pub(super) fn check_independence(g: &GenSpec, seed: u64) {
    let src = generate(g);
    check_batch(&src, seed);
    let full = run_base(&src, seed);
    let all_src = generate_with(g, true);
    let all = run_base(&all_src, seed);
    for name in full.keys() {
        assert_same_value((name, &full, &src), (name, &all, &all_src));
    }
    let plain_src = generate(&GenSpec { sections: 0, ..g.clone() });
    if plain_src != src {
        let plain = run_base(&plain_src, seed);
        for name in full.keys() {
            assert_same_value((name, &full, &src), (name, &plain, &plain_src));
        }
    }
    for k in 0..g.steps.len() {
        let cut_src = generate(&GenSpec { steps: g.steps[..=k].to_vec(), head: 0, sections: 0, input: g.input });
        let cut = run_base(&cut_src, seed);
        assert_same_value(("features", &cut, &cut_src), (&format!("v_l{k}"), &all, &all_src));
    }
}

/// Runs a generated model on input batches `a`, `[a, b]` and `b`, on one session (which
/// rebinds its buffers at each change of batch size): the batch of two holds the two
/// batches of one.
pub(super) fn check_batch(src: &str, seed: u64) {
    let plan = compile_spec(src, seed).unwrap_or_else(|why| panic!("a generated model {why}"));
    let (a, b) = (seeded_inputs(&plan, seed), seeded_inputs(&plan, seed + 1));
    let two: Data = a
        .iter()
        .zip(&b)
        .map(|((name, shape, x), (_, _, y))| {
            let mut shape = shape.clone();
            shape[0] *= 2;
            (name.clone(), shape, [&x[..], &y[..]].concat())
        })
        .collect();
    let mut s = Session::new(Arc::new(plan), 2).expect("session");
    let one_a = run_as(&mut s, "base", &a, None, src);
    let both = run_as(&mut s, "base", &two, None, src);
    let one_b = run_as(&mut s, "base", &b, None, src);
    for (((name, x), (_, y)), (_, xy)) in one_a.iter().zip(&one_b).zip(&both) {
        let mut shape = x.shape.clone();
        shape[0] *= 2;
        assert_eq!(xy.shape, shape, "the shape of `{name}` at batch size 2\n--- source ---\n{src}");
        let (first, second) = xy.data.split_at(x.data.len());
        let halves = |d: &[f32]| vec![(name.clone(), Tensor { shape: x.shape.clone(), data: d.to_vec() })];
        let what = format!("`{name}`: batch of two vs one");
        assert_close(&halves(&x.data), &halves(first), &what, src);
        assert_close(&halves(&y.data), &halves(second), &what, src);
    }
}

/// The keys of the variants a spec declares, at most `n`.
pub(super) fn variant_keys(m: &Module, n: usize) -> Vec<String> {
    m.variants.as_ref().map(|v| v.keys()).unwrap_or_default().iter().take(n).map(|k| k.to_string()).collect()
}

/// Compiles a bundled spec with seeded variants; runs the base and every variant on one
/// session, then the first variant and the base again: each second visit reproduces the
/// first bit for bit, and every variant differs from the base.
pub(super) fn check_switching(rel: &str, variants: usize, seed: u64) {
    let src = std::fs::read_to_string(common::root().join(rel)).expect("read the spec");
    let (sources, out) = common::compile_text(rel, &src, &[], None);
    assert!(!out.diagnostics.has_errors(), "{}", sources.render_all(&out.diagnostics, false));
    let m = out.module.expect("module");
    let keys = variant_keys(&m, variants);
    assert_eq!(keys.len(), variants, "{rel} declares enough variants");
    let sources_v = backend::seeded_variants(&m, &keys, seed + 1);
    let weights = backend::seeded_weights(&m.graph, seed);
    let (plan, _) = backend::compile_variants(&m, &weights, "seeded", &sources_v, &CompileOptions::default())
        .unwrap_or_else(|d| panic!("{rel}: {}", sources.render_all(&d, false)));
    let data = seeded_inputs(&plan, seed);
    let mut s = Session::new(Arc::new(plan), 2).expect("session");
    let order: Vec<&str> = std::iter::once("base").chain(keys.iter().map(String::as_str)).collect();
    let first: Vec<_> = order.iter().map(|k| run_as(&mut s, k, &data, None, &src)).collect();
    for (k, out) in order.iter().zip(&first).skip(1) {
        assert_ne!(bits(out), bits(&first[0]), "{rel}: variant `{k}` equals the base");
    }
    for (k, want) in [(order[1], &first[1]), ("base", &first[0])] {
        let again = run_as(&mut s, k, &data, None, &src);
        assert_bit_identical(want, &again, &format!("{rel}: switching back to `{k}`"), &src);
    }
}

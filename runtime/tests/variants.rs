//! Variants: each runs with its own tensors (checked against naive references computed
//! here from the weights), switching is exact and reversible, a run sees one variant while
//! another thread switches, variants survive a file round trip, and bad variant tables or
//! keys are refused with errors naming them (the other plan checks: `plan_checks.rs`).

mod common;

use std::collections::HashMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use readi_plan::VariantKey;
use readi_runtime::exec::{RunError, Session, VariantSwitch};
use readi_runtime::plan::{BASE_VARIANT, FORMAT_VERSION, Plan, PlanError, Replacement, VariantTable};
use readi_runtime::testdata::data;

use common::*;

// ---------------------------------------------------------------------------------------
// (a) Each variant computes with its own tensors
// ---------------------------------------------------------------------------------------

#[test]
fn each_mlp_variant_matches_a_reference_from_its_weights() {
    let m = mlp(24, 16);
    let plan = Arc::new(m.plan);
    assert_eq!(plan.variant_count(), 4);
    let x = data(3 * m.fin, 7);
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    assert_eq!(s.variant(), BASE_VARIANT);
    let mut outputs = Vec::new();
    for key in [BASE_VARIANT, "fog=1", "fog=2", "fog=3"] {
        s.set_variant(key).expect("known key");
        assert_eq!(s.variant(), key);
        let y = run(&mut s, &x, &[3, m.fin]);
        assert_eq!(s.last_variant().map(|i| plan.variant_key(i)), Some(key));
        assert_close(&y, &mlp_reference(&x, m.fin, m.fout, &m.weights[key]), key);
        outputs.push(y);
    }
    // The variants really differ (so the reference comparison above distinguishes them).
    for i in 0..outputs.len() {
        for j in i + 1..outputs.len() {
            assert_ne!(outputs[i], outputs[j], "variants {i} and {j}");
        }
    }
}

#[test]
fn each_conv_variant_matches_a_reference_from_its_weights() {
    let p = conv_plan(3, 5, 7);
    let x = data(2 * p.cin * p.hw * p.hw, 8);
    let shape = [2, p.cin, p.hw, p.hw];
    let plan = Arc::new(conv_plan(3, 5, 7).plan);
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    for key in [BASE_VARIANT, "fog=0.05", "gamma=2"] {
        s.set_variant(key).expect("known key");
        let y = run(&mut s, &x, &shape);
        assert_close(&y, &conv_reference(&x, &p, &p.weights[key]), key);
    }
}

#[test]
fn variant_lookups_agree_with_the_manifest() {
    let plan = mlp(4, 4).plan;
    assert_eq!(plan.variant_index(BASE_VARIANT), Some(0));
    for (i, v) in plan.manifest.variants.iter().enumerate() {
        assert_eq!(plan.variant_index(&v.key.to_string()), Some(i + 1));
        assert_eq!(plan.variant_key(i + 1), v.key.to_string());
        let t = plan.variant_tensors(i + 1).expect("variant");
        for r in &v.replaces {
            assert_eq!(t.resolve(r.base), r.with);
        }
    }
    assert_eq!(plan.variant_index("a"), None);
    assert!(plan.variant_tensors(plan.variant_count()).is_none());
    assert_eq!(plan.variant_keys().collect::<Vec<_>>(), [BASE_VARIANT, "fog=1", "fog=2", "fog=3"]);
    // Tensors no variant replaces resolve to themselves.
    let b = plan.variant_tensors(2).expect("fog=2");
    assert_eq!(b.resolve(2), 2);
    assert_eq!(b.resolve(5), 5, "A's replacement, not named by a step");
}

// ---------------------------------------------------------------------------------------
// (b) Switching is exact and reversible
// ---------------------------------------------------------------------------------------

#[test]
fn switching_a_b_a_is_bit_identical_to_a_fresh_session() {
    let m = mlp(64, 32);
    let plan = Arc::new(m.plan);
    let x = data(5 * m.fin, 9);
    let shape = [5, m.fin];
    let a = fresh(&plan, "fog=1", 2, &x, &shape);
    let b = fresh(&plan, "fog=2", 2, &x, &shape);
    let base = fresh(&plan, BASE_VARIANT, 2, &x, &shape);
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    let handle = s.switch_handle();
    assert_eq!(run(&mut s, &x, &shape), base);
    for (key, want) in
        [("fog=1", &a), ("fog=2", &b), ("fog=1", &a), (BASE_VARIANT, &base), ("fog=2", &b), ("fog=1", &a)]
    {
        handle.set(key).expect("known key");
        assert_eq!(handle.key(), key);
        assert_eq!(&run(&mut s, &x, &shape), want, "after switching to {key}");
    }
    // By index too.
    handle.set_index(2).expect("in range");
    assert_eq!(s.variant(), "fog=2");
    assert_eq!(run(&mut s, &x, &shape), b);
}

#[test]
fn switching_copies_no_weights() {
    let m = mlp(8, 8);
    let plan = Arc::new(m.plan);
    let before: Vec<Vec<f32>> = (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).to_vec()).collect();
    let ptrs: Vec<*const f32> = (0..plan.manifest.tensors.len()).map(|i| plan.tensor(i).as_ptr()).collect();
    let mut s = Session::new(Arc::clone(&plan), 1).expect("session");
    let x = data(2 * m.fin, 3);
    for key in ["fog=1", "fog=2", "fog=3", BASE_VARIANT] {
        s.set_variant(key).expect("known key");
        run(&mut s, &x, &[2, m.fin]);
    }
    for i in 0..before.len() {
        assert_eq!(plan.tensor(i), before[i], "tensor {i} changed");
        assert_eq!(plan.tensor(i).as_ptr(), ptrs[i], "tensor {i} moved");
    }
    // A variant reads the stored replacement in place.
    let a = plan.variant_tensors(1).expect("fog=1");
    assert_eq!(a.get(0).as_ptr(), plan.tensor(5).as_ptr());
}

// ---------------------------------------------------------------------------------------
// (c) A run sees exactly one variant while another thread switches
// ---------------------------------------------------------------------------------------

#[test]
fn a_run_sees_one_variant_while_another_thread_switches() {
    // Large enough that a run spans many switches.
    let m = mlp(256, 256);
    let plan = Arc::new(m.plan);
    let rows = 32;
    let x = data(rows * m.fin, 10);
    let shape = [rows, m.fin];
    let threads = 2;
    let a = fresh(&plan, "fog=1", threads, &x, &shape);
    let b = fresh(&plan, "fog=2", threads, &x, &shape);
    // A and B differ in every element, and a run mixing their steps would match neither.
    assert!(a.iter().zip(&b).all(|(p, q)| p != q));
    let (ia, ib) = (plan.variant_index("fog=1").expect("fog=1"), plan.variant_index("fog=2").expect("fog=2"));

    let mut s = Session::new(Arc::clone(&plan), threads).expect("session");
    let handle: VariantSwitch = s.switch_handle();
    handle.set("fog=1").expect("fog=1");
    let stop = Arc::new(AtomicBool::new(false));
    let started = Arc::new(AtomicBool::new(false));
    let switcher = {
        let (handle, stop, started) = (handle.clone(), Arc::clone(&stop), Arc::clone(&started));
        std::thread::spawn(move || {
            let mut switches = 0u64;
            started.store(true, Ordering::Relaxed);
            while !stop.load(Ordering::Relaxed) {
                handle.set("fog=1").expect("fog=1");
                handle.set("fog=2").expect("fog=2");
                switches += 2;
            }
            switches
        })
    };
    while !started.load(Ordering::Relaxed) {
        std::thread::yield_now();
    }
    // At least 400 runs, and on until both variants were seen (a loaded machine may
    // schedule the switcher rarely).
    let (mut seen_a, mut seen_b) = (0, 0);
    let mut i = 0;
    while i < 400 || ((seen_a == 0 || seen_b == 0) && i < 20_000) {
        i += 1;
        let y = run(&mut s, &x, &shape);
        let used = s.last_variant().expect("ran");
        if y == a {
            assert_eq!(used, ia, "run {i}: A's output, but the session reports variant {used}");
            seen_a += 1;
        } else if y == b {
            assert_eq!(used, ib, "run {i}: B's output, but the session reports variant {used}");
            seen_b += 1;
        } else {
            let off_a = y.iter().zip(&a).filter(|(p, q)| p != q).count();
            let off_b = y.iter().zip(&b).filter(|(p, q)| p != q).count();
            panic!("run {i} matches neither variant ({off_a} elements differ from A, {off_b} from B)");
        }
    }
    stop.store(true, Ordering::Relaxed);
    let switches = switcher.join().expect("switcher");
    assert!(switches > 2, "only {switches} switches happened during the runs");
    assert!(seen_a > 0 && seen_b > 0, "runs saw A {seen_a} times and B {seen_b} times");
}

#[test]
fn the_switch_handle_is_send_sync_and_clone() {
    fn check<T: Send + Sync + Clone + 'static>() {}
    check::<VariantSwitch>();
}

// ---------------------------------------------------------------------------------------
// (d) File round trip
// ---------------------------------------------------------------------------------------

#[test]
fn variants_survive_a_write_and_load() {
    let m = mlp(32, 16);
    let dir = Scratch::new("variants");
    let path = dir.join("mlp.plan");
    m.plan.write(&path).expect("writes");
    let loaded = Arc::new(Plan::load(&path).expect("loads"));
    assert!(loaded.is_mapped());
    assert_eq!(loaded.manifest.variants, m.plan.manifest.variants);
    let owned = Arc::new(m.plan);
    let x = data(4 * m.fin, 12);
    let shape = [4, m.fin];
    let mut s = Session::new(Arc::clone(&loaded), 2).expect("session");
    for key in ["fog=2", BASE_VARIANT, "fog=1", "fog=3"] {
        s.set_variant(key).expect("known key");
        let y = run(&mut s, &x, &shape);
        assert_eq!(y, fresh(&owned, key, 2, &x, &shape), "{key}: loaded and compiled plans differ");
        assert_close(&y, &mlp_reference(&x, m.fin, m.fout, &m.weights[key]), key);
    }
}

#[test]
fn bad_variant_tables_are_refused_with_the_key() {
    type Edit = Box<dyn FnOnce(&mut Vec<VariantTable>)>;
    let cases: Vec<(&str, Edit, &[&str])> = vec![
        ("replacement out of range", Box::new(|v| v[0].replaces[0].with = 99), &["variant `fog=1`", "tensor 99"]),
        ("base out of range", Box::new(|v| v[1].replaces[1].base = 1000), &["variant `fog=2`", "tensor 1000"]),
        (
            "shape mismatch",
            // W ([4, 3]) replaced with B's bias ([3]).
            Box::new(|v| v[0].replaces[0].with = 9),
            &["variant `fog=1`", "`fc.weight@t`", "[4, 3]", "`fc.bias~B`", "[3]"],
        ),
        (
            "same numel, different shape",
            // p ([1, 3]) replaced with gamma ([3]).
            Box::new(|v| v[0].replaces[2].with = 2),
            &["variant `fog=1`", "`p`", "[1, 3]", "`ln.weight`", "shape [3]", "must have its base"],
        ),
        ("duplicate key", Box::new(|v| v[2].key = key("fog=1")), &["variant `fog=1`", "two variants"]),
        ("reserved key", Box::new(|v| v[1].key = VariantKey::base()), &["variant `base`", "reserved"]),
        (
            "replaced twice",
            Box::new(|v| v[2].replaces.push(Replacement { base: 0, with: 8, added: true })),
            &["variant `fog=3`", "tensor 0 (`fc.weight@t`) twice"],
        ),
        (
            "base not read",
            // A's own replacement W is no step's tensor.
            Box::new(|v| v[1].replaces[0].base = 5),
            &["variant `fog=2`", "tensor 5 (`fc.weight@t~A`)", "no step reads"],
        ),
    ];
    for (what, edit, wanted) in cases {
        let msg = refused(edit);
        for w in wanted {
            assert!(msg.contains(w), "{what}: `{msg}` does not mention `{w}`");
        }
        assert!(msg.contains("<compiled plan>: invalid plan manifest"), "{what}: {msg}");
    }
}

#[test]
fn a_stored_value_may_be_replaced() {
    // p is read as a value (Storage::Tensor), not by a kernel: replacing it is valid.
    let (m, tensors) = edited(|v| v.truncate(0));
    let p = m.tensors.iter().position(|t| t.name == "p").expect("p");
    let p_a = m.tensors.iter().position(|t| t.name == "p~A").expect("p~A");
    let mut m = m;
    m.variants.push(table("snow=1", &[(p, p_a)]));
    let plan = Plan::new(m, tensors).expect("valid");
    assert_eq!(plan.variant_tensors(1).expect("snow=1").resolve(p), p_a);
}

#[test]
fn a_plan_file_with_a_bad_variant_table_is_refused_at_load() {
    let (mut m, tensors) = edited(|_| {});
    m.variants[1].key = key("fog=1");
    // Write the file by hand (Plan::write needs a valid plan), checksum included.
    let json = serde_json::to_string(&m).expect("json");
    let mut crc = crc32fast::Hasher::new();
    crc.update(json.as_bytes());
    let bytes: Vec<Vec<u8>> = tensors.iter().map(|t| t.iter().flat_map(|v| v.to_le_bytes()).collect()).collect();
    for b in &bytes {
        crc.update(b);
    }
    let views = m.tensors.iter().zip(&bytes).map(|(spec, b)| {
        let view = safetensors::tensor::TensorView::new(safetensors::tensor::Dtype::F32, spec.shape.clone(), b);
        (spec.name.clone(), view.expect("view"))
    });
    let metadata = HashMap::from([
        ("readi.format_version".to_string(), FORMAT_VERSION.to_string()),
        ("readi.manifest".to_string(), json),
        ("readi.checksum".to_string(), format!("{:08x}", crc.finalize())),
    ]);
    let dir = Scratch::new("variants");
    let path = dir.join("dup-key.plan");
    std::fs::write(&path, safetensors::serialize(views, Some(metadata)).expect("serialise")).expect("write");
    let e = Plan::load(&path).expect_err("a duplicate key must not load");
    let msg = e.to_string();
    assert!(matches!(e, PlanError::Manifest { .. }), "{msg}");
    assert!(msg.contains("dup-key.plan") && msg.contains("variant `fog=1`") && msg.contains("two variants"), "{msg}");
}

#[test]
fn unknown_keys_and_indices_are_errors_with_suggestions() {
    let plan = Arc::new(conv_plan(2, 2, 4).plan);
    let s = Session::new(Arc::clone(&plan), 1).expect("session");
    s.set_variant("fog=0.05").expect("known key");

    let e = s.set_variant("fog=0.5").expect_err("unknown key");
    assert_eq!(
        e,
        RunError::UnknownVariant {
            key: "fog=0.5".into(),
            known: vec!["base".into(), "fog=0.05".into(), "gamma=2".into()],
            nearest: Some("fog=0.05".into()),
            malformed: None,
        }
    );
    assert_eq!(
        e.to_string(),
        "the plan has no variant `fog=0.5`; did you mean `fog=0.05`? (its variants: base, fog=0.05, gamma=2)"
    );
    // A failed switch leaves the active variant alone.
    assert_eq!(s.variant(), "fog=0.05");

    let far = s.switch_handle().set("snow=10").expect_err("unknown key").to_string();
    assert_eq!(far, "the plan has no variant `snow=10` (its variants: base, fog=0.05, gamma=2)");
    let case = s.set_variant("GAMMA=2").expect_err("keys are case-sensitive").to_string();
    assert!(case.contains("did you mean `gamma=2`?"), "{case}");
    assert!(s.set_variant("").is_err());

    let e = s.switch_handle().set_index(3).expect_err("out of range");
    assert_eq!(e, RunError::VariantIndex { index: 3, count: 3 });
    assert!(e.to_string().contains("variant index 3 is out of range: the plan has 3 variants"), "{e}");
    assert_eq!(s.variant(), "fog=0.05");
}

/// The MLP plan with keys that have other spellings: `fog=0.01`, a meld and a missing
/// modality.
fn spelled_plan() -> Arc<Plan> {
    let (m, tensors) = edited(|v| {
        for (t, k) in v.iter_mut().zip(["fog=0.01", "blur=15+gamma=0.5", "missing=lidar"]) {
            t.key = key(k);
        }
    });
    Arc::new(Plan::new(m, tensors).expect("valid"))
}

#[test]
fn keys_are_looked_up_by_meaning() {
    let plan = spelled_plan();
    assert_eq!(
        plan.variant_keys().collect::<Vec<_>>(),
        [BASE_VARIANT, "fog=0.01", "blur=15+gamma=0.5", "missing=lidar"]
    );
    let mut s = Session::new(Arc::clone(&plan), 1).expect("session");
    let handle = s.switch_handle();
    let x = data(2 * 4, 3);
    // Each spelling names the canonical key's variant, by text and parsed, from the
    // session and from a handle, and runs exactly as the canonical key does.
    for (canonical, spellings) in [
        ("fog=0.01", &["fog=0.010", " fog = 0.01 ", "fog=1e-2", "fog=.01"][..]),
        ("blur=15+gamma=0.5", &["gamma=0.5+blur=15", "gamma=0.50+blur=15.0", "blur=15 + gamma=0.5"][..]),
        ("missing=lidar", &[" missing=lidar"][..]),
        (BASE_VARIANT, &[" base "][..]),
    ] {
        s.set_variant(canonical).expect("the canonical key");
        let want = run(&mut s, &x, &[2, 4]);
        let index = s.last_variant();
        for &text in spellings {
            s.set_variant(BASE_VARIANT).expect("base");
            s.set_variant(text).unwrap_or_else(|e| panic!("`{text}`: {e}"));
            assert_eq!(s.variant(), canonical, "`{text}`");
            let got = run(&mut s, &x, &[2, 4]);
            assert_eq!(s.last_variant(), index, "`{text}`");
            assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "`{text}`");
            handle.set_index(0).expect("base");
            handle.set(text).unwrap_or_else(|e| panic!("`{text}`: {e}"));
            assert_eq!(handle.key(), canonical, "`{text}`");
            handle.set_index(0).expect("base");
            handle.set_key(&key(text)).expect("a parsed key");
            assert_eq!(handle.key(), canonical, "`{text}`");
            s.set_variant(BASE_VARIANT).expect("base");
            s.set_variant_key(&key(text)).expect("a parsed key");
            assert_eq!(s.variant(), canonical, "`{text}`");
        }
    }
    assert_eq!(plan.variant_index_of(&key("gamma=0.5+blur=15")), plan.variant_index("blur=15+gamma=0.5"));
    assert_eq!(plan.variant_index_of(&VariantKey::base()), Some(0));
    assert_eq!(plan.variant_index_of(&key("fog=0.02")), None);
    // Only canonical text is found by the exact lookup.
    assert_eq!(plan.variant_index("fog=0.010"), None);
}

#[test]
fn unknown_and_malformed_keys_say_so() {
    let plan = spelled_plan();
    let s = Session::new(Arc::clone(&plan), 1).expect("session");
    s.set_variant("fog=0.01").expect("known key");
    let known: Vec<String> = plan.variant_keys().map(str::to_string).collect();
    // A key in another spelling that the plan does not have: the suggestion is the one
    // nearest its canonical text (`blur=5+gamma=0.5`).
    let e = s.set_variant("gamma=0.50+blur=5").expect_err("unknown key");
    assert_eq!(
        e,
        RunError::UnknownVariant {
            key: "gamma=0.50+blur=5".into(),
            known: known.clone(),
            nearest: Some("blur=15+gamma=0.5".into()),
            malformed: None,
        }
    );
    assert_eq!(
        e.to_string(),
        "the plan has no variant `gamma=0.50+blur=5`; did you mean `blur=15+gamma=0.5`? (its variants: base, \
         fog=0.01, blur=15+gamma=0.5, missing=lidar)"
    );
    let e = s.set_variant_key(&key("fog=0.020")).expect_err("unknown key");
    assert!(matches!(&e, RunError::UnknownVariant { key, malformed: None, .. } if key == "fog=0.02"), "{e}");
    // Text that is not a key says why, and still suggests a key when one is near.
    let e = s.switch_handle().set("fog0.01").expect_err("malformed");
    assert!(matches!(&e, RunError::UnknownVariant { malformed: Some(_), .. }), "{e:?}");
    assert_eq!(
        e.to_string(),
        "`fog0.01` is not a variant key: `fog0.01` has no `=` (write `axis=level`, `missing=modality` or `base`); \
         did you mean `fog=0.01`? (the plan's variants: base, fog=0.01, blur=15+gamma=0.5, missing=lidar)"
    );
    for (text, why) in [
        ("fog=thick", "the level `thick` of `fog` is not a finite number"),
        ("fog=0.01+fog=0.03", "`fog=0.01` and `fog=0.03` are on the same axis"),
        ("", "it is empty"),
        ("missing=", "`` is not a modality name"),
    ] {
        let e = s.set_variant(text).expect_err("malformed").to_string();
        assert!(e.starts_with(&format!("`{text}` is not a variant key: {why}")), "{e}");
    }
    // A failed switch leaves the active variant alone.
    assert_eq!(s.variant(), "fog=0.01");
}

#[test]
fn a_plan_without_variants_has_only_the_base() {
    let (m, tensors) = edited(Vec::clear);
    let plan = Arc::new(Plan::new(m, tensors).expect("valid"));
    assert_eq!(plan.variant_count(), 1);
    assert_eq!(plan.variant_keys().collect::<Vec<_>>(), [BASE_VARIANT]);
    let mut s = Session::new(Arc::clone(&plan), 1).expect("session");
    assert!(s.set_variant("fog=1").is_err());
    s.set_variant(BASE_VARIANT).expect("base");
    let x = data(8, 1);
    let y = run(&mut s, &x, &[2, 4]);
    let w = mlp(4, 3).weights[BASE_VARIANT].clone();
    assert_close(&y, &mlp_reference(&x, 4, 3, &w), "base");
    assert_eq!(s.last_variant(), Some(0));
}

// ---------------------------------------------------------------------------------------
// (e) Replacements stored at half precision
// ---------------------------------------------------------------------------------------

/// The MLP with the tensors whose names end in one of `suffixes` (a variant's) stored f16.
fn mlp_with_half(m: &Mlp, suffixes: &[&str]) -> Result<Plan, PlanError> {
    use readi_runtime::plan::TensorData;
    let mut manifest = m.plan.manifest.clone();
    let mut tensors = Vec::new();
    for (i, spec) in manifest.tensors.iter_mut().enumerate() {
        let d = m.plan.tensor(i);
        if suffixes.iter().any(|s| spec.name.ends_with(s)) {
            spec.dtype = readi_plan::DType::F16;
            tensors.push(TensorData::from(d.iter().map(|&x| half::f16::from_f32(x)).collect::<Vec<_>>()));
        } else {
            tensors.push(TensorData::from(d.to_vec()));
        }
    }
    Plan::new(manifest, tensors)
}

/// `w` with what variant A or B replaces (W, gamma, p; W, bias, beta, p) rounded to f16.
fn rounded(w: &MlpWeights, key: &str) -> MlpWeights {
    let r = |v: &[f32]| v.iter().map(|&x| half::f16::from_f32(x).to_f32()).collect();
    match key {
        "fog=1" => MlpWeights { w: r(&w.w), gamma: r(&w.gamma), p: r(&w.p), ..w.clone() },
        _ => MlpWeights { w: r(&w.w), bias: r(&w.bias), beta: r(&w.beta), p: r(&w.p), ..w.clone() },
    }
}

#[test]
fn a_variant_stored_f16_reads_its_values_decoded() {
    let m = mlp(24, 16);
    let plan = Arc::new(mlp_with_half(&m, &["~A", "~B"]).expect("a valid plan"));
    let (a, b) = (24 * 16 + 16 + 16, 24 * 16 + 3 * 16);
    assert_eq!(plan.tensor_bytes(), m.plan.tensor_bytes() - (a + b) * 2);
    let x = data(3 * m.fin, 7);
    let mut s = Session::new(Arc::clone(&plan), 2).expect("session");
    // A's and B's tensors are f16: one decoded copy per replaced base tensor, which A
    // and B both write (W, p); C reads A's W (the same stored tensor).
    let want = |key: &str| match key {
        "fog=1" | "fog=2" => rounded(&m.weights[key], key),
        "fog=3" => MlpWeights { w: rounded(&m.weights[key], "fog=1").w, ..m.weights[key].clone() },
        _ => m.weights[key].clone(),
    };
    for key in ["fog=1", "fog=2", "fog=1", "fog=3", BASE_VARIANT, "fog=3", "fog=2", "fog=2", "fog=1"] {
        s.set_variant(key).expect("known key");
        let y = run(&mut s, &x, &[3, m.fin]);
        assert_close(&y, &mlp_reference(&x, m.fin, m.fout, &want(key)), key);
    }
    // Through a file: the f16 tensors stay f16 and read the same.
    let dir = Scratch::new("half");
    let path = dir.join("mlp.plan");
    plan.write(&path).expect("write");
    let loaded = Arc::new(Plan::load(&path).expect("loads"));
    assert!(loaded.manifest.tensors.iter().any(|t| t.dtype == readi_plan::DType::F16));
    let mut l = Session::new(loaded, 1).expect("session");
    for key in ["fog=3", "fog=1"] {
        s.set_variant(key).expect("key");
        l.set_variant(key).expect("key");
        assert_eq!(run(&mut l, &x, &[3, m.fin]), run(&mut s, &x, &[3, m.fin]), "{key}");
    }
}

#[test]
fn only_a_replacement_may_be_stored_f16() {
    let m = mlp(8, 4);
    // The base's W, which the linear step names.
    let err = mlp_with_half(&m, &["fc.weight@t"]).expect_err("a base tensor stored f16").to_string();
    assert!(err.contains("`fc.weight@t`") && err.contains("only a variant's replacement"), "{err}");
    // A manifest that says f16 for data given as f32.
    let mut manifest = m.plan.manifest.clone();
    let at = manifest.tensors.iter().position(|t| t.name == "p~A").expect("p~A");
    manifest.tensors[at].dtype = readi_plan::DType::F16;
    let tensors: Vec<Vec<f32>> = (0..manifest.tensors.len()).map(|i| m.plan.tensor(i).to_vec()).collect();
    let err = Plan::new(manifest, tensors).expect_err("f32 data for an f16 tensor").to_string();
    assert!(err.contains("`p~A`") && err.contains("f16"), "{err}");
}

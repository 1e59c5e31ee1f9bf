//! The `readi` binary: exit codes, outputs and help, run as a user would.

use std::process::{Command, Output};

fn readi(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_readi"))
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("NO_COLOR", "1")
        .output()
        .expect("run readi")
}

fn stdout(o: &Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn check_accepts_every_bundled_model() {
    let o = readi(&[
        "check",
        "models/resnet18.readi",
        "models/vit_encoder.readi",
        "models/pointpillars_bev.readi",
        "models/bevfusion_tiny.readi",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stdout(&o).lines().filter(|l| l.starts_with("ok  ")).count(), 4, "{}", stdout(&o));
}

#[test]
fn check_fails_with_located_diagnostics() {
    let o = readi(&["check", "tests/cases/errors/syntax_missing_comma.readi"]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("tests/cases/errors/syntax_missing_comma.readi:4:23"), "{err}");
    assert!(err.contains("expected `)`, `,` or an operator, found `kernel`"), "{err}");
    assert!(err.contains("^^^^^^"), "{err}");
}

#[test]
fn check_reports_every_file_and_fails_if_any_fails() {
    let o = readi(&["check", "models/resnet18.readi", "tests/cases/errors/unknown_name.readi"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stdout(&o).contains("ok  models/resnet18.readi"), "{}", stdout(&o));
    assert!(stderr(&o).contains("unknown name `cnv1`"), "{}", stderr(&o));
}

#[test]
fn missing_file_is_a_clear_error() {
    let o = readi(&["check", "no/such/file.readi"]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("cannot read no/such/file.readi"), "{}", stderr(&o));
}

#[test]
fn params_prints_the_table_and_total() {
    let o = readi(&["params", "models/resnet18.readi"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("layer2.0.downsample.0.weight"), "{out}");
    assert!(out.contains("total: 11,689,512 parameters"), "{out}");
    let o = readi(&["params", "models/resnet18.readi", "--set", "num_classes=10"]);
    assert!(stdout(&o).contains("total: 11,181,642 parameters"), "{}", stdout(&o));
    let o = readi(&["params", "models/resnet18.readi", "--buffers"]);
    assert!(stdout(&o).contains("layer1.0.bn2.running_var"), "{}", stdout(&o));
}

#[test]
fn unknown_model_parameter_is_reported() {
    let o = readi(&["params", "models/resnet18.readi", "--set", "num_clases=10"]);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(err.contains("has no parameter `num_clases`") && err.contains("did you mean `num_classes`?"), "{err}");
}

#[test]
fn ir_stops_after_a_pass() {
    let o = readi(&["ir", "models/resnet18.readi", "--stop-after", "elaborate"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.starts_with("model resnet18(num_classes = 1000)"), "{out}");
    assert!(!out.contains("\nadapt\n"), "the adapt plan comes from a later pass:\n{out}");
    let full = stdout(&readi(&["ir", "models/resnet18.readi"]));
    assert!(full.contains("\nadapt\n") && full.contains("\nvariants\n"), "{full}");
    let bad = readi(&["ir", "models/resnet18.readi", "--stop-after", "elaborat"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(stderr(&bad).contains("passes: parse, elaborate"), "{}", stderr(&bad));
}

#[test]
fn graph_writes_dot() {
    let dir = std::env::temp_dir().join(format!("readi-cli-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    let path = dir.join("r18.dot");
    let o = readi(&["graph", "models/resnet18.readi", "-o", path.to_str().expect("utf-8 path")]);
    assert!(o.status.success(), "{}", stderr(&o));
    let dot = std::fs::read_to_string(&path).expect("dot written");
    assert!(dot.starts_with("digraph \"resnet18\""), "{dot}");
    assert!(dot.contains("subgraph cluster_"), "block instances are clusters");
    assert_eq!(dot.matches('{').count(), dot.matches('}').count(), "balanced braces");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn ast_prints_canonical_source() {
    let o = readi(&["ast", "models/vit_encoder.readi"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("block EncoderBlock(x: tensor, width: int, heads: int, mlp_ratio: int = 4) {"), "{out}");
    assert!(out.contains("lora rank=4 alpha=8 on blocks.*.{q,k,v,proj}"), "{out}");
}

#[test]
fn help_shows_examples() {
    let o = readi(&["--help"]);
    assert!(o.status.success());
    let out = stdout(&o);
    assert!(out.contains("Examples:") && out.contains("readi check models/*.readi"), "{out}");
    let o = readi(&["check", "--help"]);
    assert!(stdout(&o).contains("Example:"), "{}", stdout(&o));
}

#[test]
fn passes_lists_the_pipeline_in_order() {
    let out = stdout(&readi(&["passes"]));
    let names: Vec<&str> = out.lines().filter_map(|l| l.split_whitespace().next()).collect();
    assert_eq!(names, ["parse", "elaborate", "dead_code", "resolve_adapt", "check_variants"]);
}

#[test]
fn demo_runs_on_the_embedded_model() {
    let o = Command::new(env!("CARGO_BIN_EXE_readi"))
        .arg("demo")
        .current_dir(std::env::temp_dir())
        .output()
        .expect("run readi demo");
    assert!(o.status.success(), "{}", stderr(&o));
    let out = stdout(&o);
    assert!(out.contains("bevfusion_tiny"), "{out}");
    assert!(out.contains("exist budget") && out.contains("add budget"), "{out}");
}

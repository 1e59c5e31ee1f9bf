//! Property tests: no input makes readi panic, every graph that checks is valid, and the
//! canonical printer is stable.
//!
//! Inputs are random text, random token sequences, and the bundled models and language
//! cases with random edits (deleted ranges, inserted tokens, duplicated and swapped lines,
//! replaced numbers). Each property runs `PROPTEST_CASES` cases (default 192), which keeps
//! the whole file to a few seconds in CI.

use proptest::prelude::*;
use readi_compiler::passes::{self, Options};
use readi_compiler::print;
use readi_compiler::verify::verify;
use readi_grammar::ast_print::to_source;
use readi_grammar::diag::{FileId, SourceMap};

const SEEDS: &[&str] = &[
    include_str!("../models/resnet18.readi"),
    include_str!("../models/vit_encoder.readi"),
    include_str!("../models/pointpillars_bev.readi"),
    include_str!("../models/bevfusion_tiny.readi"),
    include_str!("cases/ok/all_ops.readi"),
    include_str!("cases/ok/adapt_and_variants.readi"),
    include_str!("cases/ok/conditionals.readi"),
    include_str!("cases/ok/arithmetic.readi"),
];

const TOKENS: &[&str] = &[
    "model",
    "block",
    "adapt",
    "variants",
    "input",
    "output",
    "let",
    "if",
    "then",
    "else",
    "for",
    "in",
    "return",
    "seq",
    "true",
    "false",
    "and",
    "or",
    "not",
    "tune",
    "lora",
    "adapter",
    "on",
    "before",
    "axis",
    "missing",
    "select",
    "by",
    "meld",
    "clear",
    "nearest",
    "meta",
    "optional",
    "{",
    "}",
    "(",
    ")",
    "[",
    "]",
    ",",
    ".",
    "..",
    "=",
    "==",
    "!=",
    "<",
    "<=",
    "+",
    "-",
    "*",
    "**",
    "/",
    "//",
    "%",
    "->",
    "@",
    ":",
    "#",
    "\"",
    "\n",
    "0",
    "1",
    "-1",
    "3",
    "64",
    "0.5",
    "1e-5",
    "1e308",
    "99999999999999999999",
    "x",
    "N",
    "conv2d",
    "batchnorm",
    "linear",
    "relu",
    "concat",
    "reshape",
    "dim",
    "seq",
    "f32",
    "i64",
    "tensor",
    "int",
    "BasicBlock",
    "layer1",
    "head.*",
    "**",
    "camera",
    "lidar",
    "é",
    "\t",
];

fn config() -> ProptestConfig {
    let cases = std::env::var("PROPTEST_CASES").ok().and_then(|v| v.parse().ok()).unwrap_or(192);
    ProptestConfig { cases, max_global_rejects: cases * 10, failure_persistence: None, ..ProptestConfig::default() }
}

/// Runs everything a user can run on a source: the pipeline, the renderer for every
/// diagnostic, the printers on a module; and checks the verifier on error-free modules.
fn exercise(src: &str) {
    let mut sources = SourceMap::new();
    let file = sources.add("fuzz.readi", src);
    let out = passes::run(file, src, &Options::default());
    let _ = sources.render_all(&out.diagnostics, false);
    let _ = to_source(&out.ast);
    if let Some(m) = &out.module {
        let _ = print::to_text(m);
        let _ = print::to_dot(&m.graph);
        let _ = print::param_table(m, true);
        if !out.diagnostics.has_errors()
            && let Err(problems) = verify(m)
        {
            panic!("a module without errors fails verification: {problems:?}\n--- source ---\n{src}");
        }
    }
}

#[derive(Clone, Debug)]
enum Edit {
    Delete { at: usize, len: usize },
    Insert { at: usize, token: usize },
    DuplicateLine { line: usize },
    SwapLines { a: usize, b: usize },
    ReplaceNumber { nth: usize, token: usize },
}

fn edit() -> impl Strategy<Value = Edit> {
    prop_oneof![
        (any::<usize>(), 1usize..40).prop_map(|(at, len)| Edit::Delete { at, len }),
        (any::<usize>(), 0..TOKENS.len()).prop_map(|(at, token)| Edit::Insert { at, token }),
        any::<usize>().prop_map(|line| Edit::DuplicateLine { line }),
        (any::<usize>(), any::<usize>()).prop_map(|(a, b)| Edit::SwapLines { a, b }),
        (any::<usize>(), 0..TOKENS.len()).prop_map(|(nth, token)| Edit::ReplaceNumber { nth, token }),
    ]
}

/// Applies an edit at char boundaries.
fn apply(src: &str, e: &Edit) -> String {
    let boundary = |at: usize| {
        let mut i = at % (src.len() + 1);
        while !src.is_char_boundary(i) {
            i -= 1;
        }
        i
    };
    match e {
        Edit::Delete { at, len } => {
            let a = boundary(*at);
            let b = boundary(a + len);
            format!("{}{}", &src[..a], &src[b.max(a)..])
        }
        Edit::Insert { at, token } => {
            let a = boundary(*at);
            format!("{} {} {}", &src[..a], TOKENS[*token], &src[a..])
        }
        Edit::DuplicateLine { line } => {
            let mut lines: Vec<&str> = src.lines().collect();
            if !lines.is_empty() {
                let i = line % lines.len();
                lines.insert(i, lines[i]);
            }
            lines.join("\n")
        }
        Edit::SwapLines { a, b } => {
            let mut lines: Vec<&str> = src.lines().collect();
            if !lines.is_empty() {
                let (i, j) = (a % lines.len(), b % lines.len());
                lines.swap(i, j);
            }
            lines.join("\n")
        }
        Edit::ReplaceNumber { nth, token } => {
            let starts: Vec<usize> = src
                .char_indices()
                .filter(|&(i, c)| c.is_ascii_digit() && !src[..i].ends_with(|p: char| p.is_alphanumeric() || p == '_'))
                .map(|(i, _)| i)
                .collect();
            if starts.is_empty() {
                return src.to_string();
            }
            let a = starts[nth % starts.len()];
            let b = src[a..].find(|c: char| !(c.is_ascii_digit() || c == '.')).map_or(src.len(), |k| a + k);
            format!("{}{}{}", &src[..a], TOKENS[*token], &src[b..])
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn random_text_never_panics(src in "\\PC{0,300}") {
        exercise(&src);
    }

    #[test]
    fn token_soup_never_panics(tokens in prop::collection::vec(0..TOKENS.len(), 0..120)) {
        let src: Vec<&str> = tokens.iter().map(|&t| TOKENS[t]).collect();
        exercise(&src.join(" "));
    }

    #[test]
    fn edited_models_never_panic(seed in 0..SEEDS.len(), edits in prop::collection::vec(edit(), 1..5)) {
        let src = edits.iter().fold(SEEDS[seed].to_string(), |s, e| apply(&s, e));
        exercise(&src);
    }

    #[test]
    fn canonical_printing_is_a_fixed_point(seed in 0..SEEDS.len(), edits in prop::collection::vec(edit(), 0..3)) {
        let src = edits.iter().fold(SEEDS[seed].to_string(), |s, e| apply(&s, e));
        let first = readi_grammar::parse(FileId(0), &src);
        prop_assume!(!first.diagnostics.has_errors());
        let printed = to_source(&first.file);
        let second = readi_grammar::parse(FileId(0), &printed);
        prop_assert!(!second.diagnostics.has_errors(), "printed source does not parse:\n{}", printed);
        prop_assert_eq!(to_source(&second.file), printed);
    }
}

/// The elaborator's recursion is bounded by the parser's limits; the worst case allowed
/// must run on the 2 MiB stack of a test thread.
#[test]
fn limits_hold_on_a_small_stack() {
    let deep_expr = format!("{}1{}", "(".repeat(30), ")".repeat(30));
    let mut blocks = String::new();
    for i in 0..40 {
        blocks.push_str(&format!(
            "block B{i}(x: tensor) {{\n  let k = {deep_expr}\n  b = B{}(x)\n  return b\n}}\n",
            i + 1
        ));
    }
    blocks.push_str("block B40(x: tensor) {\n  return relu(x)\n}\n");
    let src = format!("{blocks}model m {{\n  input x: f32[N, 4]\n  b = B0(x)\n  output y = b\n}}\n");
    let handle = std::thread::Builder::new()
        .stack_size(2 << 20)
        .spawn(move || {
            let mut sources = SourceMap::new();
            let file = sources.add("deep.readi", src.as_str());
            let out = passes::run(file, &src, &Options::default());
            sources.render_all(&out.diagnostics, false)
        })
        .expect("spawn");
    let rendered = handle.join().expect("no stack overflow");
    assert!(rendered.contains("nested more than"), "{rendered}");
}

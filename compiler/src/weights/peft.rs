//! PEFT LoRA adapters: a directory with `adapter_config.json` and
//! `adapter_model.safetensors`, as `PeftModel.save_pretrained` writes it.
//!
//! Tensor keys are `base_model.model.<path>.lora_A.weight` and `...lora_B.weight`; the
//! prefix is dropped, which leaves the names `inject_adapt` gives the LoRA layers. Other
//! keys (a `modules_to_save` head saved by PEFT under its plain name) pass through and are
//! checked like any variant tensor. The config must agree with the spec's `lora` rule for
//! every layer the adapter has: `r` with `rank`, `lora_alpha` with `alpha`, `use_rslora`
//! with `rslora`; PEFT features readi does not run (DoRA, `fan_in_fan_out`, LoRA biases,
//! per-layer rank or alpha patterns) are errors rather than silently wrong answers.

use std::collections::BTreeMap;

use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use serde_json::Value;

use super::WeightSet;
use crate::adapt::{Injection, RuleKind};
use crate::module::Module;

/// The file names inside an adapter directory.
pub const CONFIG_FILE: &str = "adapter_config.json";
pub const WEIGHTS_FILE: &str = "adapter_model.safetensors";
const PREFIX: &str = "base_model.model.";

/// The LoRA settings of an adapter config that readi uses.
#[derive(Clone, Debug, PartialEq)]
pub struct PeftConfig {
    pub r: i64,
    pub lora_alpha: f64,
    pub use_rslora: bool,
}

fn error(message: String) -> Diagnostic {
    Diagnostic::error(Code::VariantWeights, message)
}

/// Parses and checks `adapter_config.json`; `file` names it in messages.
pub fn parse_config(file: &str, text: &str) -> Result<PeftConfig, Diagnostics> {
    let v: Value = serde_json::from_str(text)
        .map_err(|e| Diagnostics(vec![error(format!("{file}:{}:{}: not valid JSON: {e}", e.line(), e.column()))]))?;
    let mut diags = Diagnostics::default();
    let field = |k: &str| v.get(k).filter(|x| !x.is_null());
    if let Some(t) = field("peft_type").and_then(Value::as_str)
        && t != "LORA"
    {
        diags.push(error(format!("{file}: `peft_type` is `{t}`; readi reads LoRA adapters (`LORA`)")));
    }
    for (k, what) in [("use_dora", "DoRA"), ("fan_in_fan_out", "fan_in_fan_out weights"), ("lora_bias", "LoRA biases")]
    {
        if field(k).and_then(Value::as_bool) == Some(true) {
            diags.push(error(format!("{file}: `{k}` is true; readi does not support {what}")));
        }
    }
    for k in ["rank_pattern", "alpha_pattern"] {
        if field(k).and_then(Value::as_object).is_some_and(|m| !m.is_empty()) {
            diags.push(
                error(format!("{file}: `{k}` sets per-layer values; readi needs one rank and alpha per rule"))
                    .with_note("split the layers over several `lora` rules instead"),
            );
        }
    }
    let r = field("r").and_then(Value::as_i64);
    let alpha = field("lora_alpha").and_then(Value::as_f64);
    if r.is_none_or(|r| r < 1) {
        diags.push(error(format!("{file}: `r` must be a positive integer")));
    }
    if alpha.is_none() {
        diags.push(error(format!("{file}: `lora_alpha` must be a number")));
    }
    if diags.has_errors() {
        return Err(diags);
    }
    Ok(PeftConfig {
        r: r.unwrap_or(1),
        lora_alpha: alpha.unwrap_or(1.0),
        use_rslora: field("use_rslora").and_then(Value::as_bool).unwrap_or(false),
    })
}

/// Reads an adapter's tensors by readi name and checks them against the spec's rules.
/// `dir` names the directory in messages.
pub fn read_adapter(dir: &str, config_text: &str, weights: &[u8], module: &Module) -> Result<WeightSet, Diagnostics> {
    let config_file = format!("{dir}/{CONFIG_FILE}");
    let weights_file = format!("{dir}/{WEIGHTS_FILE}");
    let config = parse_config(&config_file, config_text)?;
    let raw = WeightSet::from_safetensors(&weights_file, weights)?;
    let mut diags = Diagnostics::default();
    let mut set = WeightSet::default();
    for (key, value) in raw.tensors {
        match key.strip_prefix(PREFIX) {
            Some(name) => {
                set.tensors.insert(name.to_string(), value);
            }
            None => diags.push(error(format!("{weights_file}: tensor `{key}` does not start with `{PREFIX}`"))),
        }
    }
    // Each LoRA layer of the spec, by path: its rule's settings.
    let g = &module.graph;
    let mut rules: BTreeMap<String, usize> = BTreeMap::new();
    if let Some(plan) = &module.adapt {
        for inj in &plan.injections {
            if let Injection::Lora { rule, base, .. } = inj {
                rules.insert(g.node(*base).path.clone(), *rule);
            }
        }
    }
    let mut checked: Vec<usize> = Vec::new();
    for name in set.tensors.keys() {
        let Some(layer) = name.strip_suffix(".lora_A.weight").or_else(|| name.strip_suffix(".lora_B.weight")) else {
            continue;
        };
        let Some(&rule) = rules.get(layer) else {
            diags.push(
                error(format!("{weights_file}: the adapter has LoRA on `{layer}`, which no `lora` rule selects"))
                    .with_note("add the layer to a `lora` rule's selector, or retrain without it"),
            );
            continue;
        };
        if checked.contains(&rule) {
            continue;
        }
        checked.push(rule);
        let Some(plan) = &module.adapt else { continue };
        let r = &plan.rules[rule];
        if let RuleKind::Lora { rank, alpha, rslora } = r.kind {
            let mut problems = Vec::new();
            if config.r != rank {
                problems.push(format!("r = {} (the rule's rank = {rank})", config.r));
            }
            if (config.lora_alpha - alpha).abs() > 1e-9 * alpha.abs().max(1.0) {
                problems.push(format!("lora_alpha = {} (the rule's alpha = {alpha})", config.lora_alpha));
            }
            if config.use_rslora != rslora {
                problems.push(format!(
                    "use_rslora = {} (the rule {} rslora)",
                    config.use_rslora,
                    if rslora { "sets" } else { "does not set" }
                ));
            }
            if !problems.is_empty() {
                diags.push(
                    error(format!(
                        "{config_file}: the adapter disagrees with the spec's LoRA rule: {}",
                        problems.join(", ")
                    ))
                    .with_primary(r.span, "the rule for these layers"),
                );
            }
        }
    }
    if diags.has_errors() { Err(diags) } else { Ok(set) }
}

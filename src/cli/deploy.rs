//! Deployment manifests: one base model and its variants, in YAML.
//!
//! ```yaml
//! spec: models/resnet18.readi        # paths are relative to this file
//! set: { num_classes: 10 }           # model parameters (optional)
//! weights: resnet18.safetensors      # the base model's state_dict
//! lora: merge                        # or `branch` (optional; default merge)
//! variants:
//!   - key: gamma=0.25                # a key the spec's variants section declares
//!     params: gamma_0.25.safetensors # tensors the variant owns, PyTorch names (optional)
//!     peft: adapters/gamma_0.25      # a PEFT LoRA adapter directory (optional)
//!   - key: blur=5
//!     peft: adapters/blur_5
//! melds: [gamma=0.25+blur=5]          # combined conditions, by the spec's meld rule (optional)
//! ```
//!
//! Unknown fields are errors (a misspelt `varaints` must not silently drop every variant);
//! every error names the file, and YAML errors the line and column.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use readi_compiler::Module;
use readi_compiler::backend::{VariantSource, WeightSet, peft};
use readi_grammar::diag::{Code, Diagnostic, Diagnostics};
use serde::Deserialize;

/// A parsed deployment manifest, paths resolved against its directory.
#[derive(Clone, Debug)]
pub struct Deployment {
    pub spec: PathBuf,
    pub set: Vec<(String, String)>,
    pub weights: PathBuf,
    pub lora: Option<String>,
    pub variants: Vec<VariantFiles>,
    /// Melded variants to build from the listed ones, `fog=0.06+gamma=0.5`.
    pub melds: Vec<String>,
}

/// Where one variant's parameters are.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VariantFiles {
    pub key: String,
    pub params: Option<PathBuf>,
    pub peft: Option<PathBuf>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawDeployment {
    spec: PathBuf,
    #[serde(default)]
    set: BTreeMap<String, yaml_serde::Value>,
    weights: PathBuf,
    #[serde(default)]
    lora: Option<String>,
    #[serde(default)]
    variants: Vec<RawVariant>,
    #[serde(default)]
    melds: Vec<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RawVariant {
    key: String,
    #[serde(default)]
    params: Option<PathBuf>,
    #[serde(default)]
    peft: Option<PathBuf>,
}

/// Parses a manifest's text; `path` names it in errors and anchors relative paths.
pub fn parse(path: &Path, text: &str) -> Result<Deployment, String> {
    let name = path.display();
    let raw: RawDeployment = yaml_serde::from_str(text).map_err(|e| match e.location() {
        Some(at) => format!("{name}:{}:{}: {e}", at.line(), at.column()),
        None => format!("{name}: {e}"),
    })?;
    let dir = path.parent().unwrap_or(Path::new(""));
    let resolve = |p: PathBuf| if p.is_absolute() { p } else { dir.join(p) };
    let mut set = Vec::new();
    for (k, v) in raw.set {
        let value = match v {
            yaml_serde::Value::Number(n) => n.to_string(),
            yaml_serde::Value::Bool(b) => b.to_string(),
            yaml_serde::Value::String(s) => s,
            _ => return Err(format!("{name}: `set.{k}` must be a number, a boolean or a string")),
        };
        set.push((k, value));
    }
    let mut variants = Vec::new();
    for (i, v) in raw.variants.into_iter().enumerate() {
        if v.params.is_none() && v.peft.is_none() {
            return Err(format!("{name}: variant {} (`{}`) gives neither `params` nor `peft`", i + 1, v.key));
        }
        variants.push(VariantFiles { key: v.key, params: v.params.map(resolve), peft: v.peft.map(resolve) });
    }
    Ok(Deployment {
        spec: resolve(raw.spec),
        set,
        weights: resolve(raw.weights),
        lora: raw.lora,
        variants,
        melds: raw.melds,
    })
}

fn read(path: &Path) -> Result<Vec<u8>, Diagnostics> {
    std::fs::read(path).map_err(|e| {
        Diagnostics(vec![Diagnostic::error(Code::VariantWeights, format!("cannot read {}: {e}", path.display()))])
    })
}

/// Reads a variant's files into one set of tensors by readi name.
pub fn read_variant(files: &VariantFiles, module: &Module) -> Result<VariantSource, Diagnostics> {
    let mut weights = WeightSet::default();
    let mut origin = Vec::new();
    if let Some(p) = &files.params {
        let name = p.display().to_string();
        weights = WeightSet::from_safetensors(&name, &read(p)?)?;
        origin.push(name);
    }
    if let Some(dir) = &files.peft {
        let name = dir.display().to_string();
        let config = String::from_utf8_lossy(&read(&dir.join(peft::CONFIG_FILE))?).into_owned();
        let adapter = peft::read_adapter(&name, &config, &read(&dir.join(peft::WEIGHTS_FILE))?, module)?;
        for (k, v) in adapter.tensors {
            if weights.tensors.contains_key(&k) {
                return Err(Diagnostics(vec![Diagnostic::error(
                    Code::VariantWeights,
                    format!("variant `{}`: tensor `{k}` is in both {} and {name}", files.key, origin.join(", ")),
                )]));
            }
            weights.tensors.insert(k, v);
        }
        origin.push(name);
    }
    Ok(VariantSource { key: files.key.clone(), weights, origin: origin.join(" + ") })
}

/// `KEY=PATH` from the command line: a directory is a PEFT adapter, a file a parameter
/// file. Giving a key twice combines its files.
pub fn variant_args(args: &[(String, String)]) -> Vec<VariantFiles> {
    let mut out: Vec<VariantFiles> = Vec::new();
    for (key, path) in args {
        let path = PathBuf::from(path);
        let i = match out.iter().position(|v| v.key == *key) {
            Some(i) => i,
            None => {
                out.push(VariantFiles { key: key.clone(), ..Default::default() });
                out.len() - 1
            }
        };
        if path.is_dir() {
            out[i].peft = Some(path);
        } else {
            out[i].params = Some(path);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_manifest_resolves_paths_against_its_directory() {
        let text = "spec: m.readi\nset: {num_classes: 10, img: 64}\nweights: w.safetensors\nvariants:\n  - key: fog=0.03\n    params: fog.safetensors\n  - key: gamma=0.5\n    peft: adapters/g\n";
        let d = parse(Path::new("deploy/x.yaml"), text).expect("parses");
        assert_eq!(d.spec, Path::new("deploy/m.readi"));
        assert_eq!(d.weights, Path::new("deploy/w.safetensors"));
        assert_eq!(d.set, vec![("img".to_string(), "64".to_string()), ("num_classes".to_string(), "10".to_string())]);
        assert_eq!(d.variants.len(), 2);
        assert_eq!(d.variants[0].params.as_deref(), Some(Path::new("deploy/fog.safetensors")));
        assert_eq!(d.variants[1].peft.as_deref(), Some(Path::new("deploy/adapters/g")));
    }

    #[test]
    fn a_misspelt_field_is_an_error_with_its_place() {
        let text = "spec: m.readi\nweights: w.safetensors\nvaraints: []\n";
        let e = parse(Path::new("d.yaml"), text).expect_err("unknown field");
        assert!(e.starts_with("d.yaml:3:1:") && e.contains("varaints"), "{e}");
    }

    #[test]
    fn a_variant_without_files_is_an_error() {
        let text = "spec: m.readi\nweights: w.safetensors\nvariants:\n  - key: fog=0.03\n";
        let e = parse(Path::new("d.yaml"), text).expect_err("no files");
        assert!(e.contains("neither `params` nor `peft`"), "{e}");
    }
}

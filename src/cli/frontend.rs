//! The front end as the commands use it: loading spec files, running the pipeline,
//! rendering diagnostics, and the one-line error summary.

use std::io::Write;
use std::path::Path;
use std::process::ExitCode;

use readi_compiler::passes::{self, Options, Outcome, Pass};
use readi_grammar::diag::{Diagnostics, FileId, SourceMap};

use super::args::ModelArgs;

/// A loaded source file, its pipeline outcome, and how to show its diagnostics.
pub struct Frontend {
    pub sources: SourceMap,
    pub color: bool,
}

impl Frontend {
    pub fn load(&mut self, path: &Path) -> Result<(FileId, String), ExitCode> {
        // The parser refuses longer sources; reading more would only spend memory.
        let limit = readi_grammar::parser::MAX_SOURCE_BYTES as u64;
        match super::files::read_bounded(path, limit) {
            Ok(bytes) => match String::from_utf8(bytes) {
                Ok(text) => Ok((self.sources.add(path.display().to_string(), text.clone()), text)),
                Err(e) => {
                    eprintln!(
                        "error: {} is not UTF-8 text (invalid byte at offset {})",
                        path.display(),
                        e.utf8_error().valid_up_to()
                    );
                    Err(ExitCode::from(2))
                }
            },
            Err(e) => {
                eprintln!("error: {e}");
                Err(ExitCode::from(2))
            }
        }
    }

    pub fn report(&self, diags: &Diagnostics) {
        let mut err = std::io::stderr().lock();
        let _ = err.write_all(self.sources.render_all(diags, self.color).as_bytes());
    }

    pub fn compile(
        &mut self,
        path: &Path,
        model: &ModelArgs,
        stop_after: Option<Pass>,
    ) -> Result<(Outcome, FileId), ExitCode> {
        let (file, text) = self.load(path)?;
        let opts = options(model, stop_after);
        let out = passes::run(file, &text, &opts);
        self.report(&out.diagnostics);
        Ok((out, file))
    }
}

fn options(model: &ModelArgs, stop_after: Option<Pass>) -> Options {
    let mut opts = Options { stop_after, ..Options::with_overrides(&model.set) };
    opts.elab.max_activation_bytes = model.max_activation_memory.map(|b| b as u64);
    opts
}

pub fn summary_line(path: &str, diags: &Diagnostics) -> String {
    let plural = |n: usize, w: &str| format!("{n} {w}{}", if n == 1 { "" } else { "s" });
    let mut parts = Vec::new();
    if diags.error_count() > 0 {
        parts.push(plural(diags.error_count(), "error"));
    }
    if diags.warning_count() > 0 {
        parts.push(plural(diags.warning_count(), "warning"));
    }
    format!("{path}: {}", parts.join(", "))
}

/// Compiles a file and, if that succeeded, hands the module to `f`.
pub fn with_module(
    s: &mut Frontend,
    path: &Path,
    model: &ModelArgs,
    stop_after: Option<Pass>,
    f: impl FnOnce(&readi_compiler::Module),
) -> Result<(), ExitCode> {
    let (out, _) = s.compile(path, model, stop_after)?;
    if out.diagnostics.has_errors() {
        eprintln!("error: {}", summary_line(&path.display().to_string(), &out.diagnostics));
        return Err(ExitCode::FAILURE);
    }
    match &out.module {
        Some(m) => {
            f(m);
            Ok(())
        }
        None => {
            eprintln!("{}: nothing to show after pass `parse`; use `readi ast`", path.display());
            Err(ExitCode::FAILURE)
        }
    }
}

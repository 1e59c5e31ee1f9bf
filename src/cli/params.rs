//! `readi params`: every parameter (name, shape, count) and the total.

use std::path::Path;
use std::process::ExitCode;

use readi_compiler::print;

use super::args::ModelArgs;
use super::frontend::{Frontend, with_module};

/// Prints the parameter table; with `buffers`, the BatchNorm running statistics too.
pub fn run(s: &mut Frontend, file: &Path, buffers: bool, model: &ModelArgs) -> Result<(), ExitCode> {
    with_module(s, file, model, None, |m| {
        print!("{}", print::param_table(m, buffers));
    })
}

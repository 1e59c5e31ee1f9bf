//! `readi inspect`: a plan described by [`readi::inspect::plan`], and its memory footprint
//! against the memory limit ([`readi::inspect::memory_limit`]).

use std::path::Path;
use std::process::ExitCode;

use readi_runtime::exec::default_max_memory;

use super::{load_plan, threads_or_default};

pub fn run(plan_path: &Path, verbose: bool, max_memory: Option<usize>) -> Result<(), ExitCode> {
    let plan = load_plan(plan_path)?;
    print!("{}", readi::inspect::plan(&plan, plan_path, verbose));
    let limit = max_memory.unwrap_or_else(default_max_memory);
    print!("{}", readi::inspect::memory_limit(&plan, threads_or_default(None), limit));
    Ok(())
}

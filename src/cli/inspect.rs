//! `readi inspect`: a plan described by [`readi::inspect::plan`].

use std::path::Path;
use std::process::ExitCode;

use super::load_plan;

pub fn run(plan_path: &Path, verbose: bool) -> Result<(), ExitCode> {
    let plan = load_plan(plan_path)?;
    print!("{}", readi::inspect::plan(&plan, plan_path, verbose));
    Ok(())
}

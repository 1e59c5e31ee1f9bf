//! `readi simulate`: the paper's conditions applied to an input, by [`readi::simulate`].

use std::process::ExitCode;

pub fn run(args: &readi::simulate::SimulateArgs) -> Result<(), ExitCode> {
    match readi::simulate::run(args) {
        Ok(summary) => {
            println!("{summary}");
            Ok(())
        }
        Err(e) => {
            eprintln!("error: {e}");
            Err(ExitCode::FAILURE)
        }
    }
}

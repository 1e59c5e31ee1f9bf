//! `readi`: the command-line front end of the readi compiler and runtime.

mod cli;

use std::io::IsTerminal;
use std::process::ExitCode;

use clap::Parser;
use cli::args::{Cli, ColorWhen, Command};
use cli::frontend::Frontend;
use readi_grammar::diag::SourceMap;

fn main() -> ExitCode {
    let cli = Cli::parse();
    // Printing to a closed pipe panics in `println!`; that is reported below, not as a crash.
    let default_hook = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if !panic_message(info.payload()).is_some_and(|m| m.contains("Broken pipe")) {
            default_hook(info);
        }
    }));
    // Elaboration recurses with the model's nesting; give it room whatever the platform's
    // main-thread stack is.
    let worker = std::thread::Builder::new().stack_size(64 << 20).spawn(move || run(cli));
    match worker.map(|h| h.join()) {
        Ok(Ok(code)) => code,
        // `readi ... | head`: the reader went away; stop quietly, as Unix tools do.
        Ok(Err(panic)) if panic_message(panic.as_ref()).is_some_and(|m| m.contains("Broken pipe")) => {
            ExitCode::from(141)
        }
        _ => {
            eprintln!("error: internal failure (please report this with the input file)");
            ExitCode::from(3)
        }
    }
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> Option<&str> {
    payload.downcast_ref::<String>().map(String::as_str).or_else(|| payload.downcast_ref::<&str>().copied())
}

/// Runs the command; its result is the exit status.
fn run(cli: Cli) -> ExitCode {
    let color = match cli.color {
        ColorWhen::Always => true,
        ColorWhen::Never => false,
        ColorWhen::Auto => std::io::stderr().is_terminal() && std::env::var_os("NO_COLOR").is_none(),
    };
    let mut s = Frontend::new(SourceMap::new(), color);
    let result = match cli.command {
        Command::Check { files, model, deny_warnings } => cli::check::run(&mut s, &files, &model, deny_warnings),
        Command::Ast { file, debug } => cli::ast::run(&mut s, &file, debug),
        Command::Ir { file, stop_after, model, backend } => cli::ir::run(&mut s, &file, &model, stop_after, &backend),
        Command::Graph { file, output, stop_after, model, backend } => {
            cli::ir::graph(&mut s, &file, output.as_deref(), &model, stop_after, &backend)
        }
        Command::Params { file, buffers, model } => cli::params::run(&mut s, &file, buffers, &model),
        Command::Passes => cli::ir::passes(),
        Command::Compile {
            spec,
            weights,
            deploy,
            variants,
            lora,
            memory_budget,
            switch_budget,
            variant_f16,
            explain,
            seeded_variants,
            strict,
            melds,
            output,
            allow_unused,
            strip_prefix,
            verbose,
            model,
        } => {
            let args = cli::compile::CompileArgs {
                spec,
                weights,
                deploy,
                variants,
                lora,
                memory_budget,
                switch_budget,
                variant_f16,
                explain,
                seeded_variants,
                strict,
                melds,
                allow_unused,
                strip_prefix,
                verbose,
                model,
            };
            cli::compile::run(&mut s, args, &output)
        }
        Command::Run { plan, inputs, outputs, threads, max_memory, no_spin, variant, auto, meta, drop_views } => {
            let choice = match variant {
                Some(v) => cli::run::Choice::Key(v),
                None if auto => cli::run::Choice::Auto(meta),
                None => cli::run::Choice::Base,
            };
            let session = cli::session_options(threads, max_memory).spin(!no_spin);
            cli::run::run(&plan, &inputs, &outputs, session, choice, &drop_views)
        }
        Command::Bench {
            plan,
            threads,
            runs,
            warmup,
            batch,
            profile,
            steps,
            peak,
            variant,
            inputs,
            switch,
            against,
            max_memory,
            no_spin,
        } => {
            let session = cli::session_options(threads, max_memory).spin(!no_spin);
            let timing = cli::bench::Timing { runs, warmup, batch, profile, steps, peak, switch, against };
            cli::bench::run(&plan, session, &timing, variant.as_deref(), &inputs)
        }
        Command::Inspect { plan, verbose, max_memory } => cli::inspect::run(&plan, verbose, max_memory),
        Command::Demo { model, threads, frames } => {
            cli::demo::run(&mut s, model, cli::threads_or_default(threads), frames)
        }
        Command::Simulate(args) => cli::simulate::run(&args),
        Command::AdaptBn { plan, variant, samples, output, threads, max_memory } => {
            cli::adapt_bn::run(&plan, &variant, &samples, &output, cli::session_options(threads, max_memory))
        }
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(code) => code,
    }
}

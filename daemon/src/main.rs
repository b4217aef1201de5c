//! The `periscope` binary: parse arguments, set up logging, run, map errors to an
//! exit code. Everything else lives in the `periscope_daemon` library.
use std::process::ExitCode;

use clap::Parser;
use periscope_daemon::{cli, logging};

fn main() -> ExitCode {
    // Before anything can panic: a panic switches every open laser off first.
    periscope_daemon::signals::install_panic_hook();
    let args = cli::Cli::parse();
    if let Err(err) = logging::init(args.log_format, args.log_file.as_deref()) {
        eprintln!("error: cannot open the log file: {err}");
        return ExitCode::from(2);
    }
    match cli::execute(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(err) => {
            logging::report_error(&cli::report(&err));
            err.exit_code()
        }
    }
}

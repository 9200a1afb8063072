//! `aimrt_main`: flags in, runtime run, exit code out (0 clean, 255 on any failure).
//! Its own lines never panic on a closed stdout or stderr (`aimrt_main … | head`).

use std::process::ExitCode;
use std::time::Duration;

use aimrt_runtime::{parse_args, say, say_err, usage, CliAction, Runtime, RuntimeOptions, VERSION};
use anyhow::Context;

fn main() -> ExitCode {
    // Before any thread starts (see its docs: an error recorded out of memory hangs).
    aimrt_runtime::no_library_backtraces();
    say(format_args!("AimRT start, version: {VERSION}"));
    match run() {
        Ok(()) => {
            say(format_args!("AimRT exit."));
            ExitCode::SUCCESS
        }
        Err(e) => {
            if let Some(detail) = e
                .downcast_ref::<aimrt_runtime::Error>()
                .and_then(|e| e.detail())
            {
                say_err(format_args!("{detail}"));
            }
            let mut line = e.to_string();
            // Errors that print their source already are not repeated.
            for cause in e.chain().skip(1) {
                let cause = cause.to_string();
                if !line.contains(&cause) {
                    line.push_str(": ");
                    line.push_str(&cause);
                }
            }
            say(format_args!(
                "AimRT run with exception and exit. {}",
                line.replace('\n', " ")
            ));
            ExitCode::from(255)
        }
    }
}

fn run() -> anyhow::Result<()> {
    let cli = match parse_args(std::env::args_os().skip(1)).context("bad command line")? {
        CliAction::Help => {
            say(format_args!("{}", usage().trim_end()));
            return Ok(());
        }
        CliAction::Version => {
            say(format_args!("AimRT Version: {VERSION}"));
            return Ok(());
        }
        CliAction::Run(cli) => cli,
    };
    // Many connections (net_plugin) need more than the usual soft limit of 1024 files.
    if let Err(e) = aimrt_runtime::raise_open_file_limit() {
        say_err(format_args!(
            "cannot raise the open-file limit: {e}; continuing with the current one"
        ));
    }
    let mut runtime = Runtime::new(RuntimeOptions {
        cfg_file_path: cli.cfg_file(),
        running_duration: (cli.running_duration != 0)
            .then(|| Duration::from_secs(u64::try_from(cli.running_duration).unwrap_or(0))),
        dump_cfg_file: cli.dump_cfg_file(),
        dump_init_report: cli.dump_init_report(),
        ..RuntimeOptions::default()
    });
    runtime.builtin_plugin(aimrt_std_executors::plugin());
    if cli.register_signal {
        let handle = runtime.shutdown_handle();
        aimrt_runtime::on_signals(move || handle.request())
            .context("cannot install the SIGINT/SIGTERM handlers")?;
    }
    runtime.run()?;
    Ok(())
}
